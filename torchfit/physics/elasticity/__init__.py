"""Simplicial finite-element elasticity (triangles in plane strain, tetrahedra).

* :mod:`.kinematics`: rest shapes, deformation gradients, the polar rotation with a safe
  derivative;
* :mod:`.material_base`: the constitutive-model contract and its tensor algebra;
  :mod:`.materials`: ``linear``, ``corotated`` (PhysBAM's rotated linear) and the registry;
  :mod:`.stable_neo_hookean` (Smith, de Goes and Kim 2018); all parameterised by ``E``, ``nu``;
* :mod:`.fem`: energy, forces and sparse tangent of a mesh (an ``EquilibriumModel``);
* :mod:`.quasistatic`: frames of quasistatic equilibrium with prescribed vertices.
"""
from .fem import SimplicialElasticity
from .material_base import InvalidModulusError, Material, MaterialError
from .materials import ALIASES, MATERIALS, get_material
from .quasistatic import DirichletDataError, QuasistaticElasticity

__all__ = ["ALIASES", "DirichletDataError", "InvalidModulusError", "MATERIALS", "Material",
           "MaterialError", "QuasistaticElasticity", "SimplicialElasticity", "get_material"]
