"""``arm3d``: the seed's 3-D test, a tetrahedral arm with a two-bone rig (docs/problems.md).

The procedural arm of :mod:`torchfit.problems.body.procedural_arm` (upper arm 0.30 m, forearm
0.28 m, radius 0.05 to 0.035 m with a muscle profile; 48 frames: elbow bend to 120 degrees
with a bicep bulge, back, extension to -10 degrees with a tricep bulge, back) is written as
an animation folder in the user format (:mod:`torchfit.mesh.formats.folder`) and read back
through the same loader as ``problem=animation``: one path for procedural and user data.
The folder lives in the cache (``<cache>/animations/arm3d-<hash of the shape>``); every run
also copies it into its run directory (``animation/``), a worked example of the format.

Differences from ``animation``: regions are geometric (``bone`` within 0.4 of the local
radius from the bone axis, the attached core; ``muscle`` to 0.75; ``fat`` outside), the joint
region is the elbow (within 1.5 radii of it), frames are named by their elbow angle.

``rotate=[rx, ry, rz]`` (degrees about x, then y, then z) turns the whole animation (rest
surface, frames, skeleton) before it is written: ``[0, 90, 0]`` lays the arm along ``+x``,
``[-90, 0, 0]`` along ``+y`` (Y-up). The fit does not depend on it (the grid, the camera
and the reference frame follow the body: docs/notes/axes.md); regions and the elbow are
found in the arm's own frame.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from pathlib import Path
from typing import List

import numpy as np

from ...mesh import MeshError
from ...mesh import Animation, default_cache_dir, load_animation, write_animation
from .procedural_arm import (MAX_EXTENSION, MAX_FLEXION, REGION_NAMES, ArmShape,
                             arm_animation, arm_surface,
                             correctives, elbow_angles, elbow_region, region_labels)
from ..config import ProblemConfigError, require_setting

#: the longest segment accepted, in radii of the arm's thinner end
MAX_SLENDERNESS = 1000.0
from .problem import RiggedBody
from .config import RiggedBodyConfig


log = logging.getLogger(__name__)

@dataclasses.dataclass
class Arm3DConfig(RiggedBodyConfig):
    """Settings of ``problem=arm3d``: the arm's shape and animation, then everything of
    ``problem=animation`` (``path`` is not used: the arm writes its own animation; ``frames``
    are numbers among the 48, e.g. ``[0, 3, 6, 9, 11]``; the regions of ``E_regions`` are
    bone, muscle, fat)."""

    name: str = "arm3d"
    upper: float = 0.30                # upper-arm length (m)
    fore: float = 0.28                 # forearm length (m)
    r_shoulder: float = 0.05           # radius at the shoulder (m)
    r_wrist: float = 0.035             # radius at the wrist (m)
    n_frames: int = 48                 # frames of the whole animation (4 phases)
    max_flexion: float = 120.0         # degrees
    max_extension: float = 10.0        # degrees
    bicep_bulge: float = 0.012         # peak corrective displacement at full flexion (m)
    tricep_bulge: float = 0.006        # at full extension (m)
    tet_edge_length: float = 0.028     # fraction of the bounding-box diagonal: ~10k tetrahedra
    # noise as a fraction of the mean bulge displacement (0.01: 1 %); sets problem.noise
    noise_of_bulge: float = 0.0
    # degrees about x, then y, then z (fixed axes) applied to the whole animation: [0, 90, 0]
    # lays the arm along +x, [-90, 0, 0] along +y (Y-up); the fit is the same
    rotate: List[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])


class Arm3D(RiggedBody):
    """The procedural arm, fitted through the animation path."""

    config_class = Arm3DConfig
    name = "arm3d"
    writes_animation = True
    joint_label = "elbow"
    fold_docs = "docs/notes/arm3d.md, 'Several equilibria near full bend'"

    def check_source(self, cfg: Arm3DConfig) -> None:
        require_setting(not cfg.path, cfg, "path", "is not used by arm3d (it writes its own "
                        "animation); use problem=animation problem.path=<folder> for yours")
        require_setting(cfg.n_frames >= 1, cfg, "n_frames", "must be >= 1")
        for key in ("upper", "fore", "r_shoulder", "r_wrist"):
            require_setting(getattr(cfg, key) > 0, cfg, key, "must be positive (metres)")
        require_setting(0 < cfg.max_flexion <= MAX_FLEXION, cfg, "max_flexion",
                        f"must lie in (0, {MAX_FLEXION:g}] degrees (the elbow's bend at the "
                        "animation's peak; beyond it the forearm runs into the upper arm)")
        require_setting(0 <= cfg.max_extension < MAX_EXTENSION, cfg, "max_extension",
                        f"must lie in [0, {MAX_EXTENSION:g}) degrees (past straight)")
        require_setting(cfg.noise_of_bulge >= 0, cfg, "noise_of_bulge", "must be >= 0")
        # a tube the tetrahedralisation can enclose: radii below half the shorter segment,
        # segments below a thousand radii (thinner, the envelope flattens it), bulges within
        # the wrist's radius (a corrective shape, not a new limb)
        shorter, thinner = min(cfg.upper, cfg.fore), min(cfg.r_shoulder, cfg.r_wrist)
        for key in ("r_shoulder", "r_wrist"):
            require_setting(getattr(cfg, key) <= 0.5 * shorter, cfg, key, "must be at most half "
                            f"the shorter segment ({shorter:g} m: problem.upper, problem.fore)")
        for key in ("upper", "fore"):
            require_setting(getattr(cfg, key) <= MAX_SLENDERNESS * thinner, cfg, key,
                            f"must be at most {MAX_SLENDERNESS:g} times the thinner radius "
                            f"({thinner:g} m: problem.r_shoulder, problem.r_wrist)")
        for key in ("bicep_bulge", "tricep_bulge"):
            require_setting(abs(getattr(cfg, key)) <= cfg.r_wrist, cfg, key, "must be at most "
                            f"the wrist's radius in size ({cfg.r_wrist:g} m: problem.r_wrist; "
                            "a corrective displacement, metres)")
        require_setting(len(cfg.rotate) == 3 and all(np.isfinite(cfg.rotate)), cfg, "rotate",
                        "must list three angles in degrees (about x, y, z), e.g. [0, 90, 0]")
        self.rotation = rotation_matrix(cfg.rotate)
        if cfg.noise_of_bulge > 0:
            require_setting(cfg.noise == 0, cfg, "noise", "give either problem.noise (metres) or "
                            "problem.noise_of_bulge (a fraction of the mean bulge), not both")
            cfg.noise = cfg.noise_of_bulge * mean_bulge_displacement(self.shape(cfg))

    def allocation(self, cfg: Arm3DConfig) -> list[tuple[str, float, str]]:
        # the written animation: every frame's surface, and its skinned copy, in float64
        vertices = ArmShape.n_around * ArmShape.n_along
        return [*super().allocation(cfg),
                (f"problem.n_frames={cfg.n_frames}", cfg.n_frames * vertices * 3 * 8 * 2.0,
                 f"{cfg.n_frames} frames of the arm's {vertices} surface vertices")]

    def shape(self, cfg: Arm3DConfig) -> ArmShape:
        return ArmShape(upper=cfg.upper, fore=cfg.fore, r_shoulder=cfg.r_shoulder,
                        r_wrist=cfg.r_wrist, n_frames=cfg.n_frames, max_flexion=cfg.max_flexion,
                        max_extension=cfg.max_extension, bicep_bulge=cfg.bicep_bulge,
                        tricep_bulge=cfg.tricep_bulge)

    def load(self, cfg: Arm3DConfig) -> Animation:
        self.arm = self.shape(cfg)
        spec = dataclasses.asdict(self.arm)
        if any(float(a) != 0.0 for a in cfg.rotate):
            spec["rotate"] = [float(a) for a in cfg.rotate]
        key = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
        root = Path(cfg.cache_dir).expanduser() if cfg.cache_dir else default_cache_dir().parent
        folder = root / "animations" / f"arm3d-{key}"
        if not (folder / "animation.yaml").is_file():
            self.write_arm(folder)
        self.elbow_angles = elbow_angles(self.arm)
        try:
            return load_animation(folder)
        except Exception as err:  # noqa: BLE001 - derived data: an unreadable copy is rebuilt
            log.warning(f"arm3d animation cache {folder} is unreadable ({type(err).__name__}: "
                        f"{' '.join(str(err).split())}); rebuilding it")
        self.write_arm(folder)
        try:
            return load_animation(folder)
        except MeshError as err:
            raise ProblemConfigError(f"arm3d animation in {folder}: {err}") from err

    def write_arm(self, folder: Path) -> None:
        data = rotated(arm_animation(self.arm), self.rotation)
        write_animation(folder, data["rest_vertices"], data["faces"], data["frames"],
                        skeleton=data["skeleton"],
                        description="procedural arm of torchfit's arm3d problem "
                                    "(docs/problems.md): two bones, 48 frames, elbow bend with "
                                    "bicep bulge, extension with tricep bulge")

    def regions(self, cfg: Arm3DConfig) -> tuple[np.ndarray, list[str]]:
        return region_labels(self.arm, self.arm_points()), list(REGION_NAMES)

    def joint_region(self, cfg: Arm3DConfig) -> np.ndarray:
        return np.flatnonzero(elbow_region(self.arm, self.arm_points()))

    def arm_points(self) -> np.ndarray:
        """The tetrahedra's centroids ``(n_tets, 3)`` in the arm's own frame (``rotate`` undone)."""
        return self.mesh.centroids() @ self.rotation

    def reference_frame(self) -> int:
        angles = self.frame_angles()
        return int(np.argmax(angles))

    def frame_angles(self) -> np.ndarray:
        """Elbow angle (degrees) of every fitted frame."""
        return np.asarray([self.elbow_angles[f] for f in self.frame_numbers()])

    def frame_names(self) -> list[str]:
        return [f"frame {f}: elbow {a:+.0f} deg"
                for f, a in zip(self.frame_numbers(), self.frame_angles())]

    def settings_for_frames(self, numbers: list[int]) -> Arm3DConfig:
        # with noise_of_bulge, check() derived cfg.noise from it: give it back at 0, or the
        # rebuilt config would hold both (its data are replaced by this problem's anyway)
        cfg = super().settings_for_frames(numbers)
        return dataclasses.replace(cfg, noise=0.0) if self.cfg.noise_of_bulge > 0 else cfg

    def describe(self) -> dict:
        out = super().describe()
        out.update({"elbow_angle_full_bend": float(self.frame_angles()[self.full_bend_frame]),
                    "mean_bulge_displacement": mean_bulge_displacement(self.arm)})
        return out


def mean_bulge_displacement(shape: ArmShape) -> float:
    """Mean length (m) of the corrective (bulge) displacement over every frame and every
    surface vertex the bulges move: the scale of the signal a material fit explains."""
    rest, _ = arm_surface(shape)
    bulge = np.linalg.norm(correctives(shape, rest, elbow_angles(shape)), axis=-1)   # (F, V)
    moved = bulge.max(axis=0) > 0
    return float(bulge[:, moved].mean()) if moved.any() else 0.0


def rotation_matrix(degrees) -> np.ndarray:
    """``(3, 3)`` rotation by ``degrees[0]`` about x, then ``[1]`` about y, then ``[2]``
    about z (fixed axes)."""
    out = np.eye(3)
    for axis, angle in enumerate(np.radians(np.asarray(degrees, dtype=np.float64))):
        c, s = np.cos(angle), np.sin(angle)
        i, j = [k for k in range(3) if k != axis]
        turn = np.eye(3)
        turn[i, i], turn[i, j], turn[j, i], turn[j, j] = c, -s, s, c
        if axis == 1:       # about y: z -> x is positive
            turn = turn.T
        out = turn @ out
    return out


def rotated(data: dict, rotation: np.ndarray) -> dict:
    """The arm's animation (:func:`~torchfit.problems.body.procedural_arm.arm_animation`) turned by
    ``rotation`` ``(3, 3)``: points ``R p``, bone transforms ``[R A R^T | R t]``."""
    if np.array_equal(rotation, np.eye(3)):
        return data
    skeleton = data["skeleton"]
    transforms = skeleton.transforms.copy()
    transforms[..., :3] = rotation @ skeleton.transforms[..., :3] @ rotation.T
    transforms[..., 3] = skeleton.transforms[..., 3] @ rotation.T
    return {**data, "rest_vertices": data["rest_vertices"] @ rotation.T,
            "frames": data["frames"] @ rotation.T, "bulge": data["bulge"] @ rotation.T,
            "skeleton": dataclasses.replace(skeleton, heads=skeleton.heads @ rotation.T,
                                            tails=skeleton.tails @ rotation.T,
                                            transforms=transforms)}
