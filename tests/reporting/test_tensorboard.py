"""TensorBoardLogger as a user sees it: a real ``tensorboard --logdir`` (default options,
the Rust data server) read through its HTTP data API (fixture ``tensorboard_server`` of
tests/conftest.py): scalars, images, the HParams dashboard of a sweep, and the curves of a
fit that was killed and resumed."""
from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from torchfit.reporting.field_snapshots import FieldSnapshots
from torchfit.reporting.figures import field_is_chain
from torchfit.reporting.results import history_rows
from torchfit.reporting.tags import tag_for
from torchfit.reporting.tensorboard import TensorBoardLogger, event_files, scalar_steps
from torchfit.problems import build_problem
from torchfit.run.evaluator import Evaluator
from torchfit.solvers import GaussNewtonConfig, IterationRecord, gauss_newton

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def f32(value: float) -> float:
    """What TensorBoard shows for a double: its float32 rounding."""
    return float(np.float32(value))


def record(i: int, **extra: float) -> IterationRecord:
    return IterationRecord(iteration=i, theta=torch.zeros(3), objective=0.5 / (i + 1) ** 2,
                           misfit=1.0 / (i + 1) + 1e-13 * i, step_norm=0.1 * i,
                           cg_iterations=i, damping=float("nan"), wall_time=0.01 * i,
                           factorizations=i, solves=3 * i, extra=dict(extra))


def expected_series(rows: list[dict]) -> dict[str, list[tuple[int, float]]]:
    """``{tag: [(step, float32 value), ...]}`` of history rows (non-finite values skipped)."""
    out: dict[str, list[tuple[int, float]]] = {}
    for row in rows:
        for key, value in row.items():
            if key != "iteration" and np.isfinite(value):
                out.setdefault(tag_for(key), []).append((int(row["iteration"]), f32(value)))
    return out


def test_server_shows_every_scalar_and_image_of_a_fit(tmp_path, tensorboard_server):
    """A Gauss-Newton fit of spring1d (field profile image) and a Gauss-Newton fit of
    poisson2d with FieldSnapshots (field images), one run each; the Scalars dashboard has
    every per-iteration curve with iterations + 1 points equal to the history."""
    runs = {}
    spring = build_problem("spring1d", {"n": 16, "noise": 1e-4})
    assert field_is_chain(spring)
    tb = TensorBoardLogger(tmp_path / "spring" / "tb")
    run = Evaluator(spring)
    result = gauss_newton(spring.residual(), spring.theta0, callbacks=[run, tb])
    metrics = run.final(result.theta).metrics
    tb.finish(spring, spring.field(result.theta), {**metrics, "iterations": result.iterations,
                                     "wall_s": result.wall_time},
              {"problem": {"name": "spring1d", "n": 16}, "solver": {"name": "gauss_newton"}})
    runs["spring/tb"] = (result, metrics)

    poisson = build_problem("poisson2d", {"N": 9})
    tb = TensorBoardLogger(tmp_path / "poisson" / "tb")
    snaps = FieldSnapshots(poisson, tb, None, snapshot_iterations=[1], every=2)
    run = Evaluator(poisson)
    result = gauss_newton(poisson.residual(), poisson.theta0, GaussNewtonConfig(max_iter=4),
                          [run, tb, run.feed(snaps)])
    final = run.final(result.theta)
    snaps.finish(final)
    tb.close()
    runs["poisson/tb"] = (result, final.metrics)

    server = tensorboard_server(tmp_path)
    for run, (result, metrics) in runs.items():
        expected = expected_series(history_rows(result.history))
        assert {"fit/misfit", "fit/objective", "metrics/k_err_rel", "solver/step_norm",
                "solver/cg_iterations", "solver/solves", "solver/wall_time"} <= set(expected)
        # the data server loads in the background: wait for the last point of every curve
        server.wait_until(lambda: all(
            len(server.scalars(run, tag)) == len(points) for tag, points in expected.items())
            if set(expected) <= set(server.scalar_tags().get(run, {})) else False,
            what=f"the scalars of {run}")
        tags = server.scalar_tags()[run]
        assert "solver/damping" not in tags                 # NaN (Gauss-Newton) never written
        for tag, points in expected.items():
            shown = server.scalars(run, tag)
            assert shown == points, tag                      # float32 of the exact doubles
        for tag in ("fit/misfit", "fit/objective", "metrics/k_err_rel", "metrics/u_err_2",
                    "solver/step_norm", "solver/cg_iterations", "solver/solves",
                    "solver/factorizations", "solver/wall_time", "solver/accepted"):
            # every iteration once (an extra such as solver/step_length starts at 1)
            assert [s for s, _ in server.scalars(run, tag)] == \
                list(range(result.iterations + 1)), tag
        last = result.iterations
        assert server.scalars(run, "fit/misfit")[-1] == (last, f32(metrics["misfit"]))

    spring_result = runs["spring/tb"][0]
    assert server.scalars("spring/tb", "final/iterations") == [
        (spring_result.iterations, spring_result.iterations)]
    assert server.scalars("spring/tb", "final/wall_s") == [
        (spring_result.iterations, f32(spring_result.wall_time))]

    images = server.wait_until(lambda: server.image_tags().get("poisson/tb"),
                               what="the images")
    assert {"field/k_image", "field/k_error_aligned_image", "field/k_true_image",
            "field/k_panels"} <= set(images)
    assert "field/k_profile" in server.image_tags()["spring/tb"]
    last = runs["poisson/tb"][0].iterations
    steps = sorted({0, 1, last} | set(range(0, last + 1, 2)))
    entries = server.images("poisson/tb", "field/k_image")
    assert [e["step"] for e in entries] == steps
    assert [e["step"] for e in server.images("poisson/tb", "field/k_panels")] == [last]
    assert server.image_bytes(entries[-1]).startswith(b"\x89PNG")


def test_server_log_every_and_step_offset(tmp_path, tensorboard_server):
    with TensorBoardLogger(tmp_path / "every3", log_every=3) as tb:
        for i in range(8):
            tb(record(i, k_err_rel=1.0 / (i + 2), eta=0.1))
    with TensorBoardLogger(tmp_path / "offset5", step_offset=5) as tb:
        for i in range(3):
            rec = record(i)
            rec.damping = 10.0 ** -i
            tb(rec)
    server = tensorboard_server(tmp_path)
    server.wait_until(lambda: len(server.scalars("offset5", "solver/damping")) == 3
                      if "solver/damping" in server.scalar_tags().get("offset5", {}) else False)
    server.wait_until(lambda: len(server.scalar_tags().get("every3", {})) == 10)
    tags = server.scalar_tags()["every3"]
    assert set(tags) == {"fit/misfit", "fit/objective", "metrics/k_err_rel",
                         "solver/cg_iterations", "solver/step_norm", "solver/solves",
                         "solver/factorizations", "solver/wall_time", "solver/eta",
                         "solver/accepted"}      # no solver/damping: NaN is never written
    server.wait_until(lambda: len(server.scalars("every3", "fit/misfit")) == 4)
    assert server.scalars("every3", "fit/misfit") == [
        (i, f32(1.0 / (i + 1) + 1e-13 * i)) for i in (0, 3, 6, 7)]
    assert server.scalars("offset5", "solver/damping") == [(5, 1.0), (6, f32(0.1)),
                                                           (7, f32(0.01))]


def test_server_hparams_of_a_sweep(tmp_path, tensorboard_server):
    """Three jobs of a sweep (two solvers, different settings, one automatic ``mu``): the
    HParams dashboard lists the union of the settings and each job's final metrics."""
    runs = {"0_gn": ({"name": "gauss_newton", "tau": 1.5, "eta_max": 0.1}, 0.25, 4),
            "1_sb": ({"name": "split_bregman", "tau": 1.0, "isotropic": True, "mu": None}, 0.5, 6),
            "2_sb": ({"name": "split_bregman", "tau": 1.2, "isotropic": False, "mu": 3.0}, 0.4, 3)}
    for job, (solver, err, iterations) in runs.items():
        with TensorBoardLogger(tmp_path / job / "tb") as tb:
            for i in range(iterations + 1):
                tb(record(i, k_err_rel=err / (i + 1)))
            tb.log_hparams({"problem": {"name": "poisson2d", "N": 8, "noise": 0.0},
                            "solver": solver},
                           {"misfit": 1.0 / (iterations + 1), "k_err_rel": err / (iterations + 1),
                            "iterations": iterations, "wall_s": 0.5 * iterations})
    server = tensorboard_server(tmp_path)

    def complete():
        experiment = server.hparams_experiment()
        groups = server.hparams_session_groups(experiment) if experiment else []
        metrics = [{m["name"]["tag"] for m in g.get("metricValues", [])} for g in groups]
        ready = len(groups) == 3 and all({"fit/misfit", "metrics/k_err_rel", "final/iterations",
                                          "final/wall_s"} <= m for m in metrics)
        return (experiment, groups) if ready else None

    experiment, groups = server.wait_until(complete, what="the hparams sessions")
    infos = {h["name"]: h for h in experiment["hparamInfos"]}
    assert set(infos) == {"problem.name", "problem.N", "problem.noise", "solver.name",
                          "solver.tau", "solver.eta_max", "solver.isotropic", "solver.mu"}
    assert set(infos["solver.name"]["domainDiscrete"]) == {"gauss_newton", "split_bregman"}
    assert infos["solver.isotropic"]["type"] == "DATA_TYPE_BOOL"
    assert infos["solver.tau"]["type"] == "DATA_TYPE_FLOAT64" and infos["solver.tau"]["differs"]
    metric_tags = {m["name"]["tag"] for m in experiment["metricInfos"]}
    assert {"fit/misfit", "metrics/k_err_rel", "final/iterations", "final/wall_s"} <= metric_tags
    seen = set()
    for group in groups:
        (session,) = group["sessions"]
        job = session["name"].split("/")[0]
        seen.add(job)
        solver, err, iterations = runs[job]
        assert group["hparams"]["solver.name"] == solver["name"]
        assert group["hparams"]["solver.tau"] == solver["tau"]
        assert ("solver.mu" in group["hparams"]) == (solver.get("mu") is not None)
        values = {m["name"]["tag"]: m["value"] for m in group["metricValues"]}
        assert values["final/iterations"] == iterations
        assert values["final/wall_s"] == f32(0.5 * iterations)
        assert values["metrics/k_err_rel"] == f32(err / (iterations + 1))
        assert values["fit/misfit"] == f32(1.0 / (iterations + 1) + 1e-13 * iterations)
        assert session["status"] == "STATUS_SUCCESS"
    assert seen == set(runs)


CRASHING_RUN = textwrap.dedent("""
    import os, signal, sys
    import torch
    from torchfit.reporting.tensorboard import TensorBoardLogger
    from torchfit.solvers import IterationRecord

    logdir, lost = sys.argv[1], int(sys.argv[2])
    tb = TensorBoardLogger(logdir)          # flush_every=1 (the default)
    for i in range(lost + 1):
        rec = IterationRecord(iteration=i, theta=torch.zeros(3), objective=0.5 / (i + 1) ** 2,
                              misfit=1.0 / (i + 1), step_norm=0.1 * i, cg_iterations=i,
                              wall_time=0.01 * i, factorizations=i, solves=3 * i,
                              extra={"k_err_rel": 1.0 / (i + 2)})
        if i < lost:
            tb(rec)
        # iteration `lost`: its checkpoint is committed, then the process dies before
        # TensorBoardLogger writes the step
    os.kill(os.getpid(), signal.SIGKILL)
""")


def resume_records(first: int, last: int) -> list[IterationRecord]:
    """What the resumed solver emits: its iteration 0 is the checkpoint's iteration."""
    out = []
    for step in range(first, last + 1):
        rec = IterationRecord(iteration=step - first, theta=torch.zeros(3),
                              objective=0.5 / (step + 1) ** 2, misfit=1.0 / (step + 1),
                              step_norm=0.1 * step, cg_iterations=step, wall_time=0.01 * step,
                              factorizations=step, solves=3 * step,
                              extra={"k_err_rel": 1.0 / (step + 2)})
        out.append(rec)
    return out


def test_resume_after_sigkill_shows_every_step_once(tmp_path, tensorboard_server):
    """Steps 0..4 reach the event file, the process is SIGKILLed after committing the
    checkpoint of iteration 5 (step 5 lost); the resumed run restores step 5 from the
    history and continues to 9: the server shows 0..9 once each."""
    logdir = tmp_path / "run" / "tb"
    env = {**os.environ, "PYTHONPATH": REPO + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-c", CRASHING_RUN, str(logdir), "5"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9, proc.stderr
    assert {s for _, s in scalar_steps(event_files(logdir))} == set(range(5))

    # result.json's history of the first run up to its checkpoint (iterations 0..5)
    history = [{"iteration": r.iteration, **r.scalars()} for r in resume_records(0, 5)]
    tb = TensorBoardLogger(logdir, step_offset=5)
    assert tb.resume(history, last_iteration=5) == 9       # the 9 scalars of step 5
    for rec in resume_records(5, 9):                        # iteration 0 = step 5: skipped
        tb(rec)
    tb.close()
    assert TensorBoardLogger(logdir).resume(history, 5) == 0   # nothing missing any more

    server = tensorboard_server(tmp_path)
    expected = expected_series([{"iteration": step, **r.scalars()}
                                for step, r in enumerate(resume_records(0, 9))])
    assert len(expected) == 9
    server.wait_until(lambda: all(len(server.scalars("run/tb", tag)) >= len(points)
                                  for tag, points in expected.items())
                      if set(expected) <= set(server.scalar_tags().get("run/tb", {})) else False,
                      what="the resumed curves")
    for tag, points in expected.items():
        assert server.scalars("run/tb", tag) == points, tag     # 0..9, once each


def test_resume_from_an_older_checkpoint_warns_and_replaces_later_steps(
        tmp_path, caplog, tensorboard_server):
    """Event files with steps after the checkpoint (0..3 logged, checkpoint of 2): a
    warning, and TensorBoard shows the resumed run's points at 3..5, each step once."""
    logdir = tmp_path / "run"
    with TensorBoardLogger(logdir) as tb:
        for i in range(4):
            tb(record(i))
    tb = TensorBoardLogger(logdir, step_offset=2)
    with caplog.at_level(logging.WARNING, logger="torchfit.reporting.tensorboard"):
        written = tb.resume([{"iteration": i, **record(i).scalars()} for i in range(3)], 2)
    assert written == 0
    (warning,) = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "[3]" in warning.getMessage() and "replaces" in warning.getMessage()
    for i in range(4):                         # steps 2 (skipped), 3, 4, 5: other values
        rec = record(i + 2)
        rec.iteration = i
        rec.misfit = 10.0 + i
        tb(rec)
    tb.close()
    server = tensorboard_server(tmp_path)
    shown = server.wait_until(lambda: [s for s, _ in server.scalars("run", "fit/misfit")]
                              == list(range(6)) and server.scalars("run", "fit/misfit")
                              if "fit/misfit" in server.scalar_tags().get("run", {}) else None,
                              what="steps 0..5")
    assert shown == [(0, 1.0), (1, f32(0.5 + 1e-13)), (2, f32(1 / 3 + 2e-13)),
                     (3, 11.0), (4, 12.0), (5, 13.0)]


def test_flush_every_iteration(tmp_path):
    tb = TensorBoardLogger(tmp_path)
    assert tb.flush_every == 1
    for i in range(3):
        tb(record(i))
        # on disk before the next iteration, without close()
        assert ("fit/misfit", i) in scalar_steps(event_files(tmp_path))
    tb.close()
    with pytest.raises(ValueError, match="flush_every"):
        TensorBoardLogger(tmp_path, flush_every=0)
