"""ProgressPrinter: a header and one compact line per outer iteration."""
from __future__ import annotations

import io

import torch

from torchfit.logging import ProgressPrinter
from torchfit.solvers import IterationRecord


def test_header_and_lines():
    out = io.StringIO()
    printer = ProgressPrinter(stream=out)
    printer(IterationRecord(0, torch.zeros(2), 18.8, 6.135, extra={"k_err_rel": 0.7077}))
    printer(IterationRecord(1, torch.zeros(2), 14.9, 5.457, step_norm=4.1, cg_iterations=6,
                            damping=0.25, accepted=False, wall_time=0.5, solves=16))
    lines = out.getvalue().splitlines()
    assert len(lines) == 3
    assert lines[0].split() == ["iter", "misfit", "objective", "k_err_rel", "cg", "damping",
                                "|step|", "solves", "wall", "s"]
    first = lines[1].split()
    assert first[:4] == ["0", "6.135e+00", "1.880e+01", "7.077e-01"]
    assert first[5] == "-" and first[6] == "-"          # NaN damping, no step at iteration 0
    second = lines[2].split()
    assert second[3] == "-"                            # no metric on this record
    assert second[5] == "2.50e-01" and second[-1] == "rejected"
