"""Simplicial finite-element elasticity (triangles in plane strain, tetrahedra).

* :mod:`.kinematics`: rest shapes, deformation gradients, the polar rotation with a safe
  derivative;
* :mod:`.materials`: ``linear``, ``corotated`` (PhysBAM's rotated linear) and
  ``stable_neo_hookean`` (Smith, de Goes and Kim 2018), parameterised by ``E`` and ``nu``;
* :mod:`.fem`: energy, forces and sparse tangent of a mesh (an ``EquilibriumModel``);
* :mod:`.quasistatic`: frames of quasistatic equilibrium with prescribed vertices.
"""
from .fem import ElasticParamDerivative, SimplicialElasticity
from .kinematics import PolarRotation3, RestShape, polar_rotation, rotation_differential
from .materials import (ALIASES, MATERIALS, Corotated, InvalidModulusError, LinearElastic,
                        Material, MaterialError,
                        StableNeoHookean, check_poisson_ratio, get_material, lame_parameters,
                        project_psd)
from .quasistatic import DirichletDataError, QuasistaticElasticity

__all__ = ["ALIASES", "Corotated", "DirichletDataError", "ElasticParamDerivative",
           "InvalidModulusError",
           "LinearElastic", "MATERIALS", "Material", "MaterialError", "PolarRotation3",
           "QuasistaticElasticity", "RestShape", "SimplicialElasticity", "StableNeoHookean",
           "check_poisson_ratio", "get_material", "lame_parameters", "polar_rotation",
           "project_psd", "rotation_differential"]
