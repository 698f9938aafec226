"""The command line of a TD's first hour (issue 37, items 6 and 7): relative paths from where
they were typed (the scripts no longer change directory; experiments/cli.py makes them
absolute), one ``error:`` line with the nearest key for a misspelt override, a quoting hint
for a value the shell split, ``--help`` on every user command, a quoted TensorBoard hint."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import yaml

from experiments.cli import PATH_KEYS, absolute_paths
from helpers.apps import APPS, run_app
from helpers.capsule_animation import write_capsule

REPO = Path(__file__).resolve().parents[2]
DOC = "docs/guide/install-and-run.md"
_VENV_LOCK = threading.Lock()      # the tests run the scripts two at a time
#: the capsule's quick fit (tests/experiments/test_simulate.py), one iteration
CAPSULE = ("problem=animation", "problem.tet_edge_length=0.15", "problem.grid=[2,2,3]",
           "solver.max_iter=1", "threads=1")


def environment(tmp_path: Path) -> dict[str, str]:
    """The environment of a script run: ``TORCHFIT_VENV`` a stand-in whose ``bin/python``
    is this interpreter and whose install stamp is current (``scripts/_venv.sh`` installs
    nothing), no ``HYDRA_FULL_ERROR``, no ``PYTHONPATH`` (the apps put their checkout first)."""
    venv = tmp_path / "venv"
    with _VENV_LOCK:
        _stand_in_venv(venv)
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "PYTHONPATH")}
    return {**env, "TORCHFIT_VENV": str(venv), "TORCHFIT_EXTRAS": "dev", "TORCHFIT_BLENDER": "0"}


def _stand_in_venv(venv: Path) -> None:
    if not venv.is_dir():
        (venv / "bin").mkdir(parents=True)
        python = venv / "bin" / "python"
        python.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
        python.chmod(0o755)
        stamp = (REPO / "pyproject.toml").read_bytes() + (REPO / "constraints.txt").read_bytes()
        (venv / ".torchfit-install").write_text(hashlib.sha256(stamp + b"dev 0\n").hexdigest()
                                                + "\n")


def command(tmp_path: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """``args`` (a script of scripts/ or an app of experiments/ and its arguments) run in
    ``cwd``: a script as a subprocess, an app (``experiments/<app>.py``) in this process
    (:func:`helpers.apps.run_app`, with the script's environment)."""
    if _is_app(args[0]):
        env = environment(tmp_path)
        return run_app(Path(args[0]).name, *args[1:], cwd=cwd, env=env,
                       unset=("HYDRA_FULL_ERROR", "PYTHONPATH"))
    program = [str(REPO / args[0])] if args[0].endswith(".sh") else \
        [sys.executable, str(REPO / args[0])]
    return subprocess.run([*program, *args[1:]], cwd=cwd, env=environment(tmp_path),
                          capture_output=True, text=True, timeout=300)


def _is_app(path: str) -> bool:
    return path.startswith("experiments/") and Path(path).name in APPS


def commands(tmp_path: Path, cwd: Path, calls: dict) -> dict:
    """:func:`command` of each ``calls`` value (an argument tuple), by key: the scripts two
    at a time in threads, the apps meanwhile in this thread, one after another (an app in
    this process is not thread-safe)."""
    scripts = {key: args for key, args in calls.items() if not _is_app(args[0])}
    with ThreadPoolExecutor(max_workers=2) as pool:
        pending = {key: pool.submit(command, tmp_path, cwd, *args)
                   for key, args in scripts.items()}
        done = {key: command(tmp_path, cwd, *args) for key, args in calls.items()
                if key not in scripts}
        done.update({key: future.result() for key, future in pending.items()})
    return done


def one_error(proc: subprocess.CompletedProcess, *words: str) -> str:
    """The refusal's only line on stderr (exit 2) and that it holds ``words``."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr[-3000:]
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


def test_path_overrides_are_made_absolute():
    """Each path key, relative, plain or quoted, a sweep's choices; absolute values,
    interpolations, null, empty, other keys and other sweeps as they are."""
    cwd = "/home/td/shot (12)"  # brackets: Hydra needs the value quoted
    given = [f"{key}=a/b" for key in PATH_KEYS]
    assert absolute_paths(given, cwd) == [f'{key}="/home/td/shot (12)/a/b"' for key in PATH_KEYS]
    assert absolute_paths(["+problem.init_field=../m.usda", "problem.path=x,y",
                           "hydra.run.dir=runs/${now:%H}", "problem.path=/abs", "init=null",
                           "problem.cache_dir=", "solver.max_iter=3", "problem.path=glob(*)",
                           "--cfg", "job", "problem.path='it is'"], "/w") == \
        ["+problem.init_field=/m.usda", "problem.path=/w/x,/w/y",
         "hydra.run.dir=/w/runs/${now:%H}", "problem.path=/abs", "init=null",
         "problem.cache_dir=", "solver.max_iter=3", "problem.path=glob(*)", "--cfg", "job",
         'problem.path="/w/it is"']


def test_relative_paths_are_from_where_they_were_typed(tmp_path):
    """A missing relative problem.path, init= or run= typed in another directory: the one
    line names the absolute path tried there (the scripts used to resolve it from the
    repository and print it as typed); nothing written."""
    work = tmp_path / "work"
    work.mkdir()
    cases = {
        "path": (("scripts/fit.sh", "problem=animation", "problem.path=shot/missing",
                  "hydra.run.dir=r_path"), str(work / "shot" / "missing")),
        "init": (("scripts/fit.sh", "problem=spring1d", "init=runs/none",
                  "hydra.run.dir=r_init"), str(work / "runs" / "none")),
        "run": (("scripts/simulate.sh", "run=runs/none", "hydra.run.dir=r_sim"),
                str(work / "runs" / "none")),
    }
    done = commands(tmp_path, work, {name: args for name, (args, _) in cases.items()})
    for name, (_, absolute) in cases.items():
        one_error(done[name], absolute)
    assert not list(work.iterdir())


@pytest.mark.slow       # a fit, a simulation and a two-job sweep (about 35 s on 2 busy cores)
def test_fit_and_simulate_from_another_directory(tmp_path):
    """scripts/fit.sh and scripts/simulate.sh run in a directory of the TD's, with relative
    paths to the animation, the mesh cache and the run directories: the outputs are there,
    and the run's record names the absolute paths (simulate, run from a subdirectory,
    finds the fit's animation). A relative hydra.sweep.dir goes there too."""
    work = tmp_path / "work"
    write_capsule(work / "shot" / "capsule")
    fit = command(tmp_path, work, "scripts/fit.sh", *CAPSULE, "problem.path=shot/capsule",
                  "problem.cache_dir=cache", "hydra.run.dir=runs/fit")
    assert fit.returncode == 0, fit.stderr[-3000:]
    config = yaml.safe_load((work / "runs" / "fit" / ".hydra" / "config.yaml").read_text())
    assert config["problem"]["path"] == str(work / "shot" / "capsule")
    assert config["problem"]["cache_dir"] == str(work / "cache")
    assert f"tensorboard --logdir {work / 'runs' / 'fit' / 'tb'}" in fit.stdout
    (work / "later").mkdir()
    sim = command(tmp_path, work / "later", "scripts/simulate.sh", "run=../runs/fit",
                  "hydra.run.dir=sim")
    assert sim.returncode == 0, sim.stderr[-3000:]
    result = json.loads((work / "later" / "sim" / "result.json").read_text())
    assert result["fitted_run"] == str(work / "runs" / "fit")
    assert result["animation"].startswith(str(work / "shot" / "capsule"))
    sweep = command(tmp_path, work, "scripts/fit.sh", "-m", "problem=spring1d", "problem.n=8",
                    "solver.max_iter=1", "solver=gauss_newton,levenberg_marquardt",
                    "hydra.sweep.dir=sweep")
    assert sweep.returncode == 0, sweep.stderr[-3000:]
    assert len(list((work / "sweep").glob("*/result.json"))) == 2
    assert not (REPO / "sweep").exists() and not (REPO / "runs" / "fit").exists()


def test_a_misspelt_override_is_one_line_with_the_nearest_key(tmp_path):
    """Hydra's block (and its advice to add the key with +) gave way to one line with the
    nearest key and where the settings are; +key of a section is refused alike; an unknown
    option of a group names the nearest one. Nothing written."""
    cases = {
        "solver.max_iters=5": ["unknown setting solver.max_iters=5",
                               "did you mean solver.max_iter?", "LevenbergMarquardtConfig",
                               "torchfit/solvers/levenberg_marquardt.py", "--cfg job", DOC],
        "problem.tet_cont=3000": ["unknown setting problem.tet_cont=3000",
                                  "did you mean problem.tet_count?",
                                  "torchfit/problems/body/arm3d.py", DOC],
        "problm.path=x": ["unknown setting problm.path=x", "did you mean problem.path?",
                          "torchfit/config.py", DOC],
        "+problem.foo=1": ["unknown setting problem.foo=1", "tet_count, tet_stop_energy",
                           "Arm3DConfig", DOC],
        "+problem.tet_cont=3000": ["unknown setting problem.tet_cont=3000",
                                   "did you mean problem.tet_count?", DOC],
        "solver=levenbrg": ["solver=levenbrg is not an option",
                            "did you mean solver=levenberg_marquardt?", "split_bregman"],
    }
    done = commands(tmp_path, tmp_path, {o: ("experiments/fit.py",
                                             f"hydra.run.dir={tmp_path / str(hash(o))}", o)
                                         for o in cases})
    for override, words in cases.items():
        one_error(done[override], *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["venv"]      # no run directory


def test_a_value_the_shell_split_is_one_line_saying_to_quote_it(tmp_path):
    run = tmp_path / "run"
    split = command(tmp_path, tmp_path, "experiments/fit.py", f"hydra.run.dir={run}",
                    "problem=animation", "problem.path=/tmp/my", "shot/arm.usda")
    one_error(split, "'shot/arm.usda' is not a setting",
              """'problem.path="/tmp/my shot/arm.usda"'""")
    bracket = command(tmp_path, tmp_path, "experiments/fit.py", f"hydra.run.dir={run}",
                      "problem.path=/tmp/my shot (1)/arm.usda")
    one_error(bracket, "cannot read the override", """'problem.path="/tmp/my shot (1)/arm.usda"'""")
    assert not run.exists()


def test_help_on_every_user_command(tmp_path):
    """--help and -h: what the command does, the settings a TD uses, where the rest is
    documented; exit 0, nothing written (the directory stays empty). Hydra's --cfg job and
    --info still answer."""
    here = tmp_path / "here"
    here.mkdir()
    cases = {
        ("scripts/fit.sh", "--help"): ["Fit the material", "problem.path=", "problem.frames=",
                                       "problem.validation_frames=", "problem.tet_count=",
                                       "solver.max_iter=", "hydra.run.dir=", "threads=",
                                       "resume=true", "init=<run>", "--cfg job", DOC],
        ("scripts/simulate.sh", "-h"): ["Simulate the material", "run=<dir>", "problem.path=",
                                        "problem.frames=null", "docs/guide/simulate.md"],
        ("scripts/test.sh", "--help"): ["test suite", '-m "not slow"', DOC],
        ("scripts/report.py", "--help"): ["result.json", "docs/guide/sweeps.md"],
        ("scripts/write_arm.py", "-h"): ["animation folder", "docs/guide/formats.md"],
        ("experiments/fit.py", "problem=spring1d", "--cfg", "job"): ["name: spring1d"],
        ("experiments/fit.py", "--info", "searchpath"): ["Config search path"],
    }
    done = commands(tmp_path, here, {args: args for args in cases})
    for args, words in cases.items():
        proc = done[args]
        assert proc.returncode == 0, (args, proc.stderr[-2000:])
        assert all(w in proc.stdout for w in words), (args, proc.stdout[-3000:])
    assert not list(here.iterdir())


def test_the_tensorboard_hint_quotes_a_path_with_spaces(tmp_path):
    run = tmp_path / "my run"
    proc = command(tmp_path, tmp_path, "experiments/fit.py", f"hydra.run.dir={run}",
                   "problem=spring1d", "problem.n=8", "solver.max_iter=1")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"tensorboard --logdir '{run / 'tb'}'" in proc.stdout.splitlines()
