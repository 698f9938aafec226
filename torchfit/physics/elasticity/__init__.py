"""Simplicial finite-element elasticity (triangles in plane strain, tetrahedra).

* :mod:`.kinematics`: rest shapes, deformation gradients, the polar rotation with a safe
  derivative;
* :mod:`.materials`: ``linear``, ``corotated`` (PhysBAM's rotated linear) and
  ``stable_neo_hookean`` (Smith, de Goes and Kim 2018), parameterised by ``E`` and ``nu``;
* :mod:`.fem`: energy, forces and sparse tangent of a mesh (an ``EquilibriumModel``);
* :mod:`.quasistatic`: frames of quasistatic equilibrium with prescribed vertices.
"""
from .fem import SimplicialElasticity
from .materials import (ALIASES, MATERIALS, InvalidModulusError, Material, MaterialError,
                        get_material)
from .quasistatic import DirichletDataError, QuasistaticElasticity

__all__ = ["ALIASES", "DirichletDataError", "InvalidModulusError", "MATERIALS", "Material",
           "MaterialError", "QuasistaticElasticity", "SimplicialElasticity", "get_material"]
