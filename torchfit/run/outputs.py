"""The outputs of a run with a directory: its observers, and every file at its end.

Run directory (besides ``checkpoint.pt`` and ``history.jsonl``, :mod:`.checkpoint`):
``result.json`` (:mod:`.result`); ``params.pt`` and ``field.npy``, the fitted ``theta``
and field (byte-identical for identical runs; ``init=`` of a later run starts from
``params.pt``); ``tb/``, TensorBoard events (:mod:`torchfit.reporting.tensorboard`; a
resumed run adds the steps lost with the killed process and never repeats one);
``field.png``, ``error_curves.png``, ``identifiability.json`` / ``.vtu`` / ``.png``
(:mod:`torchfit.reporting.identifiability`), ``uncertainty.json`` (the posterior spread of
every parameter and region, :mod:`.uncertainty`) and what the problem's own outputs write:
``snapshots.png``, ``frame_errors.png``, ``sheet_frame<f>.png`` for 2-D fields
(:class:`~torchfit.reporting.field_snapshots.FieldSnapshots`), ``frames.npz`` for meshes,
the files of a 3-D body (:class:`~torchfit.reporting.body.BodyOutputs`) and of a dynamic
problem (:class:`~torchfit.reporting.motion.MotionOutputs`). A drawing that fails is
warned about once (:class:`~torchfit.reporting.guard.PlotGuard`) and never fails the run.

Every output reads the run's evaluations (:mod:`.evaluator`): one per record, one at the end
(the last record's, when the run ended there); the only states simulated here are a 3-D
body's model comparison (its baseline when the run did not start at the homogeneous
material, and the other model), through the evaluator.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..problems import (BodyProblem, FieldImageProblem, InverseProblem, MeshProblem,
                        MotionProblem, parameter_meaning)
from ..records import IterationRecord
from ..reporting import (BodyOutputs, Evaluation, FieldSnapshots, MotionOutputs, PROGRESS_LOGGER,
                         PlotGuard, RESULT_FILE, TensorBoardLogger, atomic_write, event_files,
                         field_is_chain, modulus_units, save_params, write_identifiability,
                         write_json, write_run_pngs)
from .checkpoint import Resume
from .evaluator import Evaluator
from .options import FitOptions
from .result import FitResult, result_dict, time_integration_text
from .uncertainty import Uncertainty
from .validation import result_values

progress = logging.getLogger(PROGRESS_LOGGER)

#: the fit's uncertainty (:mod:`.uncertainty`), per parameter
UNCERTAINTY_FILE = "uncertainty.json"


class RunOutputs:
    """TensorBoard and the problem's own observers of a run, and its files at the end.

    Args:
        run_dir: the run directory (exists).
        problem: the problem being fitted.
        evaluator: the run's evaluator (it feeds the observers).
        options: the run's options.
        config: the settings stored in ``result.json`` and TensorBoard.
        restart: the checkpoint a resumed run continues (``None``: a fresh run).
    """

    def __init__(self, run_dir: Path, problem: InverseProblem, evaluator: Evaluator,
                 options: FitOptions, config: Mapping[str, Any], restart: Resume | None) -> None:
        self.run_dir = run_dir
        self.problem = problem
        self.evaluator = evaluator
        self.config = config
        self.guard = PlotGuard()    # a failed drawing is warned about once, never fails the fit
        if restart is None:
            # a fresh start (allowed: nothing committed here) begins its curves afresh; the
            # events of a run killed before its first commit would show beside them
            for stale in event_files(run_dir / "tb"):
                stale.unlink()
                progress.debug("removed %s of a run that committed nothing", stale)
        self.tb = TensorBoardLogger(run_dir / "tb", log_every=options.log_every)
        if restart is not None:
            self.tb.resume(restart.rows, restart.iteration)
        else:
            self.tb.log_config(json.dumps(config, indent=2, default=str))
        self.snapshots = self.body = self.motion = None
        if isinstance(problem, FieldImageProblem):
            self.snapshots = FieldSnapshots(problem, self.tb, run_dir,
                                            list(options.snapshot_iterations),
                                            options.snapshot_every, options.sheet_frame,
                                            guard=self.guard)
        if isinstance(problem, BodyProblem):
            self.body = BodyOutputs(problem, self.tb, run_dir, guard=self.guard,
                                    suggest_continuation=options.fold_hint)
            # the per-frame errors of the iterations before the checkpoint (a resume draws
            # frame_errors_history.png over the whole fit)
            self.body.restore_history(None if restart is None else restart.iteration)
        if isinstance(problem, MotionProblem):
            self.motion = MotionOutputs(problem, self.tb, run_dir,
                                        list(options.snapshot_iterations), guard=self.guard)

    def callbacks(self) -> list[Callable[[IterationRecord], Any]]:
        """The record callbacks, in their order: TensorBoard first, then the problem's own
        observers (fed the evaluator's evaluation of the record)."""
        observers = [o for o in (self.snapshots, self.body, self.motion) if o is not None]
        return [self.tb, *(self.evaluator.feed(o) for o in observers)]

    def flush(self) -> None:
        self.tb.flush()

    def finish(self, result: FitResult, final: Evaluation) -> list[Path]:
        """Every file of a finished run (``final``: the run's evaluation at its end); returns
        the pictures and data files written, and sets ``result.highlights``."""
        problem, run_dir = self.problem, self.run_dir
        files = self.snapshots.finish(final) if self.snapshots is not None else []
        if self.motion is not None:
            files.extend(self.motion.finish(final))
        comparison: dict[str, Any] = {}
        if self.body is not None:
            self.body.kept_start = result.kept_start     # its USD material says not fitted
            self.body.uncertainty = body_uncertainty(result.uncertainty)
            files.extend(self.body.finish(final))
            states = self.guard.run("model comparison", self._comparison_states, final)
            if states is not None:
                written, comparison = self.body.compare(final, *states)
                files.extend(written)
            files.extend(self.body.copy_animation())
            result.highlights.extend(self.body.highlights)
        metrics = {**result.metrics, "iterations": result.iterations, "wall_s": result.wall_s}
        if result.validation is not None:   # final/validation_*: one value per run
            metrics.update({k: v for k, v in result_values(result.validation).items()
                            if v is not None})
        hparams = {"problem": self.config.get("problem", {}),
                   "solver": self.config.get("solver", {})}
        self.tb.finish(problem, final.field, metrics, hparams, self.guard)
        files[:0] = list(save_params(run_dir, result.theta, result.field, problem.field_name,
                                     problem.parameterization.transform,
                                     parameter_meaning(problem)))
        if isinstance(problem, MeshProblem):
            _save_frames(run_dir / "frames.npz", problem, final)
            files.append(run_dir / "frames.npz")
        summary = result_dict(problem, result, self.config)
        if isinstance(problem, MotionProblem):
            try:
                timing = problem.time.report(problem.simulation_input(final.theta),
                                             result.metrics)
            except Exception as error:  # noqa: BLE001  (an estimate; the fit stands)
                timing = None
                progress.warning("could not estimate the integration error at the fitted "
                            "parameters (%s: %s); the fit and its result files are not "
                            "affected", type(error).__name__, error)
            if timing is not None:
                summary["time_integration"] = timing
                result.highlights.insert(0, time_integration_text(
                    timing, metres=isinstance(problem, BodyProblem)))
                for line in timing.get("warnings", []):   # the damping, the step's error
                    progress.warning("%s", line)
                    result.highlights.insert(1, f"warning: {line}")
        if isinstance(problem, BodyProblem):
            summary["modulus_units"] = modulus_units(problem).as_dict()
        if comparison:
            summary["model_comparison"] = {"frame": comparison["frame"]}
            for material in ("homogeneous", "fitted"):
                summary["model_comparison"][material] = {
                    name: {k: v for k, v in values.items() if not k.endswith("_per_frame")}
                    for name, values in comparison[material].items()}
        write_json(run_dir / RESULT_FILE, summary)
        if result.uncertainty is not None:
            write_json(run_dir / UNCERTAINTY_FILE, result.uncertainty.as_json())
            files.append(run_dir / UNCERTAINTY_FILE)
        if result.identifiability is not None:
            report = result.identifiability
            mesh = problem.mesh if isinstance(problem, MeshProblem) else None
            regions = problem.tet_regions if isinstance(problem, BodyProblem) else None
            files.extend(write_identifiability(
                run_dir, mesh, regions, report.as_json(),
                {"sensitivity": report.cell_sensitivity, "determined": report.cell_determined},
                self.guard))
        files[:0] = write_run_pngs(run_dir, problem, final.field, result.history, self.guard,
                                   field_is_chain(problem))
        return files

    def _comparison_states(self, final: Evaluation
                           ) -> tuple[Evaluation, dict[str, dict[str, Any]]]:
        """What a 3-D body's model comparison shows: the homogeneous material's evaluation
        (iteration 0's, else simulated cold now) and the other models' states."""
        assert self.body is not None
        baseline = self.body.baseline
        if baseline is None:   # a resumed run missed iteration 0; an init= run started elsewhere
            baseline = self.evaluator.evaluate(self.problem.theta0, independent=True)
        if self.body.comparison_models():
            progress.info("simulating the linear model for the comparison (%d frames)",
                          self.problem.n_frames)
        others = {material: {model: self.evaluator.other_model(model, evaluation.field)
                             for model in self.body.comparison_models()}
                  for material, evaluation in (("homogeneous", baseline), ("fitted", final))}
        return baseline, others


def body_uncertainty(report: Uncertainty | None) -> dict[str, Any] | None:
    """What a body's files carry of the uncertainty: ``regions`` (for ``regions.json``,
    with the second mesh's fit where ``problem.mesh_check``) and ``cell_band`` (the
    two-sigma factor per tetrahedron, ``exp`` transform only, for ``usd/body.usda``)."""
    if report is None:
        return None
    if not report.computed:
        return {"regions": {"computed": False, "reason": report.reason}}
    regions: dict[str, Any] = {"meaning": report.summary()["meaning"], "sigma": report.sigma,
                               "sigma_source": report.sigma_source, "gauge": report.gauge,
                               "regions": report.regions}
    if report.mesh_check is not None:
        regions["mesh_check"] = report.mesh_check
    band = report.factor(report.cell_sd) if report.relative and report.cell_sd is not None \
        else None
    return {"regions": regions, "cell_band": band}


def _save_frames(path: Path, problem: Any, final: Evaluation) -> None:
    """Rest points, cells, fitted (and true) positions of every frame of a mesh problem."""
    arrays = {"rest_points": problem.mesh.points, "cells": problem.mesh.cells,
              "positions": final.state.detach().cpu().numpy(),
              "field": final.field.detach().cpu().numpy()}
    if problem.x_true is not None:
        arrays["true_positions"] = problem.x_true.detach().cpu().numpy()

    def write(f) -> None:
        np.savez_compressed(f, **arrays)

    atomic_write(path, write)
