"""What a run returns (:class:`FitResult`) and what its ``result.json`` holds.

``result.json``: the final metrics (docs/problems.md), ``iterations``, ``wall_s``,
``factorizations``, ``solves`` (whole-run totals, a resumed run included), ``converged``,
``stop_reason``, ``status`` (``completed``), ``resumed_from_iteration`` (a resumed run),
``problem`` (sizes), ``config`` and ``history`` (one row per outer iteration); a 3-D body
adds ``model_comparison``. ``determined`` (whether the data determine the material at all)
and ``identifiability`` (its summary, :mod:`.identifiability`) where the run made the report
(``fitted_field`` says that the outputs keep the starting field where it is false);
``uncertainty`` (the posterior spread's summary, :mod:`.uncertainty`) where the run made one;
a 3-D body adds ``modulus_units`` (what its written moduli are:
:class:`~torchfit.reporting.body_files.ModulusUnits`);
a run with frames held out of the fit adds ``validation_iteration``,
``validation_surface_err_mean``, ``validation_surface_err_reduction`` and ``validation``
(:mod:`.validation`).
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Mapping

from torch import Tensor

from ..problems import InverseProblem
from ..records import SolveResult
from .validation import held_out_worse, result_values


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`~torchfit.run.fit`.

    Attributes:
        theta: ``(n_params,)`` fitted parameters; ``field`` the physical field.
        metrics: the final metrics of docs/problems.md.
        iterations, wall_s, factorizations, solves: whole-run totals (a resumed run
            included).
        converged, stop_reason: as the solver reports them.
        history: one row per outer iteration of the whole run (``iteration`` and every
            record scalar, metrics included).
        run_dir: the run directory (``None`` without files); ``files`` what was written.
        resumed_from: the iteration a resumed run continued after (``None``: fresh).
        solve: the solver's own result for this process's part of the run.
        first_stage: the first stage of a continuation
            (:func:`~torchfit.run.fit_continued`), else ``None``.
        highlights: one line per output worth pointing a user at (written by the outputs
            themselves, e.g. a 3-D body's comparison picture and ParaView file).
        identifiability: the report of what the data determine
            (:class:`~.identifiability.Identifiability`), ``None`` where none was made (a
            finished run read back); ``determined`` its verdict (``None``: no report).
        validation: ``result.json``'s ``validation`` section (frames held out of the fit:
            the chosen iteration, the errors there and at the end), else ``None``.
        kept_start: the data determine no material, so ``theta``, ``field`` and
            ``metrics`` are the start's, not where the solver stopped (and ``converged``
            is false).
        uncertainty: the posterior spread of the fitted numbers
            (:class:`~.uncertainty.Uncertainty`), ``None`` where none was made.
    """

    theta: Tensor
    field: Tensor
    metrics: dict[str, float]
    iterations: int
    wall_s: float
    factorizations: int
    solves: int
    converged: bool
    stop_reason: str
    history: list[dict[str, float]]
    run_dir: Path | None = None
    files: list[Path] = dataclasses.field(default_factory=list)
    resumed_from: int | None = None
    solve: SolveResult | None = None
    first_stage: "FitResult | None" = None
    highlights: list[str] = dataclasses.field(default_factory=list)
    identifiability: Any = None
    validation: dict[str, Any] | None = None
    kept_start: bool = False
    uncertainty: Any = None

    @property
    def determined(self) -> bool | None:
        return None if self.identifiability is None else bool(self.identifiability.determined)

    def value(self, key: str) -> float:
        """``metrics[key]``, a count (``iterations``, ...) or a validation value
        (``validation_surface_err_mean``, ...); ``+inf`` where not finite or missing, so
        that a sweeper ranks such a run last."""
        counts: dict[str, Any] = {"iterations": self.iterations, "wall_s": self.wall_s,
                                  "factorizations": self.factorizations, "solves": self.solves}
        if self.validation is not None:
            counts.update(result_values(self.validation))
        raw = self.metrics[key] if key in self.metrics else counts[key]
        value = math.nan if raw is None else float(raw)
        return value if math.isfinite(value) else math.inf

    def summary(self) -> str:
        """One line a TD reads: where the problem has a surface, its error (mean, max, and
        how far below the homogeneous material's) on the fitted frames and on the held-out
        ones (with the iteration they chose, and a warning where they end worse than with the
        homogeneous material), else the headline metrics; the verdict (whether the data
        determine the material, :meth:`~.identifiability.Identifiability.verdict`); the stop
        reason, iterations, time and counts (an undetermined fit: never "converged")."""
        if "surface_err_mean" in self.metrics:
            told = f"surface error on the fitted frames {surface_error_text(self.metrics)}"
            if self.validation is not None:
                section = self.validation
                chosen = section.get("chosen", {})
                told += (f"; on the held-out frames {surface_error_text(section.get('final', {}))}"
                         f" (best held-out at iteration {section.get('iteration')}: "
                         f"{_mm(chosen.get('surface_err_mean'))} mean, {section.get('params')})")
                worse = held_out_worse(section)
                if worse:
                    told += f"; {worse}"
        else:
            told = ", ".join(f"{k} {self.metrics[k]:.3e}" for k in
                             ("misfit", "k_err_rel", "k_err_rel_aligned") if k in self.metrics)
        verdict = "" if self.identifiability is None else f"; {self.identifiability.verdict()}"
        # an undetermined fit's stop means nothing: never "converged"
        stop = "converged" if self.converged and self.determined is not False else \
            "not converged"
        misfit = f", misfit {self.metrics['misfit']:.3e}" if "misfit" in self.metrics and \
            "surface_err_mean" in self.metrics else ""
        return (f"{told}{verdict}; stopped by {self.stop_reason} after {self.iterations} "
                f"iterations ({stop}) in {self.wall_s:.1f} s, {self.factorizations} "
                f"factorizations, {self.solves} solves{misfit}{self._uncertainty_text()}")

    def _uncertainty_text(self) -> str:
        """The summary's piece on the uncertainty (:meth:`.uncertainty.Uncertainty.text`):
        none where no report was made or the outputs keep the start."""
        if self.uncertainty is None or self.kept_start:
            return ""
        return f"; {self.uncertainty.text()}"


def time_integration_text(report: Mapping[str, Any], metres: bool = False) -> str:
    """``in time: 24 fps x 4 substeps = 44 BDF2 steps of 10.4 ms; integration error about
    0.0031 mm, 1.2e-05 of the largest displacement (estimated against 88 steps)``: what a
    motion's ``time_integration`` report says (positions in metres where ``metres``)."""
    if report.get("integrator") != "implicit":
        return (f"in time: torchdiffeq {report.get('method')}, adaptive steps (error "
                f"controlled to rtol {report.get('rtol'):g}, atol {report.get('atol'):g})")
    scheme = {"bdf2": "BDF2", "backward_euler": "backward Euler"}.get(report["scheme"],
                                                                      report["scheme"])
    rate = f"{report['fps']:g} fps x {report['substeps']} substeps = " if "fps" in report else ""
    error = _mm(report["error_estimate"]) if metres else f"{report['error_estimate']:.3g}"
    return (f"in time: {rate}{report['steps']} {scheme} steps of {1e3 * report['dt']:.3g} ms; "
            f"integration error about {error}, {report['error_estimate_rel']:.2g} of the "
            f"largest displacement (estimated against {report['reference_steps']} steps)")


def _mm(metres: Any) -> str:
    return "-" if metres is None else f"{1e3 * float(metres):.3g} mm"


def surface_error_text(metrics: Mapping[str, Any]) -> str:
    """``0.549 mm mean, 11.2 mm max, 1.29x below the homogeneous material`` (what is known)."""
    text = f"{_mm(metrics.get('surface_err_mean'))} mean"
    if metrics.get("surface_err_max") is not None:
        text += f", {_mm(metrics['surface_err_max'])} max"
    if metrics.get("surface_err_reduction") is not None:
        text += f", {float(metrics['surface_err_reduction']):.3g}x below the homogeneous material"
    return text


def result_dict(problem: InverseProblem, result: FitResult,
                config: Mapping[str, Any]) -> dict[str, Any]:
    """The content of ``result.json`` (module docstring), without ``model_comparison``."""
    out: dict[str, Any] = {k: float(v) for k, v in result.metrics.items()}
    out.update({"iterations": result.iterations, "wall_s": result.wall_s,
                "factorizations": result.factorizations, "solves": result.solves,
                "converged": result.converged, "stop_reason": result.stop_reason,
                "status": "completed"})
    if result.identifiability is not None:
        out["determined"] = result.determined
        out["identifiability"] = result.identifiability.summary()
    if result.uncertainty is not None:
        out["uncertainty"] = result.uncertainty.summary()
    if result.kept_start:
        out["fitted_field"] = ("the starting field: the data determine no material, so the "
                               "outputs keep where the fit started (identifiability.json)")
    if result.resumed_from is not None:
        out["resumed_from_iteration"] = result.resumed_from
    if result.validation is not None:
        out.update(result_values(result.validation))
        out["validation"] = result.validation
    out["problem"] = problem.describe()
    out["config"] = dict(config)
    out["history"] = result.history
    return out
