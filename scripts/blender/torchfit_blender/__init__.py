"""The torchfit Blender extension: fit, look, paint and simulate from Blender's sidebar.

Blender 4.2+ extension (``blender_manifest.toml``, id ``torchfit``). The modules
:mod:`.command`, :mod:`.job` and :mod:`.results` are plain Python (no ``bpy``, no torch:
tested with pytest); :mod:`.ui` holds the Blender side (preferences, the panel, operators)
and is imported by :func:`register` only, so the plain modules import outside Blender.
torchfit itself runs as a separate process (its command line and run files), so Blender's
Python needs no torch (docs/guide/blender.md).
"""
from __future__ import annotations


def register() -> None:
    """Register the preferences, properties, operators and panel (Blender calls this)."""
    from . import ui

    ui.register()


def unregister() -> None:
    """Undo :func:`register`."""
    from . import ui

    ui.unregister()
