"""ProgressPrinter: a header and one compact line per outer iteration, through the logging
module (logger torchfit.progress), visible on stdout without logging configuration and
never twice with it."""
from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap

import torch

from torchfit.reporting.progress import PROGRESS_LOGGER, ProgressPrinter
from torchfit.solvers import IterationRecord

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_header_and_lines(caplog):
    printer = ProgressPrinter()
    with caplog.at_level(logging.INFO, logger=PROGRESS_LOGGER):
        printer(IterationRecord(0, torch.zeros(2), 18.8, 6.135, extra={"k_err_rel": 0.7077}))
        printer(IterationRecord(1, torch.zeros(2), 14.9, 5.457, step_norm=4.1, cg_iterations=6,
                                damping=0.25, accepted=False, wall_time=0.5, solves=16))
    records = [r for r in caplog.records if r.name == PROGRESS_LOGGER]
    assert {r.levelno for r in records} == {logging.INFO}
    lines = [r.getMessage() for r in records]
    assert len(lines) == 3
    assert lines[0].split() == ["iter", "misfit", "objective", "k_err_rel", "cg", "damping",
                                "|step|", "solves", "wall", "s"]
    first = lines[1].split()
    assert first[:4] == ["0", "6.135e+00", "1.880e+01", "7.077e-01"]
    assert first[5] == "-" and first[6] == "-"          # NaN damping, no step at iteration 0
    second = lines[2].split()
    assert second[3] == "-"                            # no metric on this record
    assert second[5] == "2.50e-01" and second[-1] == "rejected"


def test_every_and_step_offset(caplog):
    printer = ProgressPrinter(every=2, step_offset=10)
    with caplog.at_level(logging.INFO, logger=PROGRESS_LOGGER):
        for i in range(5):
            printer(IterationRecord(i, torch.zeros(2), 1.0, 1.0))
    lines = [r.getMessage() for r in caplog.records if r.name == PROGRESS_LOGGER]
    assert [line.split()[0] for line in lines] == ["iter", "10", "12", "14"]


STDOUT_THEN_CONFIGURED = textwrap.dedent("""
    import logging, sys
    import torch
    from torchfit.reporting.progress import ProgressPrinter
    from torchfit.solvers import IterationRecord

    # a notebook: logging not configured -> the table on stdout
    printer = ProgressPrinter()
    printer(IterationRecord(0, torch.zeros(2), 2.0, 2.0))
    printer(IterationRecord(1, torch.zeros(2), 1.0, 1.0))
    # an application configures the root logger (as Hydra does): its handler prints the
    # lines, the fallback stays silent
    logging.basicConfig(stream=sys.stdout, level=logging.INFO, format="[app] %(message)s")
    printer(IterationRecord(2, torch.zeros(2), 0.5, 0.5))
    ProgressPrinter(step_offset=7)(IterationRecord(0, torch.zeros(2), 0.5, 0.5))
""")


def test_visible_on_stdout_without_logging_config_and_never_twice():
    env = {**os.environ, "PYTHONPATH": REPO + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-c", STDOUT_THEN_CONFIGURED], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert [line.split()[0] for line in lines] == ["iter", "0", "1", "[app]", "[app]", "[app]"]
    assert [line.split()[1] for line in lines[3:]] == ["2", "iter", "7"]
    assert proc.stderr == ""
