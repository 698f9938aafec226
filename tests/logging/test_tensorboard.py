"""TensorBoardLogger: tag scheme, log_every, double-precision scalars, field and hparams
(read back from the event files, the hparams also through the HParams plugin itself)."""
from __future__ import annotations

import math

import pytest
import torch
from tensorboard import context
from tensorboard.backend.event_processing import data_provider, plugin_event_multiplexer
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins import base_plugin
from tensorboard.plugins.hparams import (api_pb2, backend_context, get_experiment,
                                         list_session_groups)
from tensorboard.plugins.hparams import metadata as hparams_metadata
from tensorboard.util import tensor_util

from torchfit.logging import MetricsCallback, TensorBoardLogger, field_is_chain, tag_for
from torchfit.logging.tensorboard import hparam_values, metric_tag
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
    final = {**metrics, "iterations": result.iterations, "wall_s": result.wall_time}
    tb.finish(problem, result.theta, final,
              {"problem": {"name": "spring1d", "n": 16, "loads": [0.0, 1.0], "targets": None},
               "solver": {"name": "gauss_newton", "tau": 1.5, "verbose": False}})
    acc = read_events(tmp_path / "tb")
    tags = acc.Tags()
    assert {"field/k", "field/k_true"} <= set(tags["histograms"])
    assert "field/k_profile" in tags["images"]
    steps = [s for s, _ in series(acc, "metrics/k_err_rel")]
    assert steps == list(range(result.iterations + 1))
    assert series(acc, "fit/misfit")[-1][1] == metrics["misfit"]
    assert math.isfinite(series(acc, "metrics/u_err_2")[-1][1])
    # metrics without a per-iteration curve: once, at the last step
    assert series(acc, "final/iterations") == [(result.iterations, result.iterations)]
    assert series(acc, "final/wall_s") == [(result.iterations, result.wall_time)]

    # hparams: a session (start and end info), no per-run experiment (see log_hparams)
    content = acc.PluginTagToContent("hparams")
    assert set(content) == {"_hparams_/session_start_info", "_hparams_/session_end_info"}
    start = hparams_metadata.parse_session_start_info_plugin_data(
        content["_hparams_/session_start_info"])
    values = {k: v.WhichOneof("kind") and getattr(v, v.WhichOneof("kind"))
              for k, v in start.hparams.items()}
    assert values == {"problem.name": "spring1d", "problem.n": 16.0,
                      "problem.loads": "[0.0, 1.0]", "solver.name": "gauss_newton",
                      "solver.tau": 1.5, "solver.verbose": False}   # None left out
    assert start.hparams["solver.verbose"].WhichOneof("kind") == "bool_value"
    end = hparams_metadata.parse_session_end_info_plugin_data(content["_hparams_/session_end_info"])
    assert end.status == api_pb2.STATUS_SUCCESS


def hparams_view(logdir):
    """What TensorBoard's HParams dashboard gets for ``logdir``: the experiment (columns)
    and the session groups (rows), computed by the plugin's own handlers."""
    mux = plugin_event_multiplexer.EventMultiplexer()
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    tb_context = base_plugin.TBContext(
        logdir=str(logdir), multiplexer=mux,
        data_provider=data_provider.MultiplexerDataProvider(mux, str(logdir)))
    ctx = context.RequestContext()
    backend = backend_context.Context(tb_context)
    experiment = get_experiment.Handler(ctx, backend, "", api_pb2.GetExperimentRequest()).run()
    request = api_pb2.ListSessionGroupsRequest(start_index=0, slice_size=100)
    request.allowed_statuses.extend([api_pb2.STATUS_SUCCESS, api_pb2.STATUS_UNKNOWN])
    for info in experiment.metric_infos:
        request.col_params.add(metric=info.name)
    for info in experiment.hparam_infos:
        request.col_params.add(hparam=info.name)
    groups = list_session_groups.Handler(ctx, backend, "", request).run().session_groups
    return experiment, groups


def test_hparams_view_of_a_sweep_over_solvers(tmp_path):
    """Two jobs of a sweep with different solvers (different settings): the dashboard
    shows the union of the settings and every job's final metrics."""
    runs = {"0_gn": ({"name": "gauss_newton", "tau": 1.5, "eta_max": 0.1}, 0.25, 4),
            "1_sb": ({"name": "split_bregman", "tau": 1.0, "isotropic": True, "mu": None}, 0.5, 6)}
    for job, (solver, err, iterations) in runs.items():
        with TensorBoardLogger(tmp_path / job / "tb") as tb:
            for i in range(iterations + 1):
                tb(record(i, k_err_rel=err / (i + 1)))
            tb.log_hparams({"problem": {"name": "poisson2d", "N": 8, "noise": 0.0},
                            "solver": solver},
                           {"misfit": 1.0 / (iterations + 1), "k_err_rel": err / (iterations + 1),
                            "iterations": iterations, "wall_s": 0.5 * iterations})
    experiment, groups = hparams_view(tmp_path)
    infos = {h.name: h for h in experiment.hparam_infos}
    assert set(infos) == {"problem.name", "problem.N", "problem.noise", "solver.name",
                          "solver.tau", "solver.eta_max", "solver.isotropic"}
    assert set(infos["solver.name"].domain_discrete) == {"gauss_newton", "split_bregman"}
    assert infos["solver.isotropic"].type == api_pb2.DATA_TYPE_BOOL
    assert infos["solver.tau"].type == api_pb2.DATA_TYPE_FLOAT64 and infos["solver.tau"].differs
    metric_tags = {m.name.tag for m in experiment.metric_infos}
    assert {"fit/misfit", "metrics/k_err_rel", "final/iterations", "final/wall_s"} <= metric_tags
    assert len(groups) == 2
    for group in groups:
        solver = group.hparams["solver.name"].string_value
        _, err, iterations = runs["0_gn" if solver == "gauss_newton" else "1_sb"]
        values = {m.name.tag: m.value for m in group.metric_values}
        assert values["final/iterations"] == iterations
        assert values["final/wall_s"] == 0.5 * iterations
        assert values["metrics/k_err_rel"] == pytest.approx(err / (iterations + 1), rel=1e-15)
        assert values["fit/misfit"] == pytest.approx(1.0 / (iterations + 1), rel=1e-12)


def test_metric_tags_and_hparam_values():
    assert metric_tag("misfit") == "fit/misfit"
    assert metric_tag("k_err_rel_aligned") == "metrics/k_err_rel_aligned"
    assert metric_tag("iterations") == "final/iterations"
    assert metric_tag("wall_s") == "final/wall_s"
    assert hparam_values({"solver": {"mu": None, "isotropic": True, "weights": [1, 2]},
                          "problem": {"N": 32}}) == {
        "solver.isotropic": True, "solver.weights": "[1, 2]", "problem.N": 32}
