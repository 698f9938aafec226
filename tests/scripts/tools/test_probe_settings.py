"""scripts/tools/probe_settings.py: bad values per setting type, the classification of an
outcome (PASS only for exit 2, one ``error:`` line naming the setting, nothing written), and
a short real run on spring1d."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
_spec = importlib.util.spec_from_file_location("probe_settings",
                                               REPO / "scripts/tools/probe_settings.py")
probe = importlib.util.module_from_spec(_spec)
sys.modules["probe_settings"] = probe
_spec.loader.exec_module(probe)


def case(key: str = "problem.noise") -> "probe.Case":
    return probe.Case("spring1d", key, "-1", "float", ["problem=spring1d", f"{key}=-1"])


def test_one_error_line_naming_the_setting_and_nothing_written_passes(tmp_path):
    c = probe.classify(case(), 2, "error: problem.noise=-1 must be >= 0\n", tmp_path / "absent")
    assert (c.outcome, c.reason) == ("PASS", "")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert probe.classify(case(), 2, "error: noise must be >= 0\n", empty).outcome == "PASS"


@pytest.mark.parametrize("code, stderr, reason", [
    (1, "error: problem.noise must be >= 0\n", "exit 1"),
    (2, "Traceback (most recent call last):\n  File x\nValueError: noise\n", "a traceback"),
    (2, "warning: something\nerror: problem.noise must be >= 0\n", "2 stderr lines"),
    (2, "problem.noise must be >= 0\n", "the line does not start with error:"),
    (2, "error: a value must be >= 0\n", "the line does not name noise"),
])
def test_other_refusals_fail_with_the_reason(tmp_path, code, stderr, reason):
    c = probe.classify(case(), code, stderr, tmp_path / "absent")
    assert (c.outcome, c.reason) == ("FAIL", reason)


def test_files_left_behind_fail(tmp_path):
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / "fit.log").write_text("x")
    c = probe.classify(case(), 2, "error: problem.noise must be >= 0\n", run)
    assert (c.outcome, c.reason, c.left) == ("FAIL", "2 files left", [".hydra", "fit.log"])


def test_exit_0_is_accepted_and_no_status_is_a_timeout(tmp_path):
    assert probe.classify(case(), 0, "", tmp_path).outcome == "ACCEPTED"
    assert probe.classify(case(), None, "", tmp_path).outcome == "TIMEOUT"


def test_bad_values_follow_the_type():
    assert {"-1", "0", "nan", "inf", "1e12", "abc"} == {v for v, _ in
                                                       probe.bad_values("a.b", "float", 1.0)}
    assert ("1000000000000", "int") in probe.bad_values("a.n", "int", 4)
    assert probe.bad_values("a.dynamic", "bool", False) == [("maybe", "bool")]
    assert ("[1.0,2.0]", "list") in probe.bad_values("a.grid", "list", [3])
    assert ("[a,b]", "list") in probe.bad_values("a.grid", "list", [3, 4])
    assert probe.bad_values("a.backend", "str", "auto") == [("autox", "choice")]
    assert probe.bad_values("problem.path", "str", "") == [(probe.MISSING_PATH, "path")]


def test_totals_count_every_outcome_per_section():
    cs = [probe.Case("a", "k", "v", "int", [], outcome=o) for o in ("PASS", "PASS", "FAIL")]
    cs.append(probe.Case("b", "k", "v", "int", [], outcome="TIMEOUT"))
    t = probe.totals(cs)
    assert t["a"] == {"PASS": 2, "ACCEPTED": 0, "FAIL": 1, "TIMEOUT": 0}
    assert t["all"]["TIMEOUT"] == 1 and sum(t["all"].values()) == 4


@pytest.mark.slow     # 27 s on the loaded 2-core machine (two app runs plus the compose)
def test_a_short_run_on_spring1d(tmp_path):
    out = tmp_path / "probe.json"
    done = subprocess.run([sys.executable, "scripts/tools/probe_settings.py", "--only",
                           "spring1d", "--limit", "2", "--out", str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    record = json.loads(out.read_text())
    assert len(record["cases"]) == 2 and sum(record["totals"]["spring1d"].values()) == 2
    first = record["cases"][0]
    assert first["key"].startswith("problem.") and first["outcome"] in probe.OUTCOMES
    # problem.noise=-1 (the first case): refused in one line naming it, nothing written
    assert (first["key"], first["value"], first["outcome"]) == ("problem.noise", "-1", "PASS")
    assert "spring1d" in done.stdout and "PASS" in done.stdout


def test_a_switched_section_probes_the_problem_with_its_switch_on():
    """``arm3d@dynamic``: the arm's settings with ``problem.dynamic=true`` in every case (the
    settings of the body in time come into play), the switch itself probed too."""
    assert "arm3d@dynamic" in probe.sections()
    cases = probe.cases_for("arm3d@dynamic", None)
    assert {c.key for c in cases} >= {"problem.substeps", "problem.density", "problem.dynamic"}
    substeps = next(c for c in cases if c.key == "problem.substeps")
    assert "problem.dynamic=true" in substeps.overrides and "problem.substeps=1" not in \
        substeps.overrides and substeps.overrides[-1].startswith("problem.substeps=")
    assert "@" not in substeps.name and substeps.name.startswith("arm3d_dynamic__")
