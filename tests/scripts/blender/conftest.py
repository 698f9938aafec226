"""The extension's package (scripts/blender/torchfit_blender) on the path, and a real short run
of a Blender limb that the results tests read (made once per session)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

EXTENSION_ROOT = Path(__file__).resolve().parents[3] / "scripts" / "blender"
if str(EXTENSION_ROOT) not in sys.path:
    sys.path.insert(0, str(EXTENSION_ROOT))


@pytest.fixture(scope="session")
def limb_rig(tmp_path_factory):
    """The limb of tests/helpers/blender_rigs.py exported by Blender's USD exporter (3 frames,
    the end bone bending 45 degrees): the path of its ``limb.usda``."""
    from helpers.blender_rigs import blender_available, run_blender

    if not blender_available():
        pytest.skip("needs Blender as a module (the extra blender)")
    folder = tmp_path_factory.mktemp("limb_rig")
    run_blender({"kind": "limb", "usd": "limb.usda", "frames": 3, "bend": 45.0}, folder)
    return folder / "limb.usda"


def fit_settings(**changes):
    """A small fit of the limb (file frames 0, 1 fitted; 2 held out; 2 iterations, 1 thread)."""
    from torchfit_blender.command import FitSettings

    return FitSettings(**{"frame_start": 1, "frame_end": 3, "held_out": (3,), "iterations": 2,
                          "tet_edge_length": 0.08, "threads": 1, **changes})


def start_fit(limb_rig, root, resume=False, **changes):
    """Start the small fit of ``limb_rig`` in the job folder ``root`` (the rig copied in as
    the panel's export would be): the :class:`~torchfit_blender.job.Job`."""
    import shutil
    import sys as _sys

    from torchfit_blender import job as jobs
    from torchfit_blender.command import JobFolder, fit_command

    folder = JobFolder(Path(root))
    folder.root.mkdir(parents=True, exist_ok=True)
    if not folder.rig.exists():
        shutil.copy(limb_rig, folder.rig)
    repo = EXTENSION_ROOT.parents[1]
    command = fit_command(fit_settings(**changes), folder, repo, _sys.executable, resume=resume)
    return jobs.start(command, repo, folder.run, folder.console)


@pytest.fixture(name="start_fit")
def start_fit_fixture():
    """:func:`start_fit`, for the tests (conftest is not importable by name here)."""
    return start_fit


@pytest.fixture(scope="session")
def finished_run(limb_rig, tmp_path_factory):
    """A finished small fit started through the extension's job module: its run directory."""
    job = start_fit(limb_rig, tmp_path_factory.mktemp("job"))
    status = job.wait(timeout=600)
    assert status == 0, job.console.read_text()[-3000:]
    return job.run
