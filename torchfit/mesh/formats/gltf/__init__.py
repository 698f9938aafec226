"""glTF 2.0 (the extra ``gltf``: ``pygltflib``): reading skins with their animation, and
writing a rigged animation as one.

Reading (:mod:`.reader`) and writing (:mod:`.writer`); ``pygltflib`` is imported only when a
file is read or written.
"""
from .reader import load_gltf
from .writer import write_skinned_gltf

__all__ = ["load_gltf", "write_skinned_gltf"]
