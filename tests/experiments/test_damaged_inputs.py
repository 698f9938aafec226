"""Damaged inputs of issue 38 refused by the app (exit 2, one ``error:`` line naming the file,
nothing written): a resume from a checkpoint holding a NaN (every file of the run directory
byte-identical: ``.hydra/``, ``fit.log``, no new TensorBoard event file), an animation whose
frames are text."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.capsule_animation import write_capsule
from helpers.fit_app import run_fit_app
from helpers.runs import tree_digest


@pytest.mark.slow       # two app runs (~21 s)
def test_the_app_refuses_a_resume_from_a_checkpoint_with_nan_and_writes_nothing(tmp_path):
    run_dir = tmp_path / "run"
    done = run_fit_app(run_dir, "problem=spring1d", "solver.max_iter=2")
    assert done.returncode == 0, done.stderr[-3000:]
    payload = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    payload["theta"][5] = float("nan")              # as the probe damaged it
    payload["solver_state"]["theta"][5] = float("nan")
    torch.save(payload, run_dir / "checkpoint.pt")
    before = tree_digest(run_dir)
    entries = sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*"))
    resumed = run_fit_app(run_dir, "problem=spring1d", "solver.max_iter=4", "resume=true")
    errors = [line for line in resumed.stderr.splitlines() if line.startswith("error: ")]
    assert resumed.returncode == 2, resumed.stderr[-3000:]
    assert "Traceback" not in resumed.stderr and len(errors) == 1, resumed.stderr[-3000:]
    assert str(run_dir / "checkpoint.pt") in errors[0] and "theta: 1 of" in errors[0], errors[0]
    assert "another run directory" in errors[0], errors[0]
    assert tree_digest(run_dir) == before          # .hydra/, fit.log, tb/ untouched
    assert sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*")) == entries
    assert len(list(Path(run_dir / "tb").glob("events.out.tfevents.*"))) == 1


def test_the_app_refuses_frames_of_text_and_leaves_no_run_directory(tmp_path):
    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    np.savez(folder / "frames.npz", frames=np.array(["a", "b"]))
    proc = run_fit_app(tmp_path / "run", "problem=animation", f"problem.path={folder}",
                       f"problem.cache_dir={tmp_path / 'cache'}")
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and len(errors) == 1, proc.stderr[-3000:]
    assert f"{folder / 'frames.npz'} (array 'frames'): holds text (dtype <U1)" in errors[0]
    assert not (tmp_path / "run").exists() and not (tmp_path / "cache").exists()
