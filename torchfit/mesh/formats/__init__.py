"""The files a rigged animation comes in: the folder format, USD (UsdSkel) and glTF skins.

Every reader builds the same :class:`Animation` (:func:`read_animation` chooses by the
path); the joint trees DCCs write become the folder format's bones in :mod:`.joints`.
USD needs the extra ``usd`` (``pxr``), glTF the extra ``gltf`` (``pygltflib``); both are
imported only when such a file is read or written.
"""
from .folder import Animation, AnimationError, load_animation, write_animation, write_obj
from .readers import GLTF_SUFFIXES, USD_SUFFIXES, read_animation

__all__ = ["Animation", "AnimationError", "GLTF_SUFFIXES", "USD_SUFFIXES", "load_animation",
           "read_animation", "write_animation", "write_obj"]
