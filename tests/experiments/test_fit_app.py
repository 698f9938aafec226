"""The Hydra apps ``experiments/fit.py`` and ``experiments/verify.py`` as a user runs them
(from the repo root): outputs, exit statuses, bad input, resume, sweeps.

The apps run in the test's process (:mod:`helpers.apps`: the app's ``__main__`` with its
argv, exit status and output as a subprocess would give them); one test of each app runs
it as a subprocess, the smoke test that the command itself works
(:func:`test_fit_prints_where_everything_is`, :func:`test_verify_exit_statuses`).
What the run itself computes and writes is tested in-process in tests/run/."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from helpers.apps import run_app
from helpers.fit_app import run_fit_app, run_fit_app_process, with_problem

REPO = Path(__file__).resolve().parents[2]
HAS_CUDA = torch.cuda.is_available()


def app(script: str, *args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    """``python experiments/<script> <args>`` from the repository root, in this process."""
    if script == "fit.py":      # the app's default problem is the short arm; these use spring1d
        args = tuple(with_problem(args))
    return run_app(script, *args)


def app_process(script: str, *args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    """:func:`app` as a subprocess (the smoke test of an app)."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    if script == "fit.py":
        args = tuple(with_problem(args))
    return subprocess.run([sys.executable, f"experiments/{script}", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def ok(proc: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    return proc


def digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_fit_prints_where_everything_is(tmp_path):
    """The fit app's smoke test: ``python experiments/fit.py`` as a subprocess."""
    run_dir = tmp_path / "gn"
    proc = ok(run_fit_app_process(run_dir, "problem.n=16", "problem.noise=1e-4"))
    result = json.loads((run_dir / "result.json").read_text())
    assert result["status"] == "completed" and result["stop_reason"] == "discrepancy"
    assert result["config"]["problem"]["noise"] == 1e-4
    assert result["config"]["problem"]["data"] == "dense"        # an Enum, written as its value
    lines = proc.stdout.splitlines()
    assert lines[-1] == f"tensorboard --logdir {run_dir / 'tb'}"
    assert any("stopped by discrepancy after" in line for line in lines)
    assert "field.png" in lines[-2] and "error_curves.png" in lines[-2]
    log = (run_dir / "fit.log").read_text()
    assert "misfit" in log and "k_err_rel" in log, "the progress table goes to Hydra's log"


#: Every bad input of issue 10 (and the ones that already passed): override(s), words the
#: one error line must contain. Each case exits 2 and leaves no run directory.
BAD_INPUT = [
    (["threads=1000000000000"], ["threads", "4096"]),     # the settings probe's one fail
    (["problem.noise=inf"], ["problem.noise"]),
    (["problem.noise=nan"], ["problem.noise"]),
    (["problem.k0=inf"], ["problem.k0"]),
    (["problem.k_background=inf"], ["problem.k_background"]),
    (["problem=poisson2d", "problem.N=9", "problem.noise=inf"], ["problem.noise"]),
    (["problem=poisson2d", "problem.N=9", "problem.k0=inf"], ["problem.k0"]),
    (["problem=poisson2d", "problem.N=9", "problem.s=inf"], ["problem.s"]),
    (["solver=split_bregman", "solver.growth=inf"], ["solver.growth"]),
    (["problem.noise=1e-4", "solver.tau=inf"], ["solver.tau"]),
    (["solver=levenberg_marquardt", "solver.damping_init=inf"], ["solver.damping_init"]),
    (["problem.device=gpu"], ["problem.device", "cpu"]),
    (["problem=poisson2d", "problem.N=9", "problem.device=gpu"], ["problem.device"]),
    (["problem=membrane2d", "problem.device=gpu"], ["problem.device"]),
    pytest.param(["problem.device=cuda"], ["problem.device", "CUDA"],
                 marks=pytest.mark.skipif(HAS_CUDA, reason="torch has CUDA here")),
    pytest.param(["problem=poisson2d", "problem.device=cuda"], ["problem.device", "CUDA"],
                 marks=pytest.mark.skipif(HAS_CUDA, reason="torch has CUDA here")),
    (["problem.noise=-1"], ["problem.noise"]),
    (["problem.n=0"], ["problem.n"]),
    (["problem.fixed_nodes=[]"], ["problem.fixed_nodes", "Dirichlet"]),
    (["solver.tau=0.5"], ["solver.tau"]),
    (["objective_metric=k_err"], ["objective_metric", "k_err_rel"]),
    (["problem.data=bogus"], ["dense", "sparse"]),          # an Enum: Hydra lists the choices
    (["problem.nosie=0.1"], ["nosie"]),                     # misspelt: the schema rejects it
    (["problem.n=abc"], ["problem.n"]),                     # mistyped
    (["problem=nope"], ["spring1d"]),
    (["problem=membrane2d", "problem.nu=0.5"], ["problem.nu"]),
    (["problem=membrane2d", "problem.model=mooney"], ["corotated"]),
    (["problem=membrane2d", "problem.nx=4", "problem.ny=2", "sheet_frame=9"], ["sheet_frame"]),
    (["snapshot_every=-1"], ["snapshot_every"]),
    (["init=/nonexistent/run"], ["init=/nonexistent/run", "no such file"]),
    (["continuation=true"], ["continuation=true", "body fitted to an animation", "spring1d"]),
    (["continuation=true", "continuation_min_volume=2"], ["continuation_min_volume=2"]),
    (["continuation=maybe"], ["continuation='maybe'", "true", "false", "auto"]),
    (["continuation_first_max_iter=-1"], ["continuation_first_max_iter=-1"]),
]


#: One case of each kind, for the fast suite: a problem number, a solver number, a device,
#: a value Hydra cannot compose, an enum, a run option.
SAMPLE = (["problem.k0=inf"], ["solver=split_bregman", "solver.growth=inf"],
          ["problem.device=gpu"], ["problem.n=abc"], ["problem.data=bogus"], ["snapshot_every=-1"])


def check_bad_input(tmp_path: Path, cases: list) -> None:
    """Run every case through the app (in this process, one after another) and collect
    what is wrong with each: exit status, traceback, error lines, named setting, files left."""
    def run(i, overrides):
        run_dir = tmp_path / f"case{i}" / "run"
        return run_dir, run_fit_app(run_dir, *overrides)

    done = [run(i, overrides) for i, (overrides, _) in enumerate(cases)]
    failures = []
    for (overrides, words), (run_dir, proc) in zip(cases, done):
        errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
        problems = []
        if proc.returncode != 2:
            problems.append(f"exit {proc.returncode}")
        if "Traceback" in proc.stderr:
            problems.append("traceback")
        if len(errors) != 1:
            problems.append(f"{len(errors)} error lines")
        # a setting must be named on the error line; Hydra's own messages (choices) may
        # stand above it
        where = {w: errors[0] if errors and w.startswith(("problem.", "solver.")) else
                 proc.stderr + proc.stdout for w in words}
        problems += [f"no {w!r}" for w in words if w not in where[w]]
        if run_dir.exists():
            problems.append("left " + ", ".join(str(p.relative_to(run_dir))
                                                for p in run_dir.rglob("*")))
        if problems:
            failures.append(f"{overrides}: {'; '.join(problems)}\n{proc.stderr[-600:]}")
    assert not failures, "\n".join(failures)


def _cases(sample: bool = False) -> list:
    cases = [c.values if hasattr(c, "values") else c for c in BAD_INPUT
             if not (hasattr(c, "marks") and any(m.args and m.args[0] for m in c.marks))]
    return [c for c in cases if not sample or c[0] in SAMPLE]


def test_bad_input_of_each_kind_is_one_line_exit_2_and_nothing_written(tmp_path):
    cases = _cases(sample=True)
    assert len(cases) == len(SAMPLE)
    check_bad_input(tmp_path, cases)


@pytest.mark.slow
def test_every_bad_input_is_one_line_exit_2_and_nothing_written(tmp_path):
    check_bad_input(tmp_path, _cases())


def test_unwritable_run_directory_is_an_io_error(tmp_path):
    (tmp_path / "file").write_text("")
    proc = run_fit_app(tmp_path / "file" / "run")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "cannot create the run directory" in proc.stderr and "is a file" in proc.stderr
    assert "invalid configuration" not in proc.stderr


def test_a_refused_resume_restores_hydra_files(tmp_path):
    run_dir = tmp_path / "run"
    ok(run_fit_app(run_dir, "problem.n=16", "problem.noise=1e-4", "solver.max_iter=2"))
    first = json.loads((run_dir / "result.json").read_text())
    assert first["stop_reason"] == "max_iter" and first["iterations"] == 2
    before = digest(run_dir)
    refused = run_fit_app(run_dir, "problem.n=16", "problem.noise=2e-4", "solver.max_iter=9",
                          "resume=true")
    assert refused.returncode == 2, refused.stderr
    assert "noise" in refused.stderr and "Traceback" not in refused.stderr
    assert digest(run_dir) == before, "a refused resume touches nothing, .hydra/ included"


@pytest.mark.slow      # the continuation itself is tested in-process: tests/run/test_continuation.py
def test_resume_through_the_app_continues_with_a_larger_budget(tmp_path):
    run_dir = tmp_path / "run"
    ok(run_fit_app(run_dir, "problem.n=16", "problem.noise=1e-4", "solver.max_iter=2"))
    first = json.loads((run_dir / "result.json").read_text())
    ok(run_fit_app(run_dir, "problem.n=16", "problem.noise=1e-4", "solver.max_iter=9",
                   "resume=true"))
    second = json.loads((run_dir / "result.json").read_text())
    assert second["resumed_from_iteration"] == 2 and second["stop_reason"] == "discrepancy"
    assert [row["iteration"] for row in second["history"]] == list(range(second["iterations"] + 1))
    assert second["history"][2]["misfit"] == first["misfit"]


def test_continuation_through_the_app_runs_both_stages_and_says_where(tmp_path):
    """A coarse arm with frames 0, 3 (mild) and 11 (full bend: the inner elbow folds)."""
    run_dir = tmp_path / "run"
    proc = ok(run_fit_app(run_dir, "problem=arm3d", "problem.tet_edge_length=0.1",
                          "problem.grid=[3,3,4]", "problem.frames=[0,3,11]",
                          "problem.target=synthetic", f"problem.cache_dir={tmp_path / 'cache'}",
                          "solver.max_iter=1", "continuation=true",
                          "continuation_min_volume=0.4"))
    stage = json.loads((run_dir / "unique_frames" / "result.json").read_text())
    final = json.loads((run_dir / "result.json").read_text())
    assert stage["config"]["problem"]["frames"] == [0, 3]
    assert final["config"]["problem"]["frames"] == [0, 3, 11]
    assert final["config"]["continuation_first_stage"]["near_fold"] == [11]
    lines = proc.stdout.splitlines()
    assert any(line.startswith("first stage (the frames far from a fold)") and
               str(run_dir / "unique_frames") in line for line in lines)
    assert lines[-1] == f"tensorboard --logdir {run_dir}"     # both stages' curves


def test_init_starts_from_an_earlier_run_of_the_same_parameterisation(tmp_path):
    ok(run_fit_app(tmp_path / "first", "problem.n=16", "problem.noise=1e-4", "solver.max_iter=1"))
    first = json.loads((tmp_path / "first" / "result.json").read_text())
    ok(run_fit_app(tmp_path / "second", "problem.n=16", "problem.noise=1e-4",
                   f"init={tmp_path / 'first'}"))
    second = json.loads((tmp_path / "second" / "result.json").read_text())
    assert second["history"][0]["misfit"] == first["misfit"]
    assert second["config"]["init"] == str(tmp_path / "first")
    refused = run_fit_app(tmp_path / "third", "problem.n=8", f"init={tmp_path / 'first'}")
    errors = [line for line in refused.stderr.splitlines() if line.startswith("error: ")]
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
    assert len(errors) == 1 and "(16,) parameters" in errors[0] and "(8,)" in errors[0]
    assert not (tmp_path / "third").exists()


def test_verify_exit_statuses(tmp_path):
    """The verify app's smoke test: ``python experiments/verify.py`` as a subprocess."""
    passed = ok(app_process("verify.py", f"hydra.run.dir={tmp_path / 'ok'}", "problem.n=16"))
    assert "wrote" in passed.stdout and (tmp_path / "ok" / "verify.json").is_file()
    for i, override in enumerate(["at=nowhere"]):   # the others: tests/run/test_verifying.py
        run_dir = tmp_path / f"bad{i}"
        proc = app_process("verify.py", f"hydra.run.dir={run_dir}", override)
        assert proc.returncode == 2, (override, proc.stderr)
        assert "Traceback" not in proc.stderr and "error: " in proc.stderr, override
        assert not run_dir.exists(), override


def test_a_sweep_value_hydra_cannot_compose_stops_the_sweep_before_any_job(tmp_path):
    # docs/guide/sweeps.md: Hydra composes every job before it launches the first.
    sweep = tmp_path / "sweep"
    proc = app("fit.py", "-m", f"hydra.sweep.dir={sweep}", "problem.noise=abc,0", "problem.n=8")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "problem.noise=abc" in proc.stderr and "error: invalid sweep" in proc.stderr
    assert not list(sweep.glob("*/result.json"))


def test_a_sweep_with_a_failed_job_and_its_hparams_table(tmp_path, tensorboard_server):
    """Job 0 is invalid (tau <= 1): it writes why and the other jobs run; TensorBoard's
    HParams table (a real server, default options) shows the metrics of the two others."""
    sweep = tmp_path / "sweep"
    proc = ok(app("fit.py", "-m", f"hydra.sweep.dir={sweep}", "solver.tau=0.5,1.5,3",
                  "problem.n=16", "problem.noise=1e-4", "progress=false"))
    assert "Traceback" not in proc.stderr and "solver.tau" in proc.stderr
    results = {p.parent.name.split("_")[0]: json.loads(p.read_text())
               for p in sweep.glob("*/result.json")}
    assert results["0"]["status"] == "failed" and "solver.tau" in results["0"]["error"]
    assert results["1"]["status"] == results["2"]["status"] == "completed"
    report = subprocess.run([sys.executable, "scripts/report.py", str(sweep)], cwd=REPO,
                            capture_output=True, text=True, timeout=60)
    assert report.returncode == 0, report.stderr
    assert "failed: solver.tau" in report.stdout

    server = tensorboard_server(sweep)
    metrics = ("fit/misfit", "metrics/k_err_rel", "final/iterations")

    def rows():
        groups = server.hparams_session_groups()
        values = {g["hparams"].get("solver.tau"): {
            m["name"]["tag"]: m["value"] for s in g["sessions"] for m in s.get("metricValues", [])}
            for g in groups}
        return values if len(values) == 2 and all(
            set(metrics) <= set(v) for v in values.values()) else None

    table = server.wait_until(rows, what="the HParams table of the sweep")
    experiment = server.hparams_experiment()
    assert {"solver.name", "solver.tau", "problem.noise"} <= {
        h["name"] for h in experiment["hparamInfos"]}
    for job in ("1", "2"):
        result = results[job]
        shown = table[result["config"]["solver"]["tau"]]
        assert shown["metrics/k_err_rel"] == pytest.approx(result["k_err_rel"], rel=1e-6)
        assert shown["fit/misfit"] == pytest.approx(result["misfit"], rel=1e-6)
        assert shown["final/iterations"] == result["iterations"]
