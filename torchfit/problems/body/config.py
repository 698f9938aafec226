"""Settings of ``problem=animation`` (``arm3d`` extends them): choices, RiggedBodyConfig.

Lengths in metres, ``noise`` too.
"""
from __future__ import annotations

import dataclasses
from typing import List, Optional

from ...settings import Choice
from ..config import Backend, ProblemConfig
from ..dynamic import Integrator, Scheme


class ElasticModel(Choice):
    """Constitutive model of the body."""

    linear = "linear"
    corotated = "corotated"
    stable_neo_hookean = "stable_neo_hookean"


class Target(Choice):
    """``rig``: the animated surface; ``synthetic``: simulated from a known field."""

    rig = "rig"
    synthetic = "synthetic"


class Truth(Choice):
    """The known field of ``target=synthetic``."""

    regions = "regions"     # one value per region (E_regions)
    blocks = "blocks"       # blocks of grid nodes (E_blocks), trilinear between nodes


class ModulusUnit(Choice):
    """What ``problem.E0`` is, hence the unit of every modulus a body writes."""

    # a reference: rig targets (prescribed motion only) do not fix the modulus' scale, so
    # the outputs write the field divided by E0 (1 = the homogeneous start)
    relative = "relative"
    # a Young's modulus in pascals (e.g. 3e4 for soft tissue): the outputs write pascals
    Pa = "Pa"


class Layout(Choice):
    """Where the fitted parameters live."""

    grid = "grid"           # nodes of a coarse regular grid, trilinear to tetrahedra
    region = "region"       # one per region label
    tet = "tet"             # one per tetrahedron


@dataclasses.dataclass
class RiggedBodyConfig(ProblemConfig):
    """Settings of ``problem=animation`` (lengths in metres; ``noise`` in metres too)."""

    name: str = "animation"
    path: str = ""                         # folder holding animation.yaml, or .usd/.usda/.usdc/
    #                                        .usdz (extra usd), or .glb/.gltf (extra gltf)
    prim: str = ""                         # USD: the mesh's prim path; glTF: the skinned node's
    #                                        name; "": the one skinned mesh (else point cache)
    fps: float = 0.0                       # glTF: sample the animation at this rate; 0: at its
    #                                        keyframes (every input time of its samplers)
    frames: Optional[List[int]] = None     # a subset of the frames (numbers); null: all
    # a USD layer with primvars:youngsModulus per vertex of this mesh or per tetrahedron (one
    # an artist painted, or a run's usd/material.usda or usd/body.usda): the fit's starting
    # field, projected on the parameters by least squares (docs/guide/dcc.md); "": E0
    init_field: str = ""
    # validation (problems/body/held_out.py, docs/notes/validation.md): frames (numbers) held out of
    # the fit and simulated at every recorded iteration, or every k-th distinct pose (0: none);
    # frames repeating a validation pose (within this fraction of the diagonal) leave the fit
    validation_frames: Optional[List[int]] = None
    validation_every: int = 0
    validation_repeat_tol: float = 1e-6
    model: ElasticModel = ElasticModel.corotated   # linear | corotated | stable_neo_hookean
    nu: float = 0.45                       # Poisson ratio, fixed
    # rig (the animated surface) | synthetic (simulated from a known field)
    target: Target = Target.rig
    truth: Truth = Truth.blocks            # synthetic only: blocks | regions (needs labels)
    # truth=regions: one modulus per label (arm: bone, muscle, fat; the bone core is attached to
    # the rig, so its modulus is unobservable: it gets the muscle's value by default)
    E_regions: List[float] = dataclasses.field(default_factory=lambda: [4.0, 4.0, 1.0])
    # truth=blocks: background, stiff block, soft block
    E_blocks: List[float] = dataclasses.field(default_factory=lambda: [1.0, 4.0, 0.4])
    # grid (coarse nodes, trilinear) | region (one per label; needs labels) | tet
    parameters: Layout = Layout.grid
    # parameters=grid (and the blocks truth): a node grid along the body's principal axes
    # a0, a1, a2 (increasing extent, the longest last; torchfit/problems/body/grid.py), with
    # about grid_nodes nodes in all, counts proportional to the extents (at least 4 per axis:
    # the arm gets 4 x 4 x 12); grid=[n0, n1, n2] gives the counts along a0, a1, a2 instead
    grid_nodes: int = 192
    grid: Optional[List[int]] = None
    E0: float = 1.0                        # initial guess, constant (the homogeneous material)
    E0_unit: ModulusUnit = ModulusUnit.relative  # Pa: E0 is a modulus in pascals (outputs in Pa)
    # bounds on the fitted modulus, kept by the solver's steps (problems/body/bounds.py;
    # the defaults and why: docs/notes/bounds.md). null: on for target=rig, off for synthetic
    bounds: Optional[bool] = None
    E_min: float = 0.01                    # lowest modulus: a factor of E0 (E_bounds_relative)
    E_max: float = 100.0                   # highest modulus: a factor of E0 (E_bounds_relative)
    E_bounds_relative: bool = True         # false: E_min, E_max are moduli (units of E0)
    # auto (pardiso where installed, else scipy) | pardiso | scipy | cg
    backend: Backend = Backend.auto
    # tetrahedralisation (pytetwild): target edge length as a fraction of the bounding-box
    # diagonal, envelope (fraction of the diagonal), quality (stop energy), optimisation
    tet_edge_length: float = 0.05
    tet_epsilon: float = 1e-3
    # a target number of tetrahedra instead (null: the two above): the edge length from the
    # body's volume and the envelope matched to it (on a finely tessellated surface the count
    # follows tet_epsilon more than tet_edge_length); torchfit/mesh/tetwild/size.py
    tet_count: Optional[int] = None
    tet_stop_energy: float = 10.0
    tet_optimize: bool = True
    # before anything is built: every frame at the rest's scale (not 10x off), and, where the
    # manifest gives skinning weights, the rest skinned with them reproduces the frames: the
    # median distance per frame and bone at most rig_tolerance (a fraction of the rest's
    # bounding-box diagonal); torchfit/mesh/rig_check.py
    rig_check: bool = True
    # repeat the fit on a second tetrahedralisation of the same surface (the edge length
    # x0.9, a fresh mesh) and report per region how far the fitted moduli move: the spread
    # the mesh causes (regions.json, the summary); costs a second fit; torchfit/run/uncertainty.py
    mesh_check: bool = False
    rig_tolerance: float = 0.05
    # tet meshes (and the arm's animation): "" is $TORCHFIT_CACHE_DIR or ~/.cache/torchfit
    cache_dir: str = ""
    # self-contact of the body's surface (IPC, ipctk; torchfit/physics/contact, docs/guide/
    # contact.md): off until its price on the arm is measured (docs/notes/contact.md);
    # contact_dhat: the barrier's reach, a fraction of the rest bounding box's diagonal
    contact: bool = False
    contact_dhat: float = 1e-3
    newton_rtol: float = 1e-10
    newton_atol: float = 1e-12
    newton_max_iter: int = 300
    # Newton's start at a new parameter vector: an earlier solution (true; the solver's current
    # point where it is known) or the animated pose (false, the definition in docs/problems.md;
    # when it matters: docs/notes/arm3d.md#noticed-left-alone, several equilibria near full bend)
    warm_start: bool = True
    # -- problem.dynamic=true (problems/body/dynamic.py, docs/guide/dynamics.md): the rig drives
    # its tetrahedron vertices through time (the frames at the animation's fps, a natural cubic
    # spline between them), the rest integrates M a = f_int(x; E) - C v; E in Pa, fitted with
    # the Rayleigh damping C = alpha M + beta K0 --
    dynamic: bool = False
    integrator: Integrator = Integrator.implicit   # implicit only (the body is stiff)
    scheme: Scheme = Scheme.bdf2           # bdf2 | backward_euler
    substeps: int = 4                      # implicit steps per frame (dt = 1 / (fps substeps))
    density: float = 1000.0                # kg/m^3 (soft tissue); lumped mass per vertex
    # fit a density scale s too (the mass s M; theta's last entry, starting at 1): the motion
    # sees E / rho only (the weight too scales with s), so beside a free modulus scale it is
    # one direction with it; it tells the density where the moduli's scale is held
    fit_density: bool = False
    density_scale: float = 1.0             # the true density scale s, target=synthetic
    # gravity (m/s^2) in the animation's axes: [0, 0, -9.81] for a Z-up file, [0, -9.81, 0]
    # for a Y-up one (glTF); null: none (the animated shapes already show the body as it
    # hangs); the body starts at frame 0 in equilibrium under it for E0
    gravity: Optional[List[float]] = None
    # with E0_unit=relative the moduli (E0, E_blocks, E_regions, E_min/E_max when absolute)
    # are factors of this modulus in pascals (soft tissue); with E0_unit=Pa they are pascals
    E_reference: float = 1.0e4
    alpha: float = 2.0                     # true mass damping (1/s), target=synthetic
    beta: float = 0.004                    # true stiffness damping (s), target=synthetic
    alpha0: float = 1.0                    # initial guess of alpha
    beta0: float = 0.008                   # initial guess of beta
    # 1 keeps every step's state and factor; c > 1 every c-th state (the rest recomputed);
    # 0: ceil(sqrt(steps))
    checkpoint_every: int = 1
