"""Parameterisations of physical fields (map, difference operator, scale direction)."""
from .parameterization import (TRANSFORMS, Parameterization, chain_edges, grid_edges,
                               grid_groups, per_element, per_grid_cell, per_region)

__all__ = ["TRANSFORMS", "Parameterization", "chain_edges", "grid_edges", "grid_groups",
           "per_element", "per_grid_cell", "per_region"]
