"""Parameterisations of physical fields (map, difference operator, scale direction)."""
from .parameterization import (TRANSFORMS, FieldAndScalars, Parameterization, chain_edges,
                               grid_edges,
                               grid_groups, grid_node_positions, per_element, per_grid_cell,
                               per_grid_node, per_region)

__all__ = ["FieldAndScalars", "TRANSFORMS", "Parameterization", "chain_edges", "grid_edges", "grid_groups",
           "grid_node_positions", "per_element", "per_grid_cell", "per_grid_node",
           "per_region"]
