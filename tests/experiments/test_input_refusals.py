"""Bad input of issue 27 refused by the app (experiments/fit.py, run in the test's process by
:func:`helpers.apps.run_app`): exit 2, one ``error:`` line naming the setting, nothing
written. The checks of the problems themselves are in tests/problems/test_input_checks.py."""
from __future__ import annotations

import subprocess

import pytest

from helpers.apps import run_app
from helpers.repeating_animation import write_tube


def fit(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python experiments/fit.py <args>`` from the repository root, in this process."""
    return run_app("fit.py", *args, env=env)


def refused(proc: subprocess.CompletedProcess, *words: str) -> str:
    """The one error line of a refusal (exit 2, no traceback) that holds ``words``."""
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and len(errors) == 1, proc.stderr[-3000:]
    assert all(w in errors[0] for w in words), errors[0]
    return errors[0]


def test_refusals_through_the_app(tmp_path):
    long_value = "x" * 300
    cases = {
        # a job directory name over 255 bytes: Hydra's traceback became one line
        "sweep": (["-m", f"hydra.sweep.dir={tmp_path / 'sweep'}", "problem=spring1d",
                   "problem.n=8", f"problem.targets=/tmp/{long_value}"],
                  ["317 bytes", "255", "problem.targets=/tmp/xxx",
                   "exclude_keys=[problem.targets]"]),
        # Hydra's hint for a misspelt key is to add it with "+": refused, the keys listed
        "typo": ([f"hydra.run.dir={tmp_path / 'typo'}", "problem=spring1d", "problem.n=8",
                  "+contination=true"],
                 ["unknown top-level setting contination=True", "did you mean continuation?",
                  "problem, solver, resume, init, continuation,"]),
    }

    done = {name: fit(*overrides) for name, (overrides, _) in cases.items()}
    for name, (_, words) in cases.items():
        refused(done[name], *words)
    assert not (tmp_path / "sweep").exists()       # not even multirun.yaml
    assert not [p for p in tmp_path.iterdir()]     # no run directory of any case


@pytest.mark.slow
def test_a_size_is_refused_through_the_app(tmp_path):
    # sizes: refused from the settings before anything is allocated (in-process in
    # tests/problems/test_input_checks.py; here the exit status and the run directory)
    proc = fit(f"hydra.run.dir={tmp_path / 'size'}", "problem=spring1d", "problem.n=10000000000",
               env={"TORCHFIT_MEMORY_LIMIT": "1G"})
    refused(proc, "problem.n=10000000000: needs about 2.3 TiB for 10000000001 nodes x 3 frames",
            "1.0 GiB of TORCHFIT_MEMORY_LIMIT")
    assert not (tmp_path / "size").exists()


def test_bad_validation_frames_are_refused_through_the_app(tmp_path):
    """A validation frame not in the animation, every frame held out, a frame both fitted
    and validated: one line naming the setting, exit 2, no run directory (the rules in-process:
    tests/problems/test_held_out.py)."""
    body = [f"problem.path={write_tube(tmp_path / 'tube')}", "problem=animation",
            f"problem.cache_dir={tmp_path / 'cache'}"]
    cases = {
        "missing": (["problem.validation_frames=[2,8]"],
                    ["problem.validation_frames=[2, 8]: frame 8 is not a frame of the "
                     "animation (0..7)"]),
        "all": (["problem.validation_every=1"],
                ["problem.validation_every=1: holds out every frame of the fit"]),
        "overlap": (["problem.frames=[0,1,2]", "problem.validation_frames=[2,5]"],
                    ["problem.validation_frames=[2, 5]: overlaps problem.frames (frames [2])"]),
    }

    done = {name: fit(f"hydra.run.dir={tmp_path / name}", *body, *overrides)
            for name, (overrides, _) in cases.items()}
    for name, (_, words) in cases.items():
        refused(done[name], *words)
        assert not (tmp_path / name).exists(), name
