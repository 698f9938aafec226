"""Checks of a rigged animation before fitting: the frames' scale, and skinning the rest.

Two mistakes pass every format check and then fit to nothing (issue 28): frames written in
another unit than the rest surface (millimetres against metres), and bone transforms written
in another convention than the format's ``x' = A x + t`` (``A`` transposed, i.e. a
row-vector layout stored as column-vector ``[A | t]``; bone-local instead of rest-relative
transforms; translations in another unit). :func:`check_animation` refuses both with one
:class:`~.animation.AnimationError` line that names the frames (and bones) at fault
and the likely cause.

**Scale** (every animation, skeleton or driven vertices): the size of a frame is the RMS
distance of its vertices from their centroid (translation-free, and a bend changes it by
far less than 2x); a frame whose size is more than ``sqrt(10)`` times (or less than
``1/sqrt(10)`` of) the rest's is refused, naming the pair of units (m, cm, mm, in) whose
ratio is closest.

**Skinning** (every skeleton): linear blend skinning of the rest vertices with the
manifest's weights, or where it gives none (``weights: distance``) with the weights from
distance the rig attaches the material with (:func:`~.rig.distance_weights` of each
vertex's distance to the bones, reach ``attach_radius``), and the transforms
``(F, B, 3, 4)`` is compared with the frames. Correctives (bulges, the arm's 1.2 cm on a 0.58 m arm) and another deformer's
blending near joints are legitimate differences, so the statistic is robust: per frame and
bone, the *median* distance over the vertices whose largest weight is that bone's, relative
to the rest's bounding-box diagonal. A value above ``tolerance`` (default 0.05) fails. The
failing frames are skinned again under each alternative convention (``A`` transposed, the
transforms inverted, bone-local transforms ``A (x - head) + t``, translations scaled by a
power of ten or an inch factor); the one that passes is named as the likely cause.

Measured (2026-11-26, docs/notes/rig_check.md): the arm's largest per-bone median is 0.2 % of
its diagonal; its transforms transposed give 4-60 % on every bent frame and the transposed
variant gives back 0.2 %. With weights from distance (2026-12-01): the arm 0.10 %, the
test capsule 0.14 %; their transforms transposed 166 % and 44 %, inverted 67 % and 44 %,
bone-local 50 % and 35 %. Weights from distance are torchfit's guess, not the rig's, so
there a mismatch is refused only where a mix-up of the transforms explains it (a variant
passes); otherwise the frames may be skinned with other weights, and the report keeps the
figure.

Lengths in metres (the loader's). Nothing here solves anything (docs/architecture.md, layer
``mesh``).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .animation import UNITS, Animation, AnimationError
from .rig import distance_weights, segment_distances

#: a frame whose size differs from the rest's by more than this factor is refused
SCALE_FACTOR = math.sqrt(10.0)
#: default largest per-frame, per-bone median skinning distance (fraction of the diagonal)
TOLERANCE = 0.05
#: unit factors tried for the translations (and named for the frames' scale)
_UNIT_FACTORS = {1e-3: "1/1000", 1e-2: "1/100", 1e-1: "1/10", 10.0: "10", 100.0: "100",
                 1000.0: "1000", 0.0254: "0.0254 (inches to metres)",
                 1 / 0.0254: "39.37 (metres to inches)", 2.54: "2.54 (inches to cm)",
                 1 / 2.54: "1/2.54 (cm to inches)"}
#: frames x vertices x 12 floats per chunk of the skinning (about 64 MB)
_CHUNK_VALUES = 8_000_000


@dataclasses.dataclass
class RigReport:
    """What the checks measured (for the log and ``result.json``).

    Attributes:
        scale_ratios: ``(F,)`` each frame's size over the rest's.
        skinning_error: largest per-frame, per-bone median skinning distance relative to
            the rest's diagonal, or ``None`` without a skeleton.
        distance_weights: whether the skinning used weights from distance (the manifest
            gives none).
    """

    scale_ratios: np.ndarray
    skinning_error: float | None = None
    distance_weights: bool = False

    def line(self) -> str:
        """One line for the console."""
        text = (f"rig check: frame sizes {self.scale_ratios.min():.3g}-"
                f"{self.scale_ratios.max():.3g} x the rest's")
        if self.skinning_error is None:
            return text + "; no skeleton, skinning not checked"
        weights = "weights from distance" if self.distance_weights else "the weights"
        return text + (f"; skinning the rest with {weights} reproduces the frames to a "
                       f"median {100 * self.skinning_error:.2g} % of the body's size per bone")


def size(points: np.ndarray) -> np.ndarray:
    """RMS distance from the centroid of ``points`` ``(..., V, 3)``: ``(...)``."""
    centred = points - points.mean(axis=-2, keepdims=True)
    return np.sqrt(np.einsum("...vi,...vi->...", centred, centred) / points.shape[-2])


def frame_ranges(frames: np.ndarray | list[int], limit: int = 6) -> str:
    """``1-11, 13-23`` for sorted frame numbers (at most ``limit`` ranges, then ``...``)."""
    numbers = sorted(int(f) for f in frames)
    ranges: list[list[int]] = []
    for n in numbers:
        if ranges and n == ranges[-1][1] + 1:
            ranges[-1][1] = n
        else:
            ranges.append([n, n])
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in ranges[:limit]]
    return ", ".join(parts) + (", ..." if len(ranges) > limit else "")


def _unit_guess(ratio: float) -> str:
    """``mm against a rest in m`` for the pair of units whose ratio is closest to
    ``ratio`` (a frame's size over the rest's, in file numbers)."""
    pairs = [(f, r) for f in UNITS for r in UNITS if f != r]
    frames_unit, rest_unit = min(pairs, key=lambda p: abs(math.log(
        ratio * UNITS[p[0]] / UNITS[p[1]])))
    return f"frames in {frames_unit} against a rest in {rest_unit}"


def check_scale(animation: Animation) -> np.ndarray:
    """Each frame's size over the rest's ``(F,)``; raises for frames off by ``SCALE_FACTOR``."""
    rest = float(size(animation.rest_vertices))
    if not rest > 0:
        raise AnimationError(f"{animation.path}: the rest surface has no extent (every vertex "
                             "at one point)")
    ratios = size(animation.frames) / rest
    bad = np.flatnonzero(~((ratios <= SCALE_FACTOR) & (ratios >= 1 / SCALE_FACTOR)))
    if bad.size:
        worst = float(ratios[bad[np.argmax(np.abs(np.log(ratios[bad])))]])
        raise AnimationError(
            f"{animation.path}: frames {frame_ranges(bad)} ({bad.size} of {len(ratios)}) are "
            f"{worst:.4g} times the rest surface's size (RMS distance from the centroid): "
            f"{_unit_guess(worst)}? write the rest and the frames in one unit (the manifest's "
            "'unit' applies to every file)")
    return ratios


def skin(rest: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning ``(F, V, 3)`` of ``rest`` ``(V, 3)`` with ``weights`` ``(V, B)``
    and ``transforms`` ``(F, B, 3, 4)``: the blended ``[A | t]`` per vertex applied to it
    (frames in chunks of about 64 MB)."""
    n_frames, n_vertices = transforms.shape[0], rest.shape[0]
    out = np.empty((n_frames, n_vertices, 3))
    step = max(1, _CHUNK_VALUES // max(12 * n_vertices, 1))
    flat = transforms.reshape(n_frames, transforms.shape[1], 12)
    for start in range(0, n_frames, step):
        blended = np.einsum("vb,fbk->fvk", weights, flat[start:start + step]).reshape(
            -1, n_vertices, 3, 4)
        out[start:start + step] = np.einsum("fvij,vj->fvi", blended[..., :3], rest) \
            + blended[..., 3]
    return out


def bone_medians(distances: np.ndarray, dominant: np.ndarray, n_bones: int) -> np.ndarray:
    """Median of ``distances`` ``(F, V)`` over the vertices of each bone (``dominant``
    ``(V,)``): ``(F, B)``, NaN for a bone that dominates no vertex."""
    out = np.full((distances.shape[0], n_bones), np.nan)
    for bone in np.unique(dominant):
        out[:, bone] = np.median(distances[:, dominant == bone], axis=1)
    return out


def _variants(transforms: np.ndarray, heads: np.ndarray) -> dict[str, np.ndarray]:
    """The transforms under the conventions a user may have mixed up, by the cause named."""
    A, t = transforms[..., :3], transforms[..., 3]
    out = {}
    transposed = transforms.copy()
    transposed[..., :3] = np.swapaxes(A, -1, -2)
    out["transposed A (rows written for columns, e.g. a row-vector layout x' = x A + t stored "
        "as [A | t]): transpose the 3x3 block of every transform"] = transposed
    inverse_A = np.linalg.inv(A)
    inverted = np.concatenate([inverse_A, -np.einsum("fbij,fbj->fbi", inverse_A, t)[..., None]],
                              axis=-1)
    out["inverted transforms (pose-to-rest instead of rest-to-pose): invert every [A | t]"] \
        = inverted
    local = transforms.copy()
    local[..., 3] = t - np.einsum("fbij,bj->fbi", A, heads)
    out["bone-local transforms (x' = A (x - head) + t; the rest/bind pose not removed): "
        "multiply each by the inverse of its bone's rest matrix"] = local
    for factor, name in _UNIT_FACTORS.items():
        scaled = transforms.copy()
        scaled[..., 3] = t * factor
        out[f"translations in another unit than the surfaces (they fit when multiplied by "
            f"{name}): write the transforms' t in the surfaces' unit"] = scaled
    return out


def skinning_weights(animation: Animation) -> np.ndarray:
    """``(V, B)`` weights of the rest vertices: the manifest's, else from distance as the
    rig attaches the material (reach ``attach_radius``)."""
    skeleton = animation.skeleton
    if skeleton.weights is not None:
        return skeleton.weights
    return distance_weights(segment_distances(animation.rest_vertices, skeleton.heads,
                                              skeleton.tails), skeleton.attach_radius)


def check_skinning(animation: Animation, tolerance: float = TOLERANCE) -> float | None:
    """Largest per-frame, per-bone median skinning distance (fraction of the rest's
    diagonal), ``None`` without weights; raises beyond ``tolerance`` (module docstring)."""
    skeleton = animation.skeleton
    if skeleton is None:
        return None
    rest, frames = animation.rest_vertices, animation.frames
    weights = skinning_weights(animation)
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    dominant = np.argmax(weights, axis=1)

    def medians(transforms: np.ndarray, frame_index: np.ndarray) -> np.ndarray:
        skinned = skin(rest, weights, transforms[frame_index])
        distances = np.linalg.norm(skinned - frames[frame_index], axis=-1)
        return bone_medians(distances, dominant, skeleton.n_bones) / diagonal

    every = np.arange(animation.n_frames)
    given = medians(skeleton.transforms, every)
    worst = float(np.nanmax(given))
    failing = np.nan_to_num(given, nan=0.0) > tolerance
    if not failing.any():
        return worst
    frames_bad = np.flatnonzero(failing.any(axis=1))
    bones_bad = np.flatnonzero(failing.any(axis=0))
    scores = {cause: float(np.nanmax(medians(alternative, frames_bad)))
              for cause, alternative in _variants(skeleton.transforms, skeleton.heads).items()}
    cause, best = min(scores.items(), key=lambda item: item[1])
    if skeleton.weights is None and best > tolerance:
        # weights from distance are torchfit's guess, not the rig's: frames skinned otherwise
        # (painted weights, another deformer) differ from them without a fault; only a
        # mix-up of the transforms that a variant explains is refused
        return worst
    if best <= tolerance:
        likely = f"likely cause: {cause}"
    else:
        likely = ("no simple mix-up (transposed A, inverted or bone-local transforms, "
                  "translations in another unit) explains it: check that the weights and the "
                  "transforms belong to these frames and follow x' = A x + t on rest positions")
    names = [skeleton.names[b] if b < len(skeleton.names) else f"bone{b}" for b in bones_bad]
    source = "weights from distance (weights: distance)" if skeleton.weights is None else \
        "the manifest's weights"
    raise AnimationError(
        f"{animation.path}: skinning the rest surface with {source} and bone "
        f"transforms does not reproduce frames {frame_ranges(frames_bad)} ({frames_bad.size} "
        f"of {animation.n_frames}) on bones {', '.join(names[:8])}"
        f"{', ...' if len(names) > 8 else ''}: a median distance up to "
        f"{worst * diagonal:.3g} m, {100 * worst:.3g} % of the body's size "
        f"({diagonal:.3g} m; tolerance {100 * tolerance:.3g} %); {likely}")


def check_animation(animation: Animation, tolerance: float = TOLERANCE) -> RigReport:
    """The scale of every frame, then (with a skeleton) the skinning;
    raises :class:`~.animation.AnimationError` (one line) for either."""
    ratios = check_scale(animation)
    return RigReport(ratios, check_skinning(animation, tolerance),
                     animation.skeleton is not None and animation.skeleton.weights is None)
