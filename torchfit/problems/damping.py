"""Physical bounds on Rayleigh damping: the damping ratio at the body's lowest mode and the frames'.

:class:`DampingBand` holds the frequencies the damping ``C = alpha M + beta K`` is judged at
(the body's lowest angular frequency ``w1`` and ``pi x fps``, the highest the frames show)
and gives the bounds ``alpha <= 2 ZETA_MAX w1``, ``beta <= 2 ZETA_MAX / max(w1, w_frames)``
from :func:`damping_ratio`, the refusal of a start outside them and the ratios a fit
reports. Used by every problem in time (:mod:`.dynamic`); measured figures:
docs/notes/dynamics.md.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from .config import setting_error


#: The largest damping ratio ``zeta(w) = alpha / (2 w) + beta w / 2`` the Rayleigh damping may
#: give at the body's lowest mode ``w1`` and at the highest frequency the frames show: 1,
#: critical damping. Past it that mode no longer oscillates, it only creeps back toward the
#: rig (the quasistatic body, which the static fit models with no damping to fit); damping
#: that large explains any motion by slowing it, not by the material (issue 47: started at
#: beta0 = 1e12 the body followed its skinned pose and the misfit fell 10x).
ZETA_MAX = 1.0


def damping_ratio(alpha: float, beta: float, omega: float) -> float:
    """``zeta(w) = alpha / (2 w) + beta w / 2`` of Rayleigh damping ``C = alpha M + beta K``
    at angular frequency ``omega`` (rad/s; alpha in 1/s, beta in s)."""
    return alpha / (2.0 * omega) + beta * omega / 2.0


@dataclasses.dataclass(frozen=True)
class DampingBand:
    """The frequencies the Rayleigh damping is judged at and the bounds they give.

    ``w1`` (rad/s): the lowest angular frequency of ``K0(k0) u = w^2 M u`` at the start's
    homogeneous material with the Dirichlet dofs held
    (:meth:`~torchfit.physics.dynamics.DynamicSystem.lowest_frequency`; ``None`` where
    nothing holds the body); ``w_frames`` (rad/s): ``pi x`` the frame rate (``pi / dt`` of
    the shortest interval between output times), the highest frequency the frames can show.
    The band is ``[w1, w_high]``, ``w_high = max(w1, w_frames)`` (a body stiffer than the
    frames can show has no mode below ``w1``).

    ``zeta(w)`` is convex in ``w`` (the mass term falls, the stiffness term grows), so the
    bounds ``alpha <= alpha_max = 2 ZETA_MAX w1`` (the mass term at ``w1``) and ``beta <=
    beta_max = 2 ZETA_MAX / w_high`` (the stiffness term at ``w_high``) keep every mode of
    the band at most ``ZETA_MAX`` damped by each term alone, both together at most ``2
    ZETA_MAX``. Units: 1/s and s."""

    w1: float | None
    w_frames: float

    @property
    def w_high(self) -> float:
        return self.w_frames if self.w1 is None else max(self.w1, self.w_frames)

    @property
    def alpha_max(self) -> float:
        return math.inf if self.w1 is None else 2.0 * ZETA_MAX * self.w1

    @property
    def beta_max(self) -> float:
        return 2.0 * ZETA_MAX / self.w_high

    @classmethod
    def of(cls, system: DynamicSystem, start_field: float, frame_interval: float) -> "DampingBand":
        """The band of ``system`` at the homogeneous field ``start_field`` (``w1`` scales
        as its square root) for frames ``frame_interval`` seconds apart."""
        field = torch.full((system.n_field,), float(start_field), dtype=torch.float64)
        return cls(system.lowest_frequency(field), math.pi / float(frame_interval))

    def ratios(self, alpha: float, beta: float) -> dict[str, float]:
        """``zeta`` at ``w1`` (where known) and at ``w_high``."""
        out = {"zeta_w_high": damping_ratio(alpha, beta, self.w_high)}
        if self.w1 is not None:
            out["zeta_w1"] = damping_ratio(alpha, beta, self.w1)
        return out

    def describe(self) -> dict[str, float | None]:
        """``w1``, ``w_frames``, ``w_high`` (rad/s), ``alpha_max`` (1/s), ``beta_max`` (s),
        ``zeta_max``."""
        return {"w1": self.w1, "w_frames": self.w_frames, "w_high": self.w_high,
                "alpha_max": None if self.w1 is None else self.alpha_max,
                "beta_max": self.beta_max, "zeta_max": ZETA_MAX}

    def check_start(self, cfg: Any, alpha: float, beta: float,
                    keys: tuple[str, str] = ("alpha0", "beta0"),
                    frames: str = "the frames") -> None:
        """Refuse (one line naming the setting, the bound and the ratio it gives) damping
        ``alpha``, ``beta`` outside ``[0, alpha_max] x [0, beta_max]``. ``frames``: where
        the frame rate comes from (for the message)."""
        if alpha > self.alpha_max:
            zeta = damping_ratio(alpha, 0.0, self.w1)
            raise setting_error(keys[0], getattr(cfg, keys[0]), (
                f"gives the damping ratio zeta = alpha / (2 w1) = {zeta:.3g} at the body's "
                f"lowest mode w1 = {self.w1:.4g} rad/s, above {ZETA_MAX:g} (critical damping, "
                f"ZETA_MAX): alpha must be at most 2 ZETA_MAX w1 = {self.alpha_max:.4g} 1/s; "
                f"start lower, e.g. problem.{keys[0]}={self.alpha_max / 10:.3g}"))
        if beta > self.beta_max:
            zeta = damping_ratio(0.0, beta, self.w_high)
            where = f"pi x {self.w_frames / math.pi:.4g} frames/s of {frames}, the highest " \
                "frequency they show" if self.w_high == self.w_frames else "the body's lowest mode"
            raise setting_error(keys[1], getattr(cfg, keys[1]), (
                f"gives the damping ratio zeta = beta w / 2 = {zeta:.3g} at w = "
                f"{self.w_high:.4g} rad/s ({where}), above {ZETA_MAX:g} (critical damping, "
                f"ZETA_MAX): beta must be at most 2 ZETA_MAX / w = {self.beta_max:.4g} s; start "
                f"lower, e.g. problem.{keys[1]}={self.beta_max / 10:.3g}"))
