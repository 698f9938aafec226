"""README.md's "Your own character, step by step", typed as a TD types it: the section's own
commands, extracted from the README, run one after another in a fresh working directory on
the animation folder, the USD stage and the glTF skin they write.

The only changes to the README's commands: the scripts are named by their path in this
checkout (the TD types them from the repository's root; here the working directory is
elsewhere, which also checks that relative paths are read from where they are typed), and
the fit is made small (a coarse mesh, three fitted frames, one iteration, the test's mesh
cache) by overrides appended to it.
"""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SECTION = "### Your own character, step by step"
#: appended to the fit: the README's steps, small
SMALL_FIT = ("problem.tet_count=1500", "'problem.frames=[0,11,23]'", "solver.max_iter=1",
             "threads=1")


def readme_steps(text: str) -> list[str]:
    """The commands of the README's step-by-step section (its first code block)."""
    body = text.split(SECTION, 1)[1]
    block = re.search(r"```bash\n(.*?)```", body, re.S)
    assert block, f"no bash block under {SECTION}"
    return [line for line in block.group(1).splitlines() if line.strip()]


def as_typed_here(command: str, suffix: str, cache: Path) -> list[str]:
    """``command`` with this checkout's scripts, the animation of the format ``suffix``
    ('' for the folder) and, for the fit, :data:`SMALL_FIT`."""
    words = shlex.split(command)
    if words[0] == ".venv/bin/python":
        words[0] = sys.executable
    words = [str(REPO / w) if w.startswith("scripts/") else w for w in words]
    words = [w + suffix if w in ("problem.path=my_arm", "problem.path=my_shot") else w
             for w in words]
    if words[0].endswith("fit.sh"):
        words += [shlex.split(w)[0] for w in SMALL_FIT] + [f"problem.cache_dir={cache}"]
    if words[0].endswith("simulate.sh"):
        words += [f"problem.cache_dir={cache}"]
    return words


def test_the_section_has_the_four_steps():
    steps = readme_steps((REPO / "README.md").read_text())
    assert len(steps) == 4
    assert "write_arm.py my_arm" in steps[0] and steps[1].startswith("scripts/fit.sh")
    assert "validation_frames" in steps[1] and steps[3].startswith("scripts/simulate.sh")
    assert "problem.frames=null" in steps[3]


def test_the_held_out_frames_of_the_example_are_mid_bend():
    """The README's validation example holds out poses the material decides (issue 47):
    inside the arm's range of flexion, far from rest and from the fold, as it says."""
    from torchfit.problems.body.procedural_arm import elbow_angles

    step = readme_steps((REPO / "README.md").read_text())[1]
    held = json.loads(re.search(r"validation_frames=(\[[0-9,]+\])", step).group(1))
    angles = elbow_angles()
    assert held == [4, 8]
    assert np.allclose(angles[held], [43.6, 87.3], atol=0.1)
    assert all(30 < a < 0.8 * angles.max() for a in angles[held])
    text = (REPO / "README.md").read_text()
    assert "44 and 87" in text and "frames 19 and 15 repeat them" in text
    assert np.isclose(angles[19], angles[4]) and np.isclose(angles[15], angles[8])


@pytest.mark.slow       # three formats, each a small fit and a simulation (about 3 minutes)
@pytest.mark.parametrize("suffix", ["", ".usda", ".glb"])
def test_the_readme_steps_run_in_order(tmp_path, suffix):
    steps = readme_steps((REPO / "README.md").read_text())
    where = tmp_path / "my work"                      # a directory a TD would name
    where.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env.setdefault("TORCHFIT_VENV", str(Path(sys.executable).parents[1]))
    for command in steps:
        proc = subprocess.run(as_typed_here(command, suffix, tmp_path / "cache"), cwd=where,
                              env=env, capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, (command, (proc.stdout + proc.stderr)[-3000:])
    fit = json.loads((where / "outputs" / "mine" / "result.json").read_text())
    assert fit["validation"]["frames"] == [4, 8]
    assert fit["modulus_units"]["unit"] == "relative to problem.E0"
    shot = json.loads((where / "outputs" / "mine_shot" / "result.json").read_text())
    assert shot["n_frames"] == 6                      # fewer than the validation frames' numbers
    assert len(list((where / "outputs" / "mine_shot" / "frames").glob("frame_*.obj"))) == 6
