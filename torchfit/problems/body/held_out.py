"""Frames held out of a body's fit for validation: which ones, with repeated poses grouped.

A body's settings (:class:`~.config.RiggedBodyConfig`) name the validation frames
(``validation_frames``: animation frame numbers) or a rule (``validation_every = k``: every
k-th distinct pose of the frames considered, in order of first appearance, the k-th, 2k-th,
...). Frames are *the same pose* when every surface vertex of one lies within
``validation_repeat_tol`` (a fraction of the rest surface's bounding-box diagonal) of the
other's: an animation that plays back holds each pose twice (the arm's 48 frames hold 24).
A pose is fitted or validated, never both: the frames repeating a validation frame's pose
leave the fit too (they are not validated again: the same pose gives the same error).

:func:`split_frames` returns the split (:class:`FrameSplit`) or raises
:class:`~.config.ProblemConfigError` naming the setting (a frame not in the animation, a
frame both in ``problem.frames`` and in ``validation_frames``, nothing left to fit);
:data:`NO_VALIDATION` clears the settings for the problem on a subset of frames (the
validation problem itself, a continuation's first stage).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from ..config import setting_error

#: The validation settings of a problem that holds none (``dataclasses.replace(cfg, **...)``).
NO_VALIDATION: dict[str, Any] = {"validation_frames": None, "validation_every": 0}


@dataclasses.dataclass(frozen=True)
class FrameSplit:
    """Animation frame numbers of the fit and of the validation.

    Attributes:
        fitted: the frames fitted, in the animation's order (``problem.frames`` less the
            held-out poses).
        validation: the frames simulated for validation only (one per held-out pose).
        repeats: frames that left the fit because they repeat a validation frame's pose.
        poses: distinct poses among the frames considered (fitted and validation).
    """

    fitted: list[int]
    validation: list[int]
    repeats: list[int]
    poses: int

    def describe(self) -> str:
        """One line for the log: what is fitted, what is held out and why."""
        fitted_poses = self.poses - len(self.validation)
        line = (f"validation: frames {_numbers(self.validation)} held out of the fit "
                f"({len(self.validation)} distinct poses); fitting {len(self.fitted)} frames "
                f"({fitted_poses} distinct poses)")
        if self.repeats:
            line += (f"; frames {_numbers(self.repeats)} repeat a validation pose and leave "
                     "the fit too")
        return line


def _numbers(frames: list[int]) -> str:
    return "[" + ", ".join(str(f) for f in frames) + "]"


def pose_groups(frames: np.ndarray, tolerance: float) -> np.ndarray:
    """Pose label per frame ``(F,)`` of surface positions ``frames`` ``(F, V, 3)``: labels
    ``0, 1, ...`` in order of first appearance; a frame gets the label of the first earlier
    frame none of whose vertices is farther than ``tolerance`` (metres) from its own."""
    labels = np.full(len(frames), -1, dtype=np.int64)
    label = 0
    for first in range(len(frames)):
        if labels[first] >= 0:
            continue
        open_frames = np.flatnonzero(labels < 0)                  # ``first`` among them
        distance = np.linalg.norm(frames[open_frames] - frames[first], axis=-1).max(axis=-1)
        labels[open_frames[distance <= tolerance]] = label
        label += 1
    return labels


def split_frames(cfg: Any, rest_vertices: np.ndarray, frames: np.ndarray) -> FrameSplit | None:
    """The fit's and the validation's frames (module docstring), ``None`` without validation.

    Args:
        cfg: the body's settings (``frames``, ``validation_frames``, ``validation_every``,
            ``validation_repeat_tol``).
        rest_vertices: ``(V, 3)`` the rest surface (its diagonal scales the tolerance).
        frames: ``(F, V, 3)`` every frame of the animation.
    """
    named, every = cfg.validation_frames, cfg.validation_every
    if named is None and not every:
        return None
    n = len(frames)
    if named is not None and every:
        raise setting_error("validation_every", every, "and problem.validation_frames both "
                            "choose validation frames; give one of them")
    if not isinstance(every, int) or isinstance(every, bool) or every < 0:
        raise setting_error("validation_every", every, "must be an integer >= 0 (0: none; k: "
                            "every k-th distinct pose is held out)")
    tol = cfg.validation_repeat_tol
    if not isinstance(tol, (int, float)) or not np.isfinite(tol) or tol < 0:
        raise setting_error("validation_repeat_tol", tol, "must be a number >= 0 (a fraction "
                            "of the bounding-box diagonal)")
    considered = list(range(n)) if cfg.frames is None else [int(f) for f in cfg.frames]
    outside = [f for f in considered if not 0 <= f < n]
    if outside:
        raise setting_error("frames", cfg.frames, f"frame {outside[0]} does not exist (the "
                            f"animation has frames 0..{n - 1})")
    diagonal = float(np.linalg.norm(rest_vertices.max(0) - rest_vertices.min(0)))
    if named is not None:
        validation = [int(f) for f in named]
        bad = [f for f in validation if not 0 <= f < n]
        if not validation or bad:
            raise setting_error("validation_frames", named, f"frame {bad[0]} is not a frame of "
                                f"the animation (0..{n - 1})" if bad else "lists no frame "
                                "(null: no validation)")
        if len(set(validation)) != len(validation):
            raise setting_error("validation_frames", named, "lists a frame twice; list each "
                                "frame once")
        if cfg.frames is not None:
            both = sorted(set(validation) & set(considered))
            if both:
                raise setting_error("validation_frames", named, f"overlaps problem.frames "
                                    f"(frames {_numbers(both)}): a frame is fitted or "
                                    "validated, not both; leave them out of problem.frames")
        union = sorted(set(considered) | set(validation))
    else:
        union = considered
    labels = dict(zip(union, pose_groups(frames[union], tol * diagonal).tolist()))
    poses = len(set(labels.values()))
    if every:
        first_of: dict[int, int] = {}
        for f in considered:
            first_of.setdefault(labels[f], f)
        chosen = [first_of[g] for g in sorted(first_of, key=first_of.get)][every - 1::every]
        if not chosen:
            raise setting_error("validation_every", every, f"holds out no pose: the frames "
                                f"hold {poses} distinct poses; choose k <= {poses}")
        validation = sorted(chosen)
    held = {labels[f] for f in validation}
    fitted = [f for f in considered if labels[f] not in held]
    repeats = [f for f in considered if labels[f] in held and f not in validation]
    if not fitted:
        setting, value = ("validation_every", every) if every else ("validation_frames", named)
        raise setting_error(setting, value, "holds out every frame of the fit (the frames "
                            f"hold {poses} distinct poses, each repeat of a validation pose "
                            "leaves the fit too); leave some poses to fit")
    return FrameSplit(fitted, validation, repeats, poses)
