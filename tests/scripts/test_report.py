"""scripts/report.py: a multirun directory -> one markdown/CSV row per job, failures marked."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]


def report(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "scripts/report.py", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def table_rows(markdown: str) -> list[list[str]]:
    """The cells of every markdown table line (header first, separator dropped)."""
    rows = [[c.strip() for c in line.strip().strip("|").split("|")]
            for line in markdown.splitlines() if line.startswith("|")]
    return [rows[0]] + rows[2:]


def fake_job(sweep: Path, num: int, overrides: list[str], result: dict | None,
             log: str = "") -> Path:
    """A job directory as Hydra and experiments/fit.py leave it."""
    job = sweep / f"{num}_{','.join(o for o in overrides if not o.startswith('experiment'))}"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(
        {"hydra": {"job": {"num": num, "name": "fit"}, "sweeper": {
            "_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"}}}))
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    if result is not None:
        (job / "result.json").write_text(json.dumps(result))
    if log:
        (job / "fit.log").write_text(log)
    return job


def result(k_aligned: float | None, misfit: float | None = 0.1, **extra) -> dict:
    return {"misfit": misfit, "u_err_inf": 1.5e-3, "u_err_2": 2.5e-2, "k_err_inf": 3.0,
            "k_err_2": 12.0, "k_err_rel": 0.4, "k_err_rel_aligned": k_aligned,
            "iterations": 7, "wall_s": 12.345, "factorizations": 9, "solves": 100,
            "converged": True, "stop_reason": "discrepancy", **extra}


@pytest.fixture
def fake_sweep(tmp_path) -> Path:
    """The seed table's 2 x 2 sweep: job 0 fine, job 1 killed, job 2 NaN, job 3 invalid."""
    sweep = tmp_path / "multirun" / "seed"
    sweep.mkdir(parents=True)
    # what Hydra's basic sweeper writes: the sweep parameters and the command line
    (sweep / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {
        "sweeper": {"_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper",
                    "params": {"solver": "gauss_newton,split_bregman",
                               "problem.noise": "0,1e-3"}},
        "overrides": {"task": ["experiment=seed_table", "problem.N=16"]}}}))
    fake_job(sweep, 0, ["solver=gauss_newton", "problem.noise=0", "experiment=seed_table",
                        "problem.N=16"], result(1.234e-2))
    crashed = fake_job(sweep, 1, ["solver=gauss_newton", "problem.noise=0.001",
                                  "experiment=seed_table", "problem.N=16"], None,
                       log="[2026-11-21 10:00:00,000][fit][INFO] - problem poisson2d\n"
                           "[2026-11-21 10:00:05,000][fit][ERROR] - simulation failed at "
                           "iteration 3\n")
    (crashed / "checkpoint.pt").write_bytes(b"")
    fake_job(sweep, 2, ["solver=split_bregman", "problem.noise=0", "experiment=seed_table",
                        "problem.N=16"], result(None, misfit=None, stop_reason="stalled"))
    # job 3: invalid settings; experiments/fit.py wrote why
    fake_job(sweep, 3, ["solver=split_bregman", "problem.noise=0.001", "experiment=seed_table",
                        "problem.N=16"], {"status": "failed", "error": "solver.mu=-1.0: must be > 0"})
    return sweep


def test_fake_sweep_table(fake_sweep, tmp_path):
    out, out_csv = tmp_path / "report.md", tmp_path / "report.csv"
    proc = report(fake_sweep, "--out", out, "--csv", out_csv)
    assert proc.returncode == 0, proc.stderr
    assert out.read_text() == proc.stdout
    assert "Common overrides: `problem.N=16`" in proc.stdout
    rows = table_rows(proc.stdout)
    assert rows[0] == ["job", "solver", "noise", "u_err_inf", "u_err_2", "k_err_inf", "k_err_2",
                       "k_err_rel_aligned", "iterations", "wall [s]", "factorizations",
                       "stop reason"]
    assert rows[1] == ["0", "gauss_newton", "0", "1.50e-03", "2.50e-02", "3.00e+00",
                       "1.20e+01", "1.23e-02", "7", "12.3", "9", "discrepancy"]
    # every job of the 2 x 2 product has a row, in job order, the failures marked
    assert [r[:3] for r in rows[2:]] == [["1", "gauss_newton", "0.001"],
                                         ["2", "split_bregman", "0"],
                                         ["3", "split_bregman", "0.001"]]
    assert rows[2][-1] == ("failed: no result.json (still running, or stopped during the "
                           "fit: checkpoint.pt left): simulation failed at iteration 3")
    assert rows[3][-1] == "failed: non-finite misfit in result.json"
    assert rows[4][-1] == "failed: solver.mu=-1.0: must be > 0"
    assert all(cell == "–" for r in rows[2:] for cell in r[3:-1])
    assert "4 jobs, 3 failed or unfinished." in proc.stdout

    with open(out_csv, newline="") as f:
        records = list(csv.DictReader(f))
    assert [r["job"] for r in records] == ["0", "1", "2", "3"]
    assert float(records[0]["k_err_rel_aligned"]) == 1.234e-2      # full precision
    assert float(records[0]["wall_s"]) == 12.345
    assert records[0]["status"] == "ok" and records[0]["problem.N"] == "16"
    assert [r["status"].split(":")[0] for r in records[1:]] == ["failed"] * 3
    assert records[3]["solver"] == "split_bregman" and Path(records[3]["directory"]).name.startswith("3_")


def test_not_scale_free_shows_k_err_rel(tmp_path):
    sweep = tmp_path / "sweep"
    no_aligned = {k: v for k, v in result(None).items() if k != "k_err_rel_aligned"}
    fake_job(sweep, 0, ["problem.noise=0"], no_aligned)
    fake_job(sweep, 1, ["problem.noise=0.001"], {**no_aligned, "converged": False,
                                                  "stop_reason": "max_iter"})
    proc = report(sweep)
    assert proc.returncode == 0, proc.stderr
    rows = table_rows(proc.stdout)
    assert "k_err_rel" in rows[0] and "k_err_rel_aligned" not in rows[0]
    assert rows[1][rows[0].index("k_err_rel")] == "4.00e-01"
    assert rows[2][-1] == "max_iter (not converged)"


def test_a_sweep_in_mu_with_validation_names_the_lowest_validation_error(tmp_path):
    """``-m solver.mu=...`` with validation frames: the validation columns, and the job the
    validation error picks (not the one of lowest misfit on the fitted frames)."""
    sweep = tmp_path / "sweep"
    for num, (mu, misfit, validation, chosen) in enumerate([(1.0, 0.3, 2.5e-3, 7),
                                                            (10.0, 0.2, 1.9e-3, 5),
                                                            (100.0, 0.1, 2.2e-3, 9)]):
        fake_job(sweep, num, ["solver=split_bregman", f"solver.mu={mu}"], result(
            1e-2, misfit=misfit, validation_surface_err_mean=validation,
            validation_surface_err_reduction=4e-3 / validation, validation_iteration=chosen))
    fake_job(sweep, 3, ["solver=split_bregman", "solver.mu=1000.0"], result(1e-2))
    proc = report(sweep)
    assert proc.returncode == 0, proc.stderr
    rows = table_rows(proc.stdout)
    assert rows[0][-4:] == ["validation err", "validation reduction", "chosen iteration",
                            "stop reason"]
    assert rows[2][-4:-1] == ["1.90e-03", "2.11e+00", "5"]
    assert rows[4][-4:-1] == ["nan", "nan", "nan"]          # a job without validation
    assert "Lowest validation error 1.900e-03: job 1 (`solver.mu=10.0`), at its iteration " \
        "5." in proc.stdout
    # a sweep without validation has none of its columns
    fake_job(tmp_path / "plain", 0, ["problem.noise=0"], result(1e-2))
    assert "validation" not in report(tmp_path / "plain").stdout


@pytest.mark.parametrize("make,message", [
    (lambda p: p / "missing", "does not exist"),
    (lambda p: p, "holds no jobs"),
])
def test_bad_directory_is_one_clear_line(tmp_path, make, message):
    proc = report(make(tmp_path))
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: ") and message in proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""


@pytest.mark.slow
def test_real_joblib_sweep(tmp_path):
    """spring1d through the joblib launcher, one job invalid (tau <= 1 for Gauss-Newton)."""
    sweep = tmp_path / "sweep"
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([sys.executable, "experiments/fit.py", "-m", "problem=spring1d",
                           "hydra/launcher=joblib",
                           "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}", "threads=1",
                           "problem.n=16", "problem.noise=1e-4", "solver.tau=0.5,1.5,2.0",
                           "progress=false"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rep = report(sweep, "--csv", tmp_path / "r.csv")
    assert rep.returncode == 0, rep.stderr
    rows = table_rows(rep.stdout)
    assert rows[0][:2] == ["job", "tau"]
    assert [r[:2] for r in rows[1:]] == [["0", "0.5"], ["1", "1.5"], ["2", "2.0"]]
    assert rows[1][-1].startswith("failed: solver.tau")     # the job's own error line
    for row in rows[2:]:
        job_dir = next(sweep.glob(f"{row[0]}_*"))
        res = json.loads((job_dir / "result.json").read_text())
        assert row[-1] == "discrepancy"
        assert row[rows[0].index("k_err_rel")] == f"{res['k_err_rel']:.2e}"
        assert row[rows[0].index("iterations")] == str(res["iterations"])
        assert row[rows[0].index("factorizations")] == str(res["factorizations"])
    assert "3 jobs, 1 failed or unfinished." in rep.stdout


def test_result_json_not_an_object_is_a_failed_row(tmp_path):
    # valid JSON that is not an object (issue 27, item 6): a failed row, never a traceback
    sweep = tmp_path / "sweep"
    fake_job(sweep, 0, ["problem.noise=0"], result(1e-2))
    fake_job(sweep, 1, ["problem.noise=0.001"], None)
    (sweep / "1_problem.noise=0.001" / "result.json").write_text("[1, 2, 3]")
    fake_job(sweep, 2, ["problem.noise=0.01"], None)
    (sweep / "2_problem.noise=0.01" / "result.json").write_text('"done"')
    proc = report(sweep)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    rows = table_rows(proc.stdout)
    assert rows[1][-1] == "discrepancy"
    assert rows[2][-1] == "failed: unreadable result.json (a JSON list, not an object)"
    assert rows[3][-1] == "failed: unreadable result.json (a JSON str, not an object)"


# -- issue 38: run directories, output folders ------------------------------------------------
def fake_run(run_dir: Path, overrides: list[str], res: dict | None) -> Path:
    """A single run's directory as experiments/fit.py leaves it: Hydra writes ``num: ???``."""
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "hydra.yaml").write_text(
        "hydra:\n  run:\n    dir: " + str(run_dir) + "\n  job:\n    name: fit\n    num: ???\n"
        "    id: ???\n  mode: RUN\n")
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    if res is not None:
        (run_dir / "result.json").write_text(json.dumps(res))
    return run_dir


def test_one_run_directory_is_a_one_row_table(tmp_path):
    run = fake_run(tmp_path / "outputs" / "2026-12-01" / "10-00-00",
                   ["problem=spring1d", "problem.n=16"], result(1.234e-2))
    proc = report(run, "--csv", tmp_path / "r.csv")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    rows = table_rows(proc.stdout)
    assert rows[0][:3] == ["job", "problem", "n"]
    assert len(rows) == 2 and rows[1][:3] == ["10-00-00", "spring1d", "16"]
    assert rows[1][rows[0].index("k_err_rel_aligned")] == "1.23e-02"
    assert rows[1][-1] == "discrepancy" and "1 job, 0 failed or unfinished." in proc.stdout
    with open(tmp_path / "r.csv", newline="") as f:
        assert [r["job"] for r in csv.DictReader(f)] == ["10-00-00"]


def test_several_run_directories_in_the_order_given(tmp_path, fake_sweep):
    first = fake_run(tmp_path / "b_first", ["solver.mu=1.0"], result(2e-2))
    second = fake_run(tmp_path / "a_second", ["solver.mu=10.0"], None)   # killed, no result
    proc = report(first, second, fake_sweep)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    rows = table_rows(proc.stdout)
    assert [r[0] for r in rows[1:]] == ["b_first", "a_second", "0", "1", "2", "3"]
    assert rows[1][rows[0].index("mu")] == "1.0" and rows[1][-1] == "discrepancy"
    assert rows[2][-1] == "failed: no result.json"
    assert "6 jobs, 4 failed or unfinished." in proc.stdout
    # one bad directory among them: one line, nothing on stdout
    proc = report(first, tmp_path / "missing")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: ")
    assert f"{tmp_path / 'missing'} does not exist" in proc.stderr


def test_out_and_csv_into_folders_that_do_not_exist_are_created(fake_sweep, tmp_path):
    out, out_csv = tmp_path / "new" / "deep" / "report.md", tmp_path / "other" / "r.csv"
    proc = report(fake_sweep, "--out", out, "--csv", out_csv)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert out.read_text() == proc.stdout
    with open(out_csv, newline="") as f:
        assert [r["job"] for r in csv.DictReader(f)] == ["0", "1", "2", "3"]


@pytest.mark.parametrize("where,message", [
    (lambda p: p, "is a folder; name a file in it"),
    (lambda p: p / "result.json" / "report.md", "is a file, not a folder"),
    (lambda p: p / "readonly" / "sub" / "report.md", "no permission to write"),
])
def test_an_output_that_cannot_be_written_is_one_line_and_nothing_written(tmp_path, where,
                                                                          message):
    run = fake_run(tmp_path / "run", ["problem.n=16"], result(1e-2))
    (run / "readonly").mkdir()
    (run / "readonly").chmod(0o500)
    before = sorted(str(p) for p in tmp_path.rglob("*"))
    try:
        target = where(run)
        if message == "no permission to write" and os.access(run / "readonly", os.W_OK):
            pytest.skip("running as root: permissions are not enforced")
        # a good --csv beside the bad --out: neither is written
        proc = report(run, "--csv", tmp_path / "fine" / "r.csv", "--out", target)
    finally:
        (run / "readonly").chmod(0o700)
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"error: --out {target}")
    assert message in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(str(p) for p in tmp_path.rglob("*")) == before


def test_help_says_what_it_takes():
    proc = report("--help")
    assert proc.returncode == 0 and "run directory" in proc.stdout and "--out" in proc.stdout
