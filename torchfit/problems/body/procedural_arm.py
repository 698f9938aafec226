"""The procedural arm of docs/problems.md (``arm3d``): surface, two-bone rig, 48-frame animation.

Geometry (metres): the arm lies along ``+z`` with the shoulder at the origin; the upper
arm is ``0 <= z <= upper`` (0.30), the forearm ``upper <= z <= upper + fore`` (0.28). The
radius tapers linearly from ``r_shoulder`` (0.05) to ``r_wrist`` (0.035), plus a muscle
profile on the upper arm (a smooth bump of ``muscle`` (0.006) centred at 60 % of its
length). The surface is a closed tube: ``n_around`` vertices on each of ``n_along`` rings
and one pole at each end (watertight, outward normals), built as a
:class:`trimesh.Trimesh`.

Rig: bone 0 (upper arm) from the shoulder to the elbow, bone 1 (forearm) from the elbow to
the wrist. The elbow bends about the ``y`` axis: a positive angle flexes the forearm towards
``+x`` (the front of the arm). Skinning weights come from the distance to the bones
(:func:`.rig.distance_weights`, reach ``1.5 r_shoulder``) and are written with the
animation; interior material within ``attach_ratio * r`` (0.4 r) of a bone follows it.

Animation (48 frames): frames 0-11 bend the elbow from 0 to 120 degrees, 12-23 return to
straight, 24-35 extend it to -10 degrees, 36-47 return. Correctives: a bicep bulge (radial
displacement of the front of the upper arm, growing with the flexion angle, up to
``bicep_bulge`` = 0.012) and a tricep bulge (the back of the upper arm, growing with the
extension, up to ``tricep_bulge`` = 0.006), both applied in the rest pose before skinning.

Regions (for the ``regions`` truth): ``bone`` within ``bone_ratio`` (0.4) of the local radius
from the bone axis (the attached core), ``muscle`` up to ``muscle_ratio`` (0.75), ``fat``
outside. Nothing here solves anything (docs/architecture.md, layer ``mesh``).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...mesh import Skeleton, axial_coordinates, blend, distance_weights, segment_distances

REGION_NAMES = ("bone", "muscle", "fat")
#: the largest elbow flexion the procedural arm animates (degrees): beyond it the forearm's
#: surface runs into the upper arm's
MAX_FLEXION = 150.0
#: the largest extension past straight (degrees)
MAX_EXTENSION = 90.0


@dataclasses.dataclass(frozen=True)
class ArmShape:
    """Dimensions (metres), tessellation and animation of the procedural arm."""

    upper: float = 0.30
    fore: float = 0.28
    r_shoulder: float = 0.05
    r_wrist: float = 0.035
    muscle: float = 0.006
    n_around: int = 32
    n_along: int = 60
    n_frames: int = 48
    max_flexion: float = 120.0     # degrees
    max_extension: float = 10.0    # degrees
    bicep_bulge: float = 0.012
    tricep_bulge: float = 0.006
    attach_ratio: float = 0.4
    bone_ratio: float = 0.4
    muscle_ratio: float = 0.75

    @property
    def length(self) -> float:
        return self.upper + self.fore

    def check(self) -> None:
        for key in ("upper", "fore", "r_shoulder", "r_wrist", "attach_ratio"):
            if not getattr(self, key) > 0:
                raise ValueError(f"arm.{key} must be positive, got {getattr(self, key)}")
        if self.n_around < 6 or self.n_along < 6:
            raise ValueError("the arm needs n_around >= 6 and n_along >= 6")
        if self.n_frames < 1:
            raise ValueError("the arm needs at least one frame")
        if not (0 < self.max_flexion <= MAX_FLEXION and 0 <= self.max_extension < MAX_EXTENSION):
            raise ValueError(f"the arm bends by max_flexion in (0, {MAX_FLEXION:g}] and "
                             f"max_extension in [0, {MAX_EXTENSION:g}) degrees")
        if not 0 < self.bone_ratio < self.muscle_ratio < 1:
            raise ValueError("need 0 < bone_ratio < muscle_ratio < 1")


def base_radius(shape: ArmShape, z: np.ndarray) -> np.ndarray:
    """Radius of the tube at height ``z`` without the muscle, ``z`` clipped to the arm."""
    t = np.clip(np.asarray(z, dtype=np.float64) / shape.length, 0.0, 1.0)
    return shape.r_shoulder + (shape.r_wrist - shape.r_shoulder) * t


def _bump(u: np.ndarray) -> np.ndarray:
    """Smooth bump on ``[0, 1]`` (``sin^2``), zero outside."""
    u = np.asarray(u, dtype=np.float64)
    return np.where((u > 0) & (u < 1), np.sin(math.pi * np.clip(u, 0, 1)) ** 2, 0.0)


def muscle_profile(shape: ArmShape, z: np.ndarray) -> np.ndarray:
    """Extra radius of the upper-arm muscle at height ``z`` (peak at 60 % of the upper arm)."""
    return shape.muscle * _bump((np.asarray(z) - 0.2 * shape.upper) / (0.8 * shape.upper))


def radius(shape: ArmShape, z: np.ndarray) -> np.ndarray:
    """Rest radius of the arm at height ``z`` (taper plus muscle)."""
    return base_radius(shape, z) + muscle_profile(shape, z)


def arm_surface(shape: ArmShape = ArmShape()) -> tuple[np.ndarray, np.ndarray]:
    """Closed arm surface: vertices ``(V, 3)`` and outward faces ``(T, 3)``.

    Rings are spaced more densely near the ends (cosine spacing) so that the rounded caps
    (radius shrinking as a quarter circle over the last ``r`` of length) are resolved.
    """
    shape.check()
    n, m = shape.n_around, shape.n_along
    L = shape.length
    cap0, cap1 = shape.r_shoulder, shape.r_wrist
    # heights of the rings: inside [0, L], caps rounded over their radius
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, math.pi, m + 2)[1:-1])
    z = s * L
    r = radius(shape, z)
    near0 = z < cap0
    r = np.where(near0, r * np.sqrt(np.clip(1 - ((cap0 - z) / cap0) ** 2, 0, 1)), r)
    near1 = z > L - cap1
    r = np.where(near1, r * np.sqrt(np.clip(1 - ((z - (L - cap1)) / cap1) ** 2, 0, 1)), r)
    phi = 2 * math.pi * np.arange(n) / n
    ring = np.stack([np.cos(phi), np.sin(phi)], axis=1)                   # (n, 2)
    body = np.concatenate([r[:, None, None] * ring[None], np.broadcast_to(
        z[:, None, None], (m, n, 1))], axis=2).reshape(-1, 3)
    vertices = np.concatenate([[[0.0, 0.0, 0.0]], body, [[0.0, 0.0, L]]])
    faces = []
    idx = 1 + np.arange(m * n).reshape(m, n)
    nxt = np.roll(idx, -1, axis=1)
    # side quads, outward: (i, j) -> (i, j+1) -> (i+1, j+1) counter-clockwise seen from outside
    a, b, c, d = idx[:-1], nxt[:-1], nxt[1:], idx[1:]
    faces.append(np.stack([a, b, c], axis=-1).reshape(-1, 3))
    faces.append(np.stack([a, c, d], axis=-1).reshape(-1, 3))
    # caps: bottom pole 0 (normal -z), top pole last (normal +z)
    faces.append(np.stack([np.zeros(n, dtype=np.int64), nxt[0], idx[0]], axis=1))
    top = len(vertices) - 1
    faces.append(np.stack([np.full(n, top), idx[-1], nxt[-1]], axis=1))
    return vertices, np.concatenate(faces).astype(np.int64)


def elbow_angles(shape: ArmShape = ArmShape()) -> np.ndarray:
    """Elbow angle in degrees per frame ``(n_frames,)`` (positive: flexion)."""
    n = shape.n_frames
    quarter = n / 4.0
    out = np.empty(n)
    for f in range(n):
        phase, k = divmod(f, max(int(round(quarter)), 1))
        u = k / max(int(round(quarter)) - 1, 1)
        if phase == 0:
            out[f] = shape.max_flexion * u
        elif phase == 1:
            out[f] = shape.max_flexion * (1 - u)
        elif phase == 2:
            out[f] = -shape.max_extension * u
        else:
            out[f] = -shape.max_extension * (1 - u)
    return out


def rig(shape: ArmShape = ArmShape()) -> tuple[np.ndarray, np.ndarray]:
    """Rest bones: heads and tails ``(2, 3)`` (upper arm, forearm)."""
    elbow = [0.0, 0.0, shape.upper]
    heads = np.array([[0.0, 0.0, 0.0], elbow])
    tails = np.array([elbow, [0.0, 0.0, shape.length]])
    return heads, tails


def bone_transforms(shape: ArmShape, angles_deg: np.ndarray) -> np.ndarray:
    """``(F, 2, 3, 4)`` ``[A | t]``: the upper arm stays, the forearm turns about the elbow."""
    angles = np.radians(np.asarray(angles_deg, dtype=np.float64))
    F = angles.shape[0]
    T = np.zeros((F, 2, 3, 4))
    T[:, 0, :, :3] = np.eye(3)
    c, s = np.cos(angles), np.sin(angles)
    R = np.zeros((F, 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    elbow = np.array([0.0, 0.0, shape.upper])
    T[:, 1, :, :3] = R
    T[:, 1, :, 3] = elbow - R @ elbow
    return T


def correctives(shape: ArmShape, rest: np.ndarray, angles_deg: np.ndarray) -> np.ndarray:
    """Rest-pose corrective displacements ``(F, V, 3)``: bicep and tricep bulges.

    Radial (in the ``xy`` plane), on the front (``cos phi > 0``) or back of the upper arm,
    profile ``sin^2`` along its middle 70 %, amplitude proportional to the angle.
    """
    x, y, z = rest[:, 0], rest[:, 1], rest[:, 2]
    rho = np.hypot(x, y)
    cos_phi = np.where(rho > 0, x / np.where(rho > 0, rho, 1), 0.0)
    along = _bump((z - 0.25 * shape.upper) / (0.7 * shape.upper))
    radial = np.stack([np.where(rho > 0, x / np.where(rho > 0, rho, 1), 0.0),
                       np.where(rho > 0, y / np.where(rho > 0, rho, 1), 0.0),
                       np.zeros_like(x)], axis=1)
    front = np.clip(cos_phi, 0, None) ** 2 * along
    back = np.clip(-cos_phi, 0, None) ** 2 * along
    angles = np.asarray(angles_deg, dtype=np.float64)
    flex = np.clip(angles, 0, None) / shape.max_flexion
    ext = np.clip(-angles, 0, None) / max(shape.max_extension, 1e-300)
    amount = (shape.bicep_bulge * flex[:, None] * front[None]
              + shape.tricep_bulge * ext[:, None] * back[None])           # (F, V)
    return amount[..., None] * radial[None]


def corrective_shapes(shape: ArmShape, rest: np.ndarray, angles_deg: np.ndarray
                      ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The correctives as two blend shapes (a DCC's form): offsets ``(V, 3)`` of the full
    bicep and tricep bulge, and their weights ``(F, 2)`` per frame (the flexion and the
    extension as fractions of their maxima), so that ``weights @ offsets`` is
    :func:`correctives`."""
    angles = np.asarray(angles_deg, dtype=np.float64)
    shapes = {"bicep": correctives(shape, rest, np.array([shape.max_flexion]))[0],
              "tricep": correctives(shape, rest, np.array([-shape.max_extension]))[0]}
    weights = np.stack([np.clip(angles, 0, None) / shape.max_flexion,
                        np.clip(-angles, 0, None) / max(shape.max_extension, 1e-300)], axis=1)
    return shapes, weights


def skinning_weights(shape: ArmShape, points: np.ndarray) -> np.ndarray:
    """Distance skinning weights ``(n, 2)`` of the arm's rig at rest ``points``."""
    heads, tails = rig(shape)
    return distance_weights(segment_distances(points, heads, tails), 1.5 * shape.r_shoulder)


def attach_radius(shape: ArmShape) -> float:
    """``attach_ratio`` times the mean radius of the arm."""
    z = np.linspace(0, shape.length, 200)
    return float(shape.attach_ratio * base_radius(shape, z).mean())


def arm_animation(shape: ArmShape = ArmShape()) -> dict:
    """Everything :func:`.animation.write_animation` needs for the arm.

    Returns a dict with ``rest_vertices``, ``faces``, ``frames`` ``(F, V, 3)``,
    ``skeleton`` (:class:`.animation.Skeleton`), ``angles`` ``(F,)`` degrees and
    ``bulge`` ``(F, V, 3)`` (the corrective displacements).
    """
    rest, faces = arm_surface(shape)
    angles = elbow_angles(shape)
    heads, tails = rig(shape)
    transforms = bone_transforms(shape, angles)
    weights = skinning_weights(shape, rest)
    bulge = correctives(shape, rest, angles)
    moved = blend(rest, weights, transforms)                              # (F, V, 3)
    # correctives are rest-pose offsets: skin them with the linear part of each bone
    linear = np.einsum("nb,fbij,fnj->fni", weights, transforms[..., :3], bulge)
    frames = moved + linear
    skeleton = Skeleton(heads, tails, transforms, attach_radius(shape), weights,
                        ["upper_arm", "forearm"])
    return {"rest_vertices": rest, "faces": faces, "frames": frames, "skeleton": skeleton,
            "angles": angles, "bulge": bulge}


def region_labels(shape: ArmShape, points: np.ndarray) -> np.ndarray:
    """``0`` bone, ``1`` muscle, ``2`` fat for rest ``points`` ``(n, 3)`` (by the distance
    to the bone axis relative to the local base radius)."""
    heads, tails = rig(shape)
    rho = segment_distances(points, heads, tails).min(axis=1)
    z = np.clip(axial_coordinates(points, heads[:1], np.array([[0, 0, shape.length]]))[:, 0],
                0, 1) * shape.length
    r = radius(shape, z)
    return np.where(rho < shape.bone_ratio * r, 0,
                    np.where(rho < shape.muscle_ratio * r, 1, 2)).astype(np.int64)


def elbow_region(shape: ArmShape, points: np.ndarray, reach: float | None = None) -> np.ndarray:
    """Mask of rest ``points`` within ``reach`` (default ``1.5 r`` at the elbow) of the elbow."""
    elbow = np.array([0.0, 0.0, shape.upper])
    reach = 1.5 * float(radius(shape, np.array([shape.upper]))[0]) if reach is None else reach
    return np.linalg.norm(np.asarray(points) - elbow, axis=1) <= reach


def keyframed_jiggle(frames: np.ndarray, weights: np.ndarray, fps: float = 24.0,
                     amplitude: float = 1.0, frequency: float = 6.0,
                     damping_ratio: float = 0.2) -> np.ndarray:
    """Hand-style secondary motion on top of ``frames`` ``(F, V, 3)`` (metres): after every
    change of speed the flesh lags and overshoots in a damped oscillation, as an animator keys
    overlapping action (a procedural layer, not a simulation: each vertex on its own).

    Every frame's change of velocity ``dv_g = (x_{g+1} - 2 x_g + x_{g-1}) fps`` starts a lag
    ``-amplitude w_v dv_g e^{-zeta omega tau} sin(omega_d tau) / omega_d`` at the frames
    ``tau = (f - g) / fps > 0`` after it (``omega = 2 pi frequency``, ``omega_d = omega
    sqrt(1 - zeta^2)``); ``weights`` ``(V,)`` in [0, 1] say how much flesh each vertex has.
    Returns the frames with the jiggle added (frame 0 and uniform motion unchanged)."""
    frames = np.asarray(frames, dtype=np.float64)
    n = len(frames)
    omega = 2.0 * math.pi * frequency
    zeta = float(damping_ratio)
    omega_d = omega * math.sqrt(max(1.0 - zeta * zeta, 1e-12))
    out = frames.copy()
    for g in range(1, n - 1):
        dv = (frames[g + 1] - 2.0 * frames[g] + frames[g - 1]) * fps          # (V, 3)
        tau = (np.arange(g + 1, n) - g) / fps
        lag = np.exp(-zeta * omega * tau) * np.sin(omega_d * tau) / omega_d  # (k,)
        out[g + 1:] -= amplitude * lag[:, None, None] * (weights[:, None] * dv)[None]
    return out


def flesh_weights(shape: ArmShape, rest: np.ndarray) -> np.ndarray:
    """Per rest vertex ``(V,)`` in [0, 1]: how much the bicep and tricep bellies move (their
    largest corrective displacement, normalised), at least 0.25 everywhere."""
    bulge = np.linalg.norm(correctives(shape, rest, elbow_angles(shape)), axis=-1).max(axis=0)
    peak = float(bulge.max()) or 1.0
    return np.clip(0.25 + 0.75 * bulge / peak, 0.0, 1.0)
