"""Parameterisations of physical fields (map, difference operator, scale direction)."""
from .parameterization import (TRANSFORMS, Parameterization, chain_edges, grid_edges,
                               per_element, per_region)

__all__ = ["TRANSFORMS", "Parameterization", "chain_edges", "grid_edges", "per_element",
           "per_region"]
