"""Sweep presets of experiments/fit.py (conf/experiment/, conf/hydra/launcher/) and the
launchers and sweeper they use: joblib, submitit (local executor), Optuna.

The app runs in the test's process (:func:`fit`, :func:`helpers.apps.run_app`); with the
submitit launcher (it starts the jobs as processes of their own) as a subprocess."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from helpers.apps import run_app
from helpers.fit_app import with_problem

REPO = Path(__file__).resolve().parents[2]


def fit(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python experiments/fit.py <args>`` (spring1d unless they choose a problem) from the
    repository root, in this process."""
    return run_app("fit.py", *with_problem(args))


def fit_process(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """:func:`fit` as a subprocess."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "experiments/fit.py", *with_problem(args)], cwd=REPO,
                          env=env,
                          capture_output=True, text=True, timeout=timeout)


def ok(proc: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-4000:]}\nstderr:\n{proc.stderr[-4000:]}"
    return proc


def composed(*overrides: str, part: str = "job") -> dict:
    """The config a run would get (``part="hydra"``: the ``hydra`` node), composed in this
    process by Hydra's compose API (what ``--cfg job|hydra`` prints), interpolations kept."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from torchfit.config import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="fit", overrides=with_problem(overrides),
                      return_hydra_config=part == "hydra")
    config = OmegaConf.to_container(cfg, resolve=False)
    return config if part == "hydra" else {k: v for k, v in config.items() if k != "hydra"}


def test_membrane2d_chooses_its_solver_and_threads():
    assert composed("problem=membrane2d")["solver"]["name"] == "levenberg_marquardt"
    assert composed("problem=membrane2d")["solver"]["geodesic_acceleration"] is True
    assert composed("problem=membrane2d")["threads"] == 1
    assert composed("problem=membrane2d", "solver=gauss_newton")["solver"]["name"] == "gauss_newton"
    assert composed()["solver"]["name"] == "gauss_newton"
    assert composed()["problem"]["name"] == "spring1d"


def test_seed_table_preset():
    job = composed("experiment=seed_table")
    assert job["problem"]["name"] == "poisson2d"
    assert (job["problem"]["N"], job["problem"]["pattern"]) == (64, "blocks")
    assert job["threads"] == 1
    hydra = composed("experiment=seed_table", part="hydra")["hydra"]
    assert hydra["sweeper"]["params"] == {"solver": "gauss_newton,split_bregman",
                                          "problem.data": "dense,sparse",
                                          "problem.noise": "0,1e-3"}
    assert hydra["launcher"]["_target_"].endswith("JoblibLauncher")
    assert hydra["launcher"]["n_jobs"] == 2
    assert hydra["sweep"]["dir"].startswith("multirun/seed_table/")
    assert hydra["job"]["config"]["override_dirname"]["exclude_keys"] == ["experiment"]


@pytest.mark.parametrize("overrides", [["experiment=seed_table_slurm"],
                                       ["experiment=seed_table", "hydra/launcher=slurm"]])
def test_slurm_launcher_preset(overrides):
    hydra = composed(*overrides, "hydra.launcher.partition=cpu", part="hydra")["hydra"]
    launcher = hydra["launcher"]
    assert launcher["_target_"].endswith("submitit_launcher.SlurmLauncher")
    assert (launcher["cpus_per_task"], launcher["partition"]) == (1, "cpu")
    assert "n_jobs" not in launcher
    assert hydra["sweeper"]["params"]["solver"] == "gauss_newton,split_bregman"


def test_sb_tuning_preset():
    job = composed("experiment=sb_tuning")
    assert job["solver"]["name"] == "split_bregman"
    assert (job["problem"]["N"], job["problem"]["data"], job["problem"]["noise"]) == (
        64, "dense", 1e-3)
    assert job["objective_metric"] == "k_err_rel_aligned"
    sweeper = composed("experiment=sb_tuning", part="hydra")["hydra"]["sweeper"]
    assert sweeper["_target_"].endswith("OptunaSweeper")
    assert sweeper["storage"] is None and sweeper["direction"] == "minimize"
    assert set(sweeper["params"]) == {"solver.mu_start_rel", "solver.growth", "solver.tau",
                                      "solver.beta_rel", "solver.isotropic"}


def test_optuna_ranks_an_invalid_trial_last(tmp_path):
    """Two grid trials on spring1d, one invalid (tau <= 1): it returns +inf (a NaN would
    abort the study inside hydra-optuna-sweeper), the valid one is the best, and the best
    value is the job's ``objective_metric`` read back from its result.json."""
    sweep = tmp_path / "opt"
    ok(fit("-m", "hydra/sweeper=optuna", "hydra/sweeper/sampler=grid",
           "hydra.sweeper.storage=null", "hydra.sweeper.n_trials=2", "hydra.sweeper.n_jobs=1",
           f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=${hydra.job.num}",
           "solver.tau=choice(0.5,1.5)", "objective_metric=k_err_rel", "problem.n=16",
           "problem.noise=1e-4", "progress=false", timeout=180))
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert best["best_params"] == {"solver.tau": 1.5}
    results = [json.loads(p.read_text()) for p in sweep.glob("*/result.json")]
    failed = [r for r in results if r["status"] == "failed"]
    done = [r for r in results if r["status"] == "completed"]
    assert len(failed) == 1 and "solver.tau" in failed[0]["error"]    # the invalid trial says why
    assert len(done) == 1 and best["best_value"] == done[0]["k_err_rel"]
    assert math.isfinite(best["best_value"]) and best["best_value"] < 0.05


def test_objective_metric_must_be_reported(tmp_path):
    proc = fit(f"hydra.run.dir={tmp_path / 'run'}", "objective_metric=k_err_rel_aligned",
               timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "objective_metric=k_err_rel_aligned is not reported by spring1d" in proc.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_sb_tuning_runs_optuna(tmp_path):
    """The sb_tuning preset end to end on a tiny grid (N = 8): three trials through joblib,
    optimization_results.yaml, one result.json per trial, best value = best trial's
    k_err_rel_aligned."""
    sweep = tmp_path / "tuning"
    ok(fit("-m", "experiment=sb_tuning", "problem.N=8", "solver.max_iter=8",
           "hydra.sweeper.n_trials=3", f"hydra.sweep.dir={sweep}"))
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert set(best["best_params"]) == {"solver.mu_start_rel", "solver.growth", "solver.tau",
                                        "solver.beta_rel", "solver.isotropic"}
    trials = sorted(p.parent.name for p in sweep.glob("*/result.json"))
    assert trials == ["0", "1", "2"]
    errors = [json.loads((sweep / t / "result.json").read_text())["k_err_rel_aligned"]
              for t in trials]
    assert best["best_value"] == min(errors)
    for t in trials:       # each trial ran the weights Optuna chose for it
        overrides = yaml.safe_load((sweep / t / ".hydra" / "overrides.yaml").read_text())
        config = json.loads((sweep / t / "result.json").read_text())["config"]["solver"]
        growth = float(next(o for o in overrides if o.startswith("solver.growth=")).split("=")[1])
        assert config["growth"] == growth and 2.0 <= growth <= 10.0


@pytest.mark.slow
def test_submitit_local_launcher(tmp_path):
    """The submitit launcher (its local executor: separate processes, no SLURM) runs a
    two-job spring1d sweep; both jobs write their results into the sweep directory."""
    sweep = tmp_path / "sub"
    ok(fit_process("-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5",
           f"hydra.sweep.dir={sweep}", "solver=gauss_newton,levenberg_marquardt",
           "problem.n=16", "problem.noise=1e-4", "solver.max_iter=20", "threads=1",
           "progress=false"))
    results = sorted(sweep.glob("*/result.json"))
    assert len(results) == 2
    solvers = sorted(json.loads(p.read_text())["config"]["solver"]["name"] for p in results)
    assert solvers == ["gauss_newton", "levenberg_marquardt"]
    for path in results:
        assert json.loads(path.read_text())["k_err_rel"] < 0.05
    assert (sweep / ".submitit").is_dir()        # submitit's own job files
