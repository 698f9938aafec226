"""scripts/gpu_check.py without a GPU: the wheel list and its transfer in parts, the
summaries and the goals it judges, and a run on a machine without CUDA (every step
skipped, one JSON)."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def gpu_check():
    spec = importlib.util.spec_from_file_location("gpu_check", REPO / "scripts/gpu_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def check(*args: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "scripts/gpu_check.py", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def test_wheels_are_pinned_by_the_constraints_and_travel_in_parts(tmp_path):
    module = gpu_check()
    pinned = module.pins()
    assert "nvmath-python==1.0.0" in pinned and "nvidia-cudss-cu13==0.8.0.10" in pinned
    commands = check("--download", str(tmp_path / "w"), "--dry-run")["download"]
    assert len(commands) == len(module.WHEELS)
    assert all("--no-deps" in c and "--python-version 3.12" in c and
               "--platform manylinux_2_28_x86_64" in c for c in commands)
    # a wheel above the limit is cut into parts, and joined again from several folders
    folder = tmp_path / "first"
    folder.mkdir()
    payload = os.urandom(2_500_000)
    (folder / "big-1.0-py3-none-any.whl").write_bytes(payload)
    (folder / "small-1.0-py3-none-any.whl").write_bytes(b"small")
    parts = module.split_large(folder, limit_mb=1.0)
    assert parts == [f"big-1.0-py3-none-any.whl.part-0{i}" for i in range(3)]
    second = tmp_path / "second"
    second.mkdir()
    (folder / parts[2]).rename(second / parts[2])          # the last part came separately
    wheels = module.join_parts([folder, second], tmp_path / "joined")
    assert [w.name for w in wheels] == ["big-1.0-py3-none-any.whl",
                                        "small-1.0-py3-none-any.whl"]
    assert wheels[0].read_bytes() == payload


def test_summaries_and_goals(tmp_path):
    module = gpu_check()
    junit = tmp_path / "t.xml"
    junit.write_text(
        '<testsuites><testsuite tests="3" failures="1" errors="0" skipped="1">'
        '<testcase classname="a" name="ok"/>'
        '<testcase classname="a" name="bad"><failure message="boom\nmore"/></testcase>'
        '<testcase classname="a" name="gpu"><skipped message="needs CUDA"/></testcase>'
        '</testsuite></testsuites>')
    summary = module.junit_summary(junit)
    assert (summary["passed"], summary["failures"], summary["skipped"]) == (1, 1, 1)
    assert summary["failed"][0]["test"] == "a::bad"

    def box(setup, forward, again, backward, analyses=1):
        return {"report": {"rows": [{"problem": "device_init"}, {
            "problem": "tetbox", "setup": {"total_s": setup},
            "forward": {"seconds": forward, "counts": {"analyses": analyses}},
            "forward_again": {"seconds": again}, "backward": {"seconds": backward},
            "backward_again": {"seconds": backward / 2}}]}}

    fits = {"misfit": 1.0, "surface_err_mean": 2e-3, "wall_s": 10.0, "tetrahedralize_s": 3.0}
    results = {"tests": {"summary": summary}, "box_linear": box(1.5, 9.0, 1.2, 0.05),
               "neo_hookean_cudss": box(1.0, 4.0, 1.0, 0.1),
               "neo_hookean_cg": box(1.0, 10.1, 1.0, 0.1, analyses=0),
               "arm3d_cuda": {"fit": {**fits, "misfit": 1.0 + 3e-9, "wall_s": 8.0,
                                      "tetrahedralize_s": 9.0}},
               "arm3d_cpu": {"fit": fits}}
    judged = module.goals(results)
    assert judged["cuda_tests_pass"]["met"] is False
    assert judged["linear_box_setup_s"]["met"] and judged["linear_box_further_forward_s"]["met"]
    assert judged["linear_box_backward_s"] == {"value": 0.05, "limit": 0.1, "met": True,
                                               "what": "adjoint solve with the stored factor"}
    assert abs(judged["neo_hookean_forward_vs_cg"]["value"] - 4.0 / 10.1) < 1e-12
    assert judged["neo_hookean_analyses"]["met"]
    assert judged["arm_fit_cuda_vs_cpu"]["value"] == 0.8 and judged["arm_metrics_equal"]["met"]
    assert module.compare_fits(fits, results["arm3d_cuda"]["fit"])["at"] == "misfit"


def test_without_cuda_every_step_is_skipped_in_one_json(tmp_path):
    report = check("--steps", "tests", "box_linear", "--budget-s", "60", "--work",
                   str(tmp_path / "work"))
    assert report["check"] == "gpu" and report["machine"]["cuda_available"] is False
    assert set(report["steps"]) == {"tests", "box_linear"}
    assert all(step == {"skipped": "torch sees no CUDA device here"}
               for step in report["steps"].values())
    assert report["goals"] == {}
    planned = check("--dry-run", "--with-300k")["steps"]
    assert list(planned)[:2] == ["tests", "box_linear"] and "arm300k" in planned
    assert "problem.tet_count=300000" in planned["arm300k"]
    assert "tests/problems/body/test_arm3d.py::test_the_arm_on_cuda_matches_the_cpu" in \
        planned["tests"]
