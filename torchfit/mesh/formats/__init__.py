"""The files a rigged animation comes in: the folder format, USD (UsdSkel) and glTF skins.

Every reader builds the same :class:`~torchfit.mesh.Animation` (:mod:`torchfit.mesh.animation`;
:func:`read_animation` chooses by the path); the joint trees DCCs write become the folder
format's bones in :mod:`.joints`. USD needs the extra ``usd`` (``pxr``), glTF the extra
``gltf`` (``pygltflib``); both are imported only when such a file is read or written, and
their subpackages (:mod:`.usd`, :mod:`.gltf`) are their faces.
"""
from .folder import check_replaceable, load_animation, write_animation, write_obj
from .readers import GLTF_SUFFIXES, USD_SUFFIXES, read_animation

__all__ = ["GLTF_SUFFIXES", "USD_SUFFIXES", "check_replaceable", "load_animation", "read_animation",
           "write_animation", "write_obj"]
