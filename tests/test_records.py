"""The records every solver emits: the stop reasons (an Enum listing every reason the code
emits), the iteration record's rows and the result's summary."""
import ast
import io
import json
import math
from pathlib import Path

import torch

from torchfit.records import IterationRecord, SolveResult, StopReason

SOLVERS = Path(__file__).resolve().parents[1] / "torchfit" / "solvers"


def emitted_reasons() -> set[str]:
    """Every ``StopReason.<name>`` the solver package names."""
    found = set()
    for path in SOLVERS.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                    and node.value.id == "StopReason":
                found.add(node.attr)
    return found


def test_every_reason_the_solvers_emit_is_a_member_and_documented():
    members = {reason.name for reason in StopReason}
    assert emitted_reasons() <= members
    # ``validation``: the run's early stopping by validation (torchfit/run/validation.py)
    assert members == {"discrepancy", "tolerance", "resolution", "plateau", "max_iter",
                       "line_search", "stalled", "interrupted", "validation"}
    for reason in StopReason:
        assert reason.name == reason.value
        assert f"``{reason.value}``" in StopReason.__doc__


def test_a_stop_reason_is_its_value_as_text():
    reason = StopReason.discrepancy
    assert reason == "discrepancy" and str(reason) == "discrepancy"
    assert f"{reason} after" == "discrepancy after" and "%s" % reason == "discrepancy"
    assert json.dumps({"stop_reason": reason}) == '{"stop_reason": "discrepancy"}'
    assert StopReason("plateau") is StopReason.plateau
    # a checkpoint stores the value: torch.load(weights_only=True) reads plain strings
    buffer = io.BytesIO()
    torch.save({"stop_reason": str(reason)}, buffer)
    buffer.seek(0)
    assert type(torch.load(buffer, weights_only=True)["stop_reason"]) is str


def test_rows_and_summary_are_plain():
    record = IterationRecord(3, torch.zeros(2), 0.5, 1.0, step_norm=0.1, extra={"tv": 2.0})
    row = record.row(step_offset=10)
    assert row["iteration"] == 13 and row["tv"] == 2.0 and math.isnan(row["damping"])
    result = SolveResult(torch.zeros(2), True, StopReason.tolerance, 3, [record], 1.0, 4, 5)
    summary = result.summary()
    assert type(summary["stop_reason"]) is str and summary["stop_reason"] == "tolerance"
    assert json.loads(json.dumps(summary))["misfit"] == 1.0
