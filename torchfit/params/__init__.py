"""Parameterisations of physical fields (map, difference operator, scale direction)."""
from .parameterization import (FieldAndScalars, Parameterization, chain_edges, grid_edges,
                               grid_groups, per_element, per_grid_cell, per_grid_node,
                               per_region)

__all__ = ["FieldAndScalars", "Parameterization", "chain_edges", "grid_edges", "grid_groups",
           "per_element", "per_grid_cell", "per_grid_node", "per_region"]
