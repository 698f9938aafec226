"""USD stages (the extra ``usd``: Pixar's ``pxr``): reading UsdSkel rigs and point caches,
writing rigs, simulated frames and tetrahedral meshes.

Reading (:mod:`.reader`), writing (:mod:`.writer`) and a modulus layer on the user's mesh
(:mod:`.material`); ``pxr`` is imported only when a stage is read or written.
"""
from .material import ModulusLayer, layer_cell_values, read_damping, read_modulus_layer
from .reader import load_usd
from .writer import (write_point_cache_usd, write_skinned_usd, write_tet_mesh_usd,
                     write_vertex_field_usd)

__all__ = ["ModulusLayer", "layer_cell_values", "load_usd", "read_damping", "read_modulus_layer",
           "write_point_cache_usd", "write_skinned_usd", "write_tet_mesh_usd",
           "write_vertex_field_usd"]
