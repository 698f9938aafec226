"""TensorBoardLogger: tag scheme, log_every, double-precision scalars, field and hparams."""
from __future__ import annotations

import math

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.util import tensor_util

from torchfit.logging import MetricsCallback, TensorBoardLogger, field_is_chain, tag_for
from torchfit.problems import build_problem
from torchfit.solvers import IterationRecord, gauss_newton


def read_events(logdir) -> EventAccumulator:
    acc = EventAccumulator(str(logdir), size_guidance={"scalars": 0, "tensors": 0,
                                                       "histograms": 0, "images": 0})
    acc.Reload()
    return acc


def series(acc: EventAccumulator, tag: str) -> list[tuple[int, float]]:
    """(step, value) of a scalar tag, new-style (double) or legacy."""
    if tag in acc.Tags()["tensors"]:
        return [(e.step, float(tensor_util.make_ndarray(e.tensor_proto))) for e in acc.Tensors(tag)]
    return [(e.step, float(e.value)) for e in acc.Scalars(tag)]


def record(i: int, **extra: float) -> IterationRecord:
    return IterationRecord(iteration=i, theta=torch.zeros(3), objective=0.5 / (i + 1) ** 2,
                           misfit=1.0 / (i + 1) + 1e-13 * i, step_norm=0.1 * i,
                           cg_iterations=i, damping=float("nan"), wall_time=0.01 * i,
                           factorizations=i, solves=3 * i, extra=dict(extra))


def test_tag_scheme():
    assert tag_for("misfit") == "fit/misfit"
    assert tag_for("objective") == "fit/objective"
    for key in ("u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel", "k_err_rel_aligned"):
        assert tag_for(key) == f"metrics/{key}"
    for key in ("cg_iterations", "damping", "step_norm", "solves", "factorizations",
                "wall_time", "eta", "gain_ratio"):
        assert tag_for(key) == f"solver/{key}"
    assert tag_for("custom/thing") == "custom/thing"


def test_log_every_keeps_first_and_last_and_skips_nan(tmp_path):
    with TensorBoardLogger(tmp_path, log_every=3) as tb:
        for i in range(8):
            tb(record(i, k_err_rel=1.0 / (i + 2), eta=0.1))
    acc = read_events(tmp_path)
    tags = set(acc.Tags()["tensors"])
    assert {"fit/misfit", "fit/objective", "metrics/k_err_rel", "solver/cg_iterations",
            "solver/step_norm", "solver/solves", "solver/factorizations", "solver/wall_time",
            "solver/eta"} <= tags
    assert "solver/damping" not in tags        # NaN damping is never written
    misfit = series(acc, "fit/misfit")
    assert [s for s, _ in misfit] == [0, 3, 6, 7]
    # double precision: the 1e-13 offset survives
    assert misfit[-1][1] == 1.0 / 8 + 7e-13


def test_step_offset_and_finite_damping(tmp_path):
    with TensorBoardLogger(tmp_path, step_offset=5) as tb:
        for i in range(3):
            rec = record(i)
            rec.damping = 10.0 ** -i
            tb(rec)
    acc = read_events(tmp_path)
    assert [s for s, _ in series(acc, "solver/damping")] == [5, 6, 7]
    assert series(acc, "solver/damping")[-1][1] == pytest.approx(0.01, rel=1e-15)


def test_finish_writes_field_histogram_figure_and_hparams(tmp_path):
    problem = build_problem("spring1d", {"n": 16, "noise": 1e-4})
    assert field_is_chain(problem)
    tb = TensorBoardLogger(tmp_path / "tb")
    result = gauss_newton(problem.residual(), problem.theta0, callbacks=[MetricsCallback(problem), tb])
    metrics = problem.metrics(result.theta)
    tb.finish(problem, result.theta, metrics,
              {"problem": {"name": "spring1d", "n": 16, "loads": [0.0, 1.0], "targets": None},
               "solver": {"name": "gauss_newton", "tau": 1.5}})
    acc = read_events(tmp_path / "tb")
    tags = acc.Tags()
    assert {"field/k", "field/k_true"} <= set(tags["histograms"])
    assert "field/k_profile" in tags["images"]
    assert set(acc.PluginTagToContent("hparams")) >= {"_hparams_/experiment",
                                                      "_hparams_/session_start_info"}
    steps = [s for s, _ in series(acc, "metrics/k_err_rel")]
    assert steps == list(range(result.iterations + 1))
    assert series(acc, "fit/misfit")[-1][1] == metrics["misfit"]
    assert math.isfinite(series(acc, "metrics/u_err_2")[-1][1])
