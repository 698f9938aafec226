"""scripts/tools/iterates.py compare: two records of the same fits are identical bit for bit,
or the first difference is named and the exit status is 1 (the check of a refactor)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]


def compare(tmp_path: Path, before: dict, after: dict) -> subprocess.CompletedProcess:
    (tmp_path / "before.json").write_text(json.dumps(before))
    (tmp_path / "after.json").write_text(json.dumps(after))
    return subprocess.run([sys.executable, "scripts/tools/iterates.py", "compare",
                           str(tmp_path / "before.json"), str(tmp_path / "after.json")],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


def record(theta_bits: str, misfit: float) -> dict:
    return {"theta_bits": theta_bits, "iterations": 2, "stop_reason": "tolerance",
            "history": [{"iteration": 0, "misfit": 1.0}, {"iteration": 1, "misfit": misfit}]}


def test_identical_records_pass(tmp_path):
    runs = {"spring1d_gn": record("000000000000f03f", 0.5)}
    done = compare(tmp_path, runs, runs)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.strip() == "spring1d_gn: identical"


def test_one_bit_of_theta_or_a_history_row_fails(tmp_path):
    before = {"a": record("000000000000f03f", 0.5), "b": record("00", 0.5)}
    after = {"a": record("010000000000f03f", 0.5), "b": record("00", 0.5 + 2 ** -53)}
    done = compare(tmp_path, before, after)
    assert done.returncode == 1
    lines = done.stdout.splitlines()
    assert lines[0].startswith("a: DIFFERS a/theta_bits:")
    assert lines[1].startswith("b: DIFFERS b/history[1]/misfit:")
