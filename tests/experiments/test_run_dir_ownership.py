"""The fit app owns its run directory (issue 27): two runs started at once into one directory
(one runs, the other exits 2 with one line, nothing mixed), SIGTERM like Ctrl-C (143 and the
resume hint), a finished run left byte-identical by a resume, and a resume that never starts
over where the checkpoint is missing or unreadable.

The two runs at once and SIGTERM are about processes: the app runs as subprocesses there;
the resumes and refusals run in the test's process (:func:`helpers.fit_app.run_fit_app`)."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from helpers.fit_app import REPO, run_fit_app
from helpers.runs import tree_digest

LOCK_FILE = ".torchfit.lock"


def _start(run_dir: Path, *overrides: str) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.Popen([sys.executable, "experiments/fit.py", f"hydra.run.dir={run_dir}",
                             "problem=spring1d", *overrides], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_two_runs_started_at_once_into_one_directory_one_runs_the_other_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    noises = {"1e-4": 1e-4, "3e-4": 3e-4}
    procs = {}
    started = time.perf_counter()
    for noise in noises:           # started within a few milliseconds of each other
        procs[noise] = _start(run_dir, f"problem.noise={noise}")
    assert time.perf_counter() - started < 0.1
    done = {noise: (p, *p.communicate(timeout=300)) for noise, p in procs.items()}
    codes = sorted(p.returncode for p, _, _ in done.values())
    assert codes == [0, 2], {k: (p.returncode, err[-800:]) for k, (p, _, err) in done.items()}
    winner = next(k for k, (p, _, _) in done.items() if p.returncode == 0)
    loser_proc, loser_out, loser_err = next(v for v in done.values() if v[0].returncode == 2)
    lines = [line for line in loser_err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), loser_err
    assert str(run_dir) in lines[0] and f"process {procs[winner].pid} on " in lines[0]
    assert loser_out == ""
    # nothing mixed: the directory is the winner's alone
    result = json.loads((run_dir / "result.json").read_text())
    assert result["config"]["problem"]["noise"] == noises[winner]
    hydra = yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())
    assert hydra["problem"]["noise"] == noises[winner]
    assert (run_dir / ".hydra" / "overrides.yaml").read_text().count("problem.noise=") == 1
    assert f"problem.noise={winner}" in (run_dir / ".hydra" / "overrides.yaml").read_text()
    rows = [json.loads(line) for line in (run_dir / "history.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == list(range(result["iterations"] + 1))
    assert (run_dir / "fit.log").read_text().count("problem spring1d:") == 1
    assert not (run_dir / LOCK_FILE).exists()


def test_sigterm_ends_the_run_like_ctrl_c_and_it_resumes(tmp_path):
    run_dir = tmp_path / "run"
    proc = _start(run_dir, "problem.noise=1e-4")
    assert proc.stdout is not None
    for line in proc.stdout:        # the progress table: terminate after iteration 1
        if re.search(r"\] - +1 ", line):
            proc.send_signal(signal.SIGTERM)
            break
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-1500:]
    assert "Traceback" not in err
    assert f"terminated (SIGTERM); continue with: python experiments/fit.py " \
        f"hydra.run.dir={run_dir} resume=true" in err
    assert not (run_dir / "result.json").exists() and not (run_dir / LOCK_FILE).exists()
    resumed = run_fit_app(run_dir, "problem.noise=1e-4", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-1500:]
    result = json.loads((run_dir / "result.json").read_text())
    # the progress line of iteration 1 comes before its checkpoint: 0 or 1 was committed
    assert result["resumed_from_iteration"] in (0, 1) and result["stop_reason"] == "discrepancy"


def test_resuming_a_finished_run_leaves_its_directory_byte_identical(tmp_path):
    run_dir = tmp_path / "run"
    first = run_fit_app(run_dir, "problem.n=16", "problem.noise=1e-4", "solver.max_iter=2")
    assert first.returncode == 0, first.stderr
    before = tree_digest(run_dir)
    again = run_fit_app(run_dir, "problem.n=16", "problem.noise=1e-4", "solver.max_iter=2",
                        "resume=true")
    assert again.returncode == 0, again.stderr
    assert "max_iter after 2 iterations" in again.stdout
    assert tree_digest(run_dir) == before, ".hydra/ and fit.log included"


def test_a_resume_without_its_checkpoint_is_refused_and_changes_nothing(tmp_path):
    run_dir = tmp_path / "run"
    first = run_fit_app(run_dir, "problem.n=16", "problem.noise=1e-4", "solver.max_iter=3")
    assert first.returncode == 0, first.stderr
    (run_dir / "checkpoint.pt").unlink()
    (run_dir / ".result.json.4242.1.tmp").write_text("{")   # a killed writer's: kept here
    before = tree_digest(run_dir)
    refused = run_fit_app(run_dir, "problem.n=16", "problem.noise=1e-4", "solver.max_iter=3",
                          "resume=true")
    errors = [line for line in refused.stderr.splitlines() if line.strip()]
    assert refused.returncode == 2 and len(errors) == 1, refused.stderr
    assert f"{run_dir / 'checkpoint.pt'} is missing" in errors[0]
    assert "another run directory" in errors[0] and "resume=false" not in errors[0]
    assert tree_digest(run_dir) == before
    assert not (run_dir / LOCK_FILE).exists()
