"""scripts/blender/torchfit_blender/job.py: a real fit in the background, cancelled with
SIGTERM and resumed to the end with the same settings."""
from __future__ import annotations

import json
import time

import pytest

from torchfit_blender.job import last_error_line
from torchfit_blender.results import read_progress, read_summary

pytestmark = pytest.mark.slow


def test_a_cancelled_fit_resumes_to_its_end(limb_rig, tmp_path, start_fit):
    job = start_fit(limb_rig, tmp_path / "job", iterations=4)
    assert job.running                                   # start returns at once
    deadline = time.monotonic() + 300
    while read_progress(job.run, 4).iteration < 1 and job.running:
        assert time.monotonic() < deadline
        time.sleep(0.2)
    assert job.cancel() == 143, job.console.read_text()[-2000:]   # SIGTERM: torchfit's 143
    assert read_summary(job.run) is None and (job.run / "checkpoint.pt").is_file()
    stopped = read_progress(job.run, 4).iteration
    assert 1 <= stopped < 4
    resumed = start_fit(limb_rig, tmp_path / "job", resume=True, iterations=4)
    assert resumed.wait(timeout=600) == 0, resumed.console.read_text()[-3000:]
    rows = [json.loads(x) for x in (job.run / "history.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [0, 1, 2, 3, 4]
    assert read_summary(job.run).iterations == 4


def test_a_failed_start_says_torchfits_error_line(limb_rig, tmp_path, start_fit):
    job = start_fit(limb_rig, tmp_path / "job", model="no_such_model")
    assert job.wait(timeout=300) != 0
    line = job.error_line()
    assert "no_such_model" in line and "model" in line
    assert last_error_line(tmp_path / "missing.txt") == ""
