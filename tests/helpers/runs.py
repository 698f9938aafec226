"""Helpers of the run tests: quiet options, a run in a killable subprocess, and what a run
directory holds (parameters, TensorBoard steps, file digests)."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import torch
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

from torchfit.run import FitOptions

REPO = Path(__file__).resolve().parents[2]
QUIET = FitOptions(progress=False)

SCRIPT = """
import json, os, signal, sys
from torchfit.run import FitOptions, fit
from torchfit.problems import build_problem
run_dir, problem, solver, kill_at, resume = sys.argv[1:6]
def killer(record):
    if record.iteration == int(kill_at):
        os.kill(os.getpid(), signal.SIGKILL)   # no cleanup, no flush: as a crash or OOM kill
fit(build_problem("spring1d", json.loads(problem)), json.loads(solver), run_dir=run_dir,
    resume=resume == "1", callbacks=[killer], options=FitOptions(progress=False))
"""


def run_script(run_dir: Path, problem: dict, solver: dict, kill_at: int = -1,
               resume: bool = False) -> subprocess.CompletedProcess:
    """A spring1d fit in a subprocess, SIGKILLed after the record of ``kill_at`` (if >= 0)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", SCRIPT, str(run_dir), json.dumps(problem),
                           json.dumps(solver), str(kill_at), "1" if resume else "0"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)


def scalar_steps(logdir: Path, tag: str) -> list[int]:
    """Every step written for ``tag`` in every event file (not a sample)."""
    steps = []
    for path in sorted(logdir.glob("events.out.tfevents.*")):
        for event in EventFileLoader(str(path)).Load():
            steps += [event.step for value in event.summary.value if value.tag == tag]
    return sorted(steps)


def load_params(run_dir: Path) -> dict:
    with open(run_dir / "params.pt", "rb") as f:
        return torch.load(f, weights_only=True)


def tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}
