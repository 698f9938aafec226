"""Derivative verification: every Jacobian product has a check (hIPPYlib style).

Problem-agnostic: the checks see only a :class:`~torchfit.residual.ResidualFunction`
(``value(theta)`` and ``linearize(theta)`` with ``r``, ``jvp(v)`` and ``vjp(w)``), so they
apply to every problem, parameterisation and simulator alike.

* :func:`taylor_test`: the remainder ``e(h) = ||r(theta + h v) - r(theta) - h J v||`` must
  fall as ``h^2``. Steps form a geometric sequence (halving) from a step that changes
  ``theta`` by about 10 % of its norm; steps whose remainder is within a safety factor of
  the round-off floor are discarded, and so are the pre-asymptotic ones at the large
  end: the reported rate is the median observed rate ``log2(e(h) / e(h/2))`` over the
  last stable run of rates before round-off. A residual that is linear in ``theta``
  (all remainders at round-off) is reported as such (``linear=True``, ``rate=nan``).
  ``order=1`` drops the ``h J v`` term and must show rate 1 (a sanity check of the test).
* :func:`dot_product_test`: ``<J v, w>`` against ``<v, J^T w>`` (``vjp`` is the transpose
  of ``jvp``); its bound (:func:`default_dot_tol`) is 1e-10 where ``J^T w`` is the exact
  transpose of ``J v``, and follows the residual's ``product_consistency`` (an ODE
  tolerance) where the two are separate approximations.
* :func:`finite_difference_test`: central difference of ``r`` against ``J v``.
* :func:`verify`: the three at one point with seeded random directions, and a
  :class:`VerificationReport` (``passed``, ``to_dict()``, ``format_report()``).

Random directions are drawn from a seeded ``torch.Generator`` in float64 on the CPU
(reproducible across devices) and used as they are: for a scale-free problem the
gauge direction is part of the residual's null space and needs no special treatment
here.
"""
from __future__ import annotations

import dataclasses
import math
import statistics
from typing import Any, Protocol

import torch
from torch import Tensor

__all__ = ["TaylorResult", "DotProductResult", "FiniteDifferenceResult", "VerificationReport",
           "taylor_test", "dot_product_test", "finite_difference_test", "random_direction",
           "default_fd_tol", "default_dot_tol",
           "verify", "format_report"]


class _Linearization(Protocol):
    r: Tensor

    def jvp(self, v: Tensor) -> Tensor: ...

    def vjp(self, w: Tensor) -> Tensor: ...


class _Residual(Protocol):
    def value(self, theta: Tensor) -> Tensor: ...

    def linearize(self, theta: Tensor) -> _Linearization: ...


# Errors a forward evaluation at a too-large Taylor step may raise (non-positive field,
# Newton failure, singular tangent): such steps count as pre-asymptotic, not as bugs.
_STEP_ERRORS = (RuntimeError, ValueError, ArithmeticError)


def _norm(x: Tensor) -> float:
    return float(torch.linalg.vector_norm(x))


def _scale(theta: Tensor) -> float:
    """Norm of ``theta`` for relative steps; 1 where ``theta`` is zero."""
    norm = _norm(theta)
    return norm if norm > 0 and math.isfinite(norm) else 1.0


def _direction_norm(v: Tensor) -> float:
    norm = _norm(v)
    if not (norm > 0 and math.isfinite(norm)):
        raise ValueError(f"the direction must be a finite non-zero vector, got norm {norm}")
    return norm


def random_direction(n: int, generator: torch.Generator, like: Tensor) -> Tensor:
    """Unit-norm Gaussian vector ``(n,)`` (float64 draw on the CPU, then ``like``'s device/dtype)."""
    v = torch.randn(n, generator=generator, dtype=torch.float64)
    return (v / torch.linalg.vector_norm(v)).to(device=like.device, dtype=like.dtype)


# -- Taylor test ----------------------------------------------------------------------
@dataclasses.dataclass
class TaylorResult:
    """Outcome of :func:`taylor_test`.

    Attributes:
        steps: ``h_i = h_0 2^-i``.
        remainders: ``e(h_i)`` (``nan`` where the forward evaluation failed).
        rates: ``log2(e(h_i) / e(h_{i+1}))`` for ``i < len(steps) - 1`` (``nan`` where
            either remainder is discarded).
        rate: median rate over the window (``nan`` if linear or no window).
        window: ``(start, stop)``: the rates ``rates[start:stop]`` were used, i.e. steps
            ``start .. stop`` inclusive.
        linear: every remainder is at round-off (the residual is linear in ``theta``
            along ``v``, to machine precision).
        expected: the rate a correct Jacobian gives (``order``: 2, or 1 without ``J v``).
        roundoff: whether each step was discarded as round-off dominated.
        threshold: the remainder below which a step is round-off dominated.
        order: 2 (with ``h J v``) or 1 (without: a first-order check).
    """

    steps: list[float]
    remainders: list[float]
    rates: list[float]
    rate: float
    window: tuple[int, int]
    linear: bool
    expected: float
    roundoff: list[bool]
    threshold: list[float]
    order: int = 2

    @property
    def window_rates(self) -> list[float]:
        return self.rates[self.window[0]:self.window[1]]

    def passed(self, tol: float = 0.05) -> bool:
        """Linear residual, or observed rate within ``tol`` of the expected one."""
        if self.linear:
            return True
        return math.isfinite(self.rate) and abs(self.rate - self.expected) <= tol

    def to_dict(self) -> dict[str, Any]:
        return {"steps": list(self.steps), "remainders": [_json_float(e) for e in self.remainders],
                "rates": [_json_float(r) for r in self.rates], "rate": _json_float(self.rate),
                "window": list(self.window), "linear": self.linear, "expected": self.expected,
                "roundoff": list(self.roundoff), "threshold": list(self.threshold),
                "order": self.order}


def taylor_test(residual: _Residual, theta: Tensor, direction: Tensor, *,
                lin: _Linearization | None = None, order: int = 2, n_steps: int = 24,
                relative_step: float = 0.1, safety: float = 1e4, window_tol: float = 0.05,
                min_window: int = 3, max_drop: int = 2) -> TaylorResult:
    """Taylor remainders of ``residual`` at ``theta`` along ``direction``.

    Args:
        residual: a :class:`ResidualFunction` (or anything with ``value``/``linearize``).
        theta: ``(n,)`` the point.
        direction: ``(n,)`` the direction ``v`` (any non-zero norm).
        lin: the linearisation at ``theta`` if already made (saves one forward solve).
        order: 2 (remainder without the first-order term ``h J v``, rate 2 expected) or
            1 (``||r(theta + h v) - r(theta)||``, rate 1: no Jacobian involved).
        n_steps: number of steps; the first changes ``theta`` by ``relative_step`` of its
            norm (``||h_0 v|| = relative_step * ||theta||``, ``||theta||`` taken as 1 at
            zero), each next one is half the previous.
        safety: a remainder below ``safety * eps * (||r(theta + h v)|| + ||r(theta)|| +
            ||data|| + h ||J v||)`` is round-off dominated; so is any remainder below 100
            times the plateau the remainders settle on once they stop decreasing. Such a
            step and all smaller ones are discarded.
        window_tol: the rates of the asymptotic window lie within this of their median.
        min_window: fewest rates in the window before the last rates are blamed on
            round-off and dropped (``max_drop`` of them at most).
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order}")
    if n_steps < 3:
        raise ValueError(f"the Taylor test needs at least 3 steps, got {n_steps}")
    theta = theta.detach()
    direction = direction.detach().to(theta)
    v_norm = _direction_norm(direction)
    if lin is None:
        lin = residual.linearize(theta)
    r0 = lin.r.detach()
    eps = torch.finfo(r0.dtype).eps
    jv = lin.jvp(direction).detach() if order == 2 else torch.zeros_like(r0)
    jv_norm = _norm(jv)
    data = getattr(residual, "data", None)
    data_norm = _norm(data) if isinstance(data, Tensor) else 0.0
    r0_norm = _norm(r0)
    accuracy = float(getattr(residual, "accuracy", None) or 0.0)

    h0 = relative_step * _scale(theta) / v_norm
    steps = [h0 * 2.0 ** -i for i in range(n_steps)]
    remainders: list[float] = []
    floors: list[float] = []
    for h in steps:
        try:
            r_h = residual.value(theta + h * direction).detach()
        except _STEP_ERRORS:
            remainders.append(math.nan)
            floors.append(math.nan)
            continue
        e = _norm(r_h - r0 - h * jv)
        remainders.append(e if math.isfinite(e) else math.nan)
        # round-off of forming r = y - data (relative to everything, the data included),
        # or the simulation's own tolerance (residual.accuracy, e.g. Newton's rtol:
        # remainders below ~10x that are its noise, not Taylor's h^2), relative to the
        # residuals: a Newton-solved position is exact to rtol of what it moved, not of
        # where it is (docs/notes/verification.md).
        size = _norm(r_h) + r0_norm + h * jv_norm
        floors.append(max(eps * (size + data_norm), 10.0 * accuracy * size / safety))

    finite = [e for e in remainders if math.isfinite(e)]
    if not finite:
        raise RuntimeError("the residual could not be evaluated at any Taylor step; check "
                           "that theta is a valid point")
    threshold = [safety * f if math.isfinite(f) else math.nan for f in floors]
    # Empirical floor: where the remainders, already far below their largest value,
    # stop decreasing they sit on round-off (solver error amplified by conditioning).
    # "Stop" is a halving of h that removes less than 10 % of the remainder (a rate
    # below 0.15) once it has fallen two decades (docs/notes/verification.md). The slow
    # decrease must last (the next three halvings stay above half of it): where a wrong
    # J v's first-order error cancels the second-order term, the remainders dip once and
    # then fall at rate 1 again, which is a finding, not a floor.
    e_max = max(finite)

    def lasts(i: int) -> bool:
        later = [e for e in remainders[i + 1:i + 4] if math.isfinite(e)]
        return len(later) == 3 and min(later) >= 0.5 * remainders[i]

    for i in range(1, n_steps):
        prev, cur = remainders[i - 1], remainders[i]
        if math.isfinite(prev) and math.isfinite(cur) and (
                (cur >= prev and cur <= 1e-6 * e_max)
                or (cur >= 0.9 * prev and cur <= 1e-2 * e_max and lasts(i))):
            tail = [e for e in remainders[i - 1:] if math.isfinite(e)]
            plateau = 100.0 * statistics.median(tail)
            threshold = [max(t, plateau) if math.isfinite(t) else t for t in threshold]
            break
    roundoff = [math.isfinite(e) and e <= t for e, t in zip(remainders, threshold)]
    expected = float(order)

    def result(rates: list[float], rate: float, window: tuple[int, int], linear: bool) -> TaylorResult:
        return TaylorResult(steps=steps, remainders=remainders, rates=rates, rate=rate,
                            window=window, linear=linear, expected=expected,
                            roundoff=roundoff, threshold=threshold, order=order)

    if all(roundoff[i] for i in range(n_steps) if math.isfinite(remainders[i])):
        return result([math.nan] * (n_steps - 1), math.nan, (0, 0), True)

    # Usable steps: from the first evaluable, non-round-off step (large-step failures
    # are pre-asymptotic) to the first step that is round-off dominated or failed.
    start = next(i for i in range(n_steps) if math.isfinite(remainders[i]) and not roundoff[i])
    stop = start
    while stop < n_steps and math.isfinite(remainders[stop]) and not roundoff[stop]:
        stop += 1
    rates = [math.nan] * (n_steps - 1)
    for i in range(start, stop - 1):
        a, b = remainders[i], remainders[i + 1]
        rates[i] = math.log2(a / b) if a > 0 and b > 0 else math.nan
    # Asymptotic window: the last stable run of rates before round-off (trailing rates
    # that disagree with it are dropped, up to the point where the run is long enough).
    first, last = start, stop - 1                         # rates[first:last] usable
    if last - first < 1:
        # One usable remainder: it falls to round-off within one halving, i.e. the
        # residual is linear along v to machine precision.
        return result(rates, math.nan, (first, first), True)
    # At most ``max_drop`` trailing rates are dropped: a clean run of wrong rates just
    # above round-off is a finding, not noise.
    best = (last - 1, last)
    for end in range(last, max(first, last - max_drop - 1), -1):
        lo = end - 1
        while lo > first and _stable(rates[lo - 1:end], window_tol):
            lo -= 1
        if end - lo > best[1] - best[0]:
            best = (lo, end)
        if end - lo >= min_window or end - first <= min_window:
            break
    window_rates = [r for r in rates[best[0]:best[1]] if math.isfinite(r)]
    rate = statistics.median(window_rates) if window_rates else math.nan
    return result(rates, rate, best, False)


def _stable(rates: list[float], tol: float) -> bool:
    if not all(math.isfinite(r) for r in rates):
        return False
    mid = statistics.median(rates)
    return all(abs(r - mid) <= tol for r in rates)


# -- dot-product test -----------------------------------------------------------------
@dataclasses.dataclass
class DotProductResult:
    """``<J v, w>`` against ``<v, J^T w>``."""

    jv_w: float
    v_jtw: float
    rel_error: float

    def passed(self, tol: float = 1e-10) -> bool:
        return math.isfinite(self.rel_error) and self.rel_error <= tol

    def to_dict(self) -> dict[str, Any]:
        return {"jv_w": self.jv_w, "v_jtw": self.v_jtw, "rel_error": _json_float(self.rel_error)}


def dot_product_test(lin: _Linearization, v: Tensor, w: Tensor) -> DotProductResult:
    """Relative error ``|<J v, w> - <v, J^T w>| / max(|<J v, w>|, |<v, J^T w>|)`` (0 if both 0)."""
    jv = lin.jvp(v).detach()
    jtw = lin.vjp(w).detach()
    if jv.shape != w.shape or jtw.shape != v.shape:
        raise ValueError(f"J v has shape {tuple(jv.shape)} for w {tuple(w.shape)}, J^T w has "
                         f"shape {tuple(jtw.shape)} for v {tuple(v.shape)}")
    a = float(torch.dot(jv, w.to(jv)))
    b = float(torch.dot(v.to(jtw), jtw))
    denom = max(abs(a), abs(b))
    rel = 0.0 if denom == 0 else abs(a - b) / denom
    return DotProductResult(jv_w=a, v_jtw=b, rel_error=rel if math.isfinite(rel) else math.nan)


# -- finite differences ---------------------------------------------------------------
@dataclasses.dataclass
class FiniteDifferenceResult:
    """Central difference ``(r(theta + h v) - r(theta - h v)) / 2h`` against ``J v``."""

    step: float
    jv_norm: float
    fd_norm: float
    rel_error: float

    def passed(self, tol: float = 1e-6) -> bool:
        return math.isfinite(self.rel_error) and self.rel_error <= tol

    def to_dict(self) -> dict[str, Any]:
        return {"step": self.step, "jv_norm": self.jv_norm, "fd_norm": self.fd_norm,
                "rel_error": _json_float(self.rel_error)}


def finite_difference_test(residual: _Residual, lin: _Linearization, v: Tensor,
                           theta: Tensor | None = None, step: float | None = None
                           ) -> FiniteDifferenceResult:
    """Relative 2-norm error of the central difference of ``r`` along ``v`` against ``J v``.

    Args:
        theta: the point of ``lin`` (default ``lin.theta``).
        step: ``h``; default ``a^(1/3) ||theta|| / ||v||`` (``||theta||`` taken as 1 at
            zero) with ``a`` the residual's ``accuracy`` (machine epsilon by default), which
            balances the ``h^2`` truncation and ``a / h`` errors.
    """
    if theta is None:
        theta = getattr(lin, "theta", None)
        if theta is None:
            raise ValueError("pass theta: the linearisation does not record its point")
    theta = theta.detach()
    v = v.detach().to(theta)
    v_norm = _direction_norm(v)
    if step is None:
        # balance the h^2 truncation against the error of r itself: round-off, or the
        # tolerance a simulation is solved to (residual.accuracy, e.g. Newton's rtol)
        accuracy = max(getattr(residual, "accuracy", None) or 0.0, torch.finfo(theta.dtype).eps)
        step = accuracy ** (1.0 / 3.0) * _scale(theta) / v_norm
    jv = lin.jvp(v).detach()
    fd = (residual.value(theta + step * v) - residual.value(theta - step * v)).detach() / (2 * step)
    jv_norm, fd_norm = _norm(jv), _norm(fd)
    err = _norm(fd - jv)
    denom = max(jv_norm, fd_norm)
    rel = 0.0 if denom == 0 else err / denom
    return FiniteDifferenceResult(step=float(step), jv_norm=jv_norm, fd_norm=fd_norm,
                                  rel_error=rel if math.isfinite(rel) else math.nan)


# -- everything at one point ----------------------------------------------------------
@dataclasses.dataclass
class VerificationReport:
    """The three checks at one ``theta`` and whether each passed."""

    taylor: TaylorResult
    dot: DotProductResult
    fd: FiniteDifferenceResult
    taylor_tol: float
    dot_tol: float
    fd_tol: float
    seed: int
    n_params: int
    n_data: int
    residual_norm: float
    dot_tol_basis: str = "given"

    @property
    def taylor_passed(self) -> bool:
        return self.taylor.passed(self.taylor_tol)

    @property
    def dot_passed(self) -> bool:
        return self.dot.passed(self.dot_tol)

    @property
    def fd_passed(self) -> bool:
        return self.fd.passed(self.fd_tol)

    @property
    def passed(self) -> bool:
        return self.taylor_passed and self.dot_passed and self.fd_passed

    def to_dict(self) -> dict[str, Any]:
        return {
            "taylor_rate": _json_float(self.taylor.rate),
            "taylor_linear": self.taylor.linear,
            "dot_product_rel_error": _json_float(self.dot.rel_error),
            "fd_rel_error": _json_float(self.fd.rel_error),
            "passed": self.passed,
            "taylor_passed": self.taylor_passed,
            "dot_product_passed": self.dot_passed,
            "fd_passed": self.fd_passed,
            "tolerances": {"taylor_tol": self.taylor_tol, "dot_tol": self.dot_tol,
                           "fd_tol": self.fd_tol, "dot_tol_basis": self.dot_tol_basis},
            "seed": self.seed, "n_params": self.n_params, "n_data": self.n_data,
            "residual_norm": self.residual_norm,
            "taylor": self.taylor.to_dict(),
            "dot_product": self.dot.to_dict(),
            "finite_difference": self.fd.to_dict(),
        }

    def format(self) -> str:
        return format_report(self)


#: the finite-difference check's floor, and the factor on its own resolution ``a^(2/3)``
FD_TOL_FLOOR, FD_TOL_FACTOR = 1e-6, 100.0


def default_fd_tol(residual: _Residual, dtype: torch.dtype = torch.float64) -> float:
    """What a central difference can resolve for ``residual``: ``max(1e-6, 100 a^(2/3))``
    with ``a`` its ``accuracy`` (machine epsilon when exact): the step of
    :func:`finite_difference_test` leaves a relative error of order ``a^(2/3)`` times the
    simulation's conditioning (figures: ``docs/notes/verification.md``)."""
    accuracy = max(getattr(residual, "accuracy", None) or 0.0, torch.finfo(dtype).eps)
    return max(FD_TOL_FLOOR, FD_TOL_FACTOR * accuracy ** (2.0 / 3.0))


#: the dot-product check's bound for exact transposes, and the factor on a residual's
#: ``product_consistency`` (measured 2.5-54 times ``rtol``: ``docs/notes/verification.md``)
DOT_TOL_EXACT, DOT_TOL_FACTOR = 1e-10, 1e3


def default_dot_tol(residual: _Residual) -> tuple[float, str]:
    """The dot-product check's bound for ``residual`` and why: ``1e-10`` where ``J^T w``
    is the exact transpose of ``J v`` (``product_consistency`` ``None``: a discrete
    adjoint, an explicit chain; round-off only), else ``max(1e-10, 1000 c)`` with
    ``c = product_consistency``.

    Why ``1000 c``: where the reverse product is a continuous adjoint and the forward one
    the forward sensitivities (torchdiffeq), each is accurate to the ODE tolerance ``c``
    (``rtol``) on its own, and the two disagree by a multiple of it that the
    conditioning of the trajectory sets (the adjoint integrates the state back through
    damping, which amplifies). Measured on the 64-spring chain over 6 s (dopri5): 54,
    2.5 and 18 times ``rtol`` = 1e-6, 1e-8, 1e-10; 1000 leaves 18 times the worst.
    A transposed or wrongly scaled adjoint (1e-3 off and more) still fails it.
    """
    consistency = getattr(residual, "product_consistency", None)
    if consistency is None:
        return DOT_TOL_EXACT, "exact transpose: round-off"
    consistency = float(consistency)
    tol = max(DOT_TOL_EXACT, DOT_TOL_FACTOR * consistency)
    return tol, (f"{DOT_TOL_FACTOR:g} x product consistency {consistency:g} (J^T w and J v "
                 "are separate approximations, each to the ODE tolerance)")


def verify(residual: _Residual, theta: Tensor, seed: int = 0, taylor_tol: float = 0.05,
           dot_tol: float | None = None, fd_tol: float | None = None, **taylor_options: Any
           ) -> VerificationReport:
    """Taylor, dot-product and finite-difference checks of ``J`` at ``theta``.

    Directions ``v`` (parameters) and ``w`` (data) are unit Gaussian vectors from
    ``torch.Generator().manual_seed(seed)``; ``taylor_options`` go to :func:`taylor_test`.
    ``fd_tol=None``: :func:`default_fd_tol` (1e-6 for exact simulations, looser for those
    solved to a tolerance). ``dot_tol=None``: :func:`default_dot_tol` (1e-10 for exact
    transposes, ``1000 rtol`` for a continuous adjoint against forward sensitivities); the
    report says which (``dot_tol_basis``).
    """
    if fd_tol is None:
        fd_tol = default_fd_tol(residual, theta.dtype)
    if dot_tol is None:
        dot_tol, dot_basis = default_dot_tol(residual)
    else:
        dot_basis = "given"

    for name, tol in (("taylor_tol", taylor_tol), ("dot_tol", dot_tol), ("fd_tol", fd_tol)):
        if not (tol > 0 and math.isfinite(tol)):
            raise ValueError(f"{name} must be a positive number, got {tol}")
    theta = theta.detach()
    if theta.dim() != 1:
        raise ValueError(f"theta must be a flat vector, got shape {tuple(theta.shape)}")
    if not bool(torch.isfinite(theta).all()):
        raise ValueError("theta contains NaN or infinite values")
    generator = torch.Generator().manual_seed(int(seed))
    lin = residual.linearize(theta)
    v = random_direction(theta.numel(), generator, theta)
    w = random_direction(lin.r.numel(), generator, lin.r)
    taylor = taylor_test(residual, theta, v, lin=lin, **taylor_options)
    dot = dot_product_test(lin, v, w)
    fd = finite_difference_test(residual, lin, v, theta=theta)
    return VerificationReport(taylor=taylor, dot=dot, fd=fd, taylor_tol=taylor_tol,
                              dot_tol=dot_tol, fd_tol=fd_tol, seed=int(seed),
                              n_params=int(theta.numel()), n_data=int(lin.r.numel()),
                              residual_norm=_norm(lin.r), dot_tol_basis=dot_basis)


def format_report(report: VerificationReport | TaylorResult) -> str:
    """Short human-readable table: step, remainder, rate (``*``: in the window,
    ``~``: round-off), then one line per check."""
    taylor = report.taylor if isinstance(report, VerificationReport) else report
    lo, hi = taylor.window
    term = "r(t+hv) - r(t) - h Jv" if taylor.order == 2 else "r(t+hv) - r(t)"
    lines = [f"Taylor test: e(h) = ||{term}||, expected rate {taylor.expected:g}",
             f"  {'i':>3}  {'h':>10}  {'e(h)':>10}  {'rate':>7}"]
    for i, (h, e) in enumerate(zip(taylor.steps, taylor.remainders)):
        rate = taylor.rates[i - 1] if i > 0 else math.nan
        rate_s = f"{rate:7.3f}" if math.isfinite(rate) else f"{'-':>7}"
        mark = "*" if lo < i <= hi else ("~" if taylor.roundoff[i] else " ")
        lines.append(f"  {i:>3}  {h:10.3e}  {e:10.3e}  {rate_s} {mark}")
    lines.append("  (* asymptotic window, ~ round-off dominated)")

    def verdict(ok: bool) -> str:
        return "ok" if ok else "FAIL"

    if taylor.linear:
        lines.append("Taylor rate: residual is linear along v (remainders at round-off)")
    else:
        lines.append(f"Taylor rate: {taylor.rate:.4f} (median of {hi - lo} rate(s), steps "
                     f"{lo}..{hi})")
    if isinstance(report, VerificationReport):
        if taylor.linear:
            lines[-1] += f"  [{verdict(report.taylor_passed)}]"
        else:
            lines[-1] += (f"  [{verdict(report.taylor_passed)}: |rate - {taylor.expected:g}| "
                          f"<= {report.taylor_tol:g}]")
        lines.append(f"dot product: <Jv,w> = {report.dot.jv_w:.12e}, <v,J^T w> = "
                     f"{report.dot.v_jtw:.12e}, rel. error {report.dot.rel_error:.3e}  "
                     f"[{verdict(report.dot_passed)}: <= {report.dot_tol:g}, "
                     f"{report.dot_tol_basis}]")
        lines.append(f"finite differences: h = {report.fd.step:.3e}, ||Jv|| = "
                     f"{report.fd.jv_norm:.6e}, rel. error {report.fd.rel_error:.3e}  "
                     f"[{verdict(report.fd_passed)}: <= {report.fd_tol:g}]")
        lines.append(f"verification {'PASSED' if report.passed else 'FAILED'} "
                     f"(n_params={report.n_params}, n_data={report.n_data}, "
                     f"||r|| = {report.residual_norm:.6e}, seed={report.seed})")
    return "\n".join(lines)


def _json_float(x: float) -> float | None:
    """``nan``/``inf`` become ``None`` so that result files stay strict JSON."""
    return float(x) if math.isfinite(x) else None
