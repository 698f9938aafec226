"""Fault injection on the fit app (issue 27): what a probe of the fault path did, seeded.

Each case asserts the promise of docs/guide/resume.md: a run killed at any point
continues with ``resume=true`` to the uninterrupted run's ``params.pt`` (``torch.equal``),
iterations and stop reason; a corrupt file of a run directory either resumes to the same
result or is refused with one ``error:`` line (exit 2) leaving the directory byte-identical,
never a traceback; two runs started at once into one directory: one runs, the other exits
2; a full disk stops the run with one line naming the file and the resume command, leaves
no empty or temporary file, and the resume after space is freed ends where the
uninterrupted run ended. The fast suite runs a seeded sample of each; ``-m slow`` all.

What is about a process runs the app as one (the run that is killed, the two runs at once,
the runs on a full disk in a private mount namespace, and the uninterrupted reference,
whose wall time places the kills); the resumes after a kill or a damaged file run in the
test's process (:func:`helpers.fit_app.run_fit_app`).
"""
from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from helpers.fit_app import REPO, run_fit_app, run_fit_app_process
from helpers.runs import tree_digest

SEED = 20261126
PROBLEM = ("problem=spring1d", "problem.n=16", "problem.noise=1e-4", "solver.max_iter=4")
LOCK_FILE = ".torchfit.lock"


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}


def _command(run_dir: Path, *extra: str) -> list[str]:
    return [sys.executable, "experiments/fit.py", f"hydra.run.dir={run_dir}", *PROBLEM, *extra]


def _params(run_dir: Path) -> dict:
    with open(run_dir / "params.pt", "rb") as f:
        return torch.load(f, weights_only=False)


def _same_result(run_dir: Path, reference: Path) -> None:
    """``run_dir`` ended where the uninterrupted ``reference`` did."""
    mine, theirs = _params(run_dir), _params(reference)
    assert torch.equal(mine["theta"], theirs["theta"])
    result = json.loads((run_dir / "result.json").read_text())
    expected = json.loads((reference / "result.json").read_text())
    # every metric, count and the stop (wall time aside), to the last digit; the
    # identifiability report's and the uncertainty's figures too (where they took their
    # Jacobian, and its seconds, may differ: outputs written again from a checkpoint have no
    # linearisation of the solver's to reuse)
    provenance = ("source", "extra_products", "cost")
    for key, value in expected.items():
        if key in ("identifiability", "uncertainty"):
            assert {k: v for k, v in result[key].items() if k not in provenance} == \
                {k: v for k, v in value.items() if k not in provenance}
        elif key not in ("wall_s", "resumed_from_iteration", "config", "history"):
            assert result.get(key) == value, key
    assert [row["misfit"] for row in result["history"]] == \
        [row["misfit"] for row in expected["history"]]
    rows = [json.loads(line) for line in (run_dir / "history.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == list(range(result["iterations"] + 1))


def _clean(run_dir: Path) -> None:
    """No lock, no temporary and no empty file is left in ``run_dir``."""
    assert not (run_dir / LOCK_FILE).exists()
    leftovers = [p for p in run_dir.rglob("*") if p.is_file() and (
        p.name.endswith(".tmp") or ".tmp." in p.name or p.stat().st_size == 0)]
    assert not leftovers, leftovers


def _one_error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr[-2000:]
    assert "Traceback" not in stderr
    return lines[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, float]:
    """The uninterrupted run and its wall time (s), a subprocess: the kills are placed in the
    wall time of a process that imports and runs the app."""
    run_dir = tmp_path_factory.mktemp("faults") / "reference"
    started = time.perf_counter()
    done = run_fit_app_process(run_dir, *PROBLEM)
    assert done.returncode == 0, done.stderr[-2000:]
    return run_dir, time.perf_counter() - started


# -- kill at random points ------------------------------------------------------------------
def _kill_points(count: int) -> list[float]:
    """Seeded kill times as fractions of the reference run's wall time."""
    rng = random.Random(SEED)
    return [round(rng.uniform(0.35, 1.0), 3) for _ in range(count)]


def _kill_and_resume(tmp_path: Path, reference: tuple[Path, float], fraction: float) -> None:
    ref_dir, wall = reference
    run_dir = tmp_path / f"killed_{fraction}"
    proc = subprocess.Popen(_command(run_dir), cwd=REPO, env=_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        proc.wait(timeout=fraction * wall)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    resumed = run_fit_app(run_dir, *PROBLEM, "resume=true")
    assert resumed.returncode == 0, (fraction, resumed.stderr[-2000:])
    _same_result(run_dir, ref_dir)
    _clean(run_dir)


@pytest.mark.parametrize("fraction", _kill_points(1))
def test_a_run_killed_at_a_seeded_random_point_resumes_to_the_same_result(tmp_path, reference,
                                                                          fraction):
    _kill_and_resume(tmp_path, reference, fraction)


@pytest.mark.slow
@pytest.mark.parametrize("fraction", _kill_points(6)[1:])
def test_runs_killed_at_more_seeded_random_points_resume_to_the_same_result(tmp_path, reference,
                                                                            fraction):
    _kill_and_resume(tmp_path, reference, fraction)


# -- corrupt each file of a run directory ---------------------------------------------------
def _corrupt(path: Path, how: str, rng: random.Random) -> None:
    if how == "deleted":
        path.unlink()
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "truncated":
        path.write_bytes(path.read_bytes()[: max(1, path.stat().st_size // 2)])
    elif how == "random bytes":
        path.write_bytes(rng.randbytes(max(16, path.stat().st_size)))


FILES = ("checkpoint.pt", "history.jsonl", "result.json", "params.pt", ".hydra/config.yaml",
         ".hydra/overrides.yaml", "tb", "fit.log")
DAMAGE = ("deleted", "empty", "truncated", "random bytes")
CASES = [(name, how) for name in FILES for how in DAMAGE]


def _sample_cases(count: int) -> list[tuple[str, str]]:
    return random.Random(SEED).sample(CASES, count)


def _resume_damaged(tmp_path: Path, reference: tuple[Path, float], name: str, how: str) -> None:
    ref_dir, _ = reference
    run_dir = tmp_path / "run"
    shutil.copytree(ref_dir, run_dir)
    target = run_dir / name
    if target.is_dir():     # tb/: its event file
        target = next(target.iterdir())
    _corrupt(target, how, random.Random(f"{SEED}{name}{how}"))
    before = tree_digest(run_dir)
    resumed = run_fit_app(run_dir, *PROBLEM, "resume=true")
    assert "Traceback" not in resumed.stderr, resumed.stderr[-2000:]
    if resumed.returncode == 2:
        line = _one_error_line(resumed.stderr)
        assert str(run_dir) in line
        assert tree_digest(run_dir) == before, "a refused resume changes nothing"
    else:
        assert resumed.returncode == 0, resumed.stderr[-2000:]
        _same_result(run_dir, ref_dir)
    assert not (run_dir / LOCK_FILE).exists()


@pytest.mark.parametrize("name,how", _sample_cases(4))
def test_a_resume_after_a_file_of_the_run_was_damaged_continues_or_refuses_in_one_line(
        tmp_path, reference, name, how):
    _resume_damaged(tmp_path, reference, name, how)


@pytest.mark.slow
@pytest.mark.parametrize("name,how", [c for c in CASES if c not in _sample_cases(4)])
def test_every_damaged_file_of_a_run_continues_or_is_refused_in_one_line(tmp_path, reference,
                                                                           name, how):
    _resume_damaged(tmp_path, reference, name, how)


# -- concurrent runs ------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("gap", [round(random.Random(SEED + i).uniform(0, 0.1), 3)
                                 for i in range(3)])
def test_two_runs_started_a_seeded_moment_apart_one_runs(tmp_path, reference, gap):
    run_dir = tmp_path / "run"
    first = subprocess.Popen(_command(run_dir), cwd=REPO, env=_env(), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    time.sleep(gap)
    second = subprocess.Popen(_command(run_dir, "problem.seed=7"), cwd=REPO, env=_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    outputs = [(p.returncode, *p.communicate(timeout=600)) for p in (first, second)]
    codes = sorted(p.returncode for p in (first, second))
    assert codes == [0, 2], [(p.returncode, err[-500:]) for p, (_, _, err) in
                             zip((first, second), outputs)]
    loser = first if first.returncode == 2 else second
    _one_error_line(outputs[(first, second).index(loser)][2])
    if loser is second:        # the winner's run, unmixed: the reference's result
        _same_result(run_dir, reference[0])
    result = json.loads((run_dir / "result.json").read_text())
    assert result["config"]["problem"]["seed"] == (7 if loser is first else 0)
    _clean(run_dir)


# -- a full disk ----------------------------------------------------------------------------
def _private_mounts() -> bool:
    """Whether this machine lets an unprivileged process mount a tmpfs in its own mount
    namespace (``unshare -rm``)."""
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs "
                            "/tmp 2>/dev/null"], capture_output=True)
    return probe.returncode == 0


def _full_disk_sizes(count: int) -> list[int]:
    """Seeded sizes (KiB) of the tmpfs the run writes into: small enough that the disk
    fills at different points of the run (the whole run directory is about 110 KiB)."""
    rng = random.Random(SEED)
    return [rng.randrange(24, 150) for _ in range(count)]


def _full_disk(tmp_path: Path, reference: tuple[Path, float], size_kib: int) -> None:
    if not _private_mounts():
        pytest.skip("this machine does not allow a tmpfs in a private mount namespace")
    mount, out = tmp_path / "disk", tmp_path / "out"
    mount.mkdir()
    out.mkdir()
    run_dir = mount / "run"
    q = subprocess.list2cmdline
    script = "\n".join([
        f"mount -t tmpfs -o size={size_kib}k tmpfs {mount}",
        f"{q(_command(run_dir))} > {out}/first.out 2> {out}/first.err; echo $? > {out}/first.rc",
        # what the full disk left: copied out before the tmpfs grows (it vanishes with us)
        f"mkdir {out}/left && cp -a {run_dir}/. {out}/left/ 2>/dev/null",
        f"mount -o remount,size=16m {mount}",
        f"{q(_command(run_dir, 'resume=true'))} > {out}/resume.out 2> {out}/resume.err; "
        f"echo $? > {out}/resume.rc",
        f"cp -a {run_dir} {out}/run",
    ])
    subprocess.run(["unshare", "-rm", "sh", "-c", script], cwd=REPO, env=_env(), check=True,
                   timeout=600)
    first_rc = int((out / "first.rc").read_text())
    first_err = (out / "first.err").read_text()
    assert "Traceback" not in first_err and "Exception in thread" not in first_err, first_err
    if first_rc == 2:
        line = _one_error_line(first_err)
        assert "no space left" in line and f"hydra.run.dir={run_dir} resume=true" in line, line
        assert f" while writing {run_dir}/" in line, line       # the file, not the directory
    else:       # the disk was large enough after all
        assert first_rc == 0, first_err[-2000:]
    if (out / "left").is_dir():
        leftovers = [p for p in (out / "left").rglob("*") if p.is_file() and (
            ".tmp" in p.name or p.stat().st_size == 0)]
        assert not leftovers and not list((out / "left").glob(".*.partial")), leftovers
    assert int((out / "resume.rc").read_text()) == 0, (out / "resume.err").read_text()[-2000:]
    _same_result(out / "run", reference[0])
    _clean(out / "run")


@pytest.mark.parametrize("size_kib", _full_disk_sizes(1))
def test_a_full_disk_stops_the_run_in_one_line_and_the_resume_ends_where_it_would_have(
        tmp_path, reference, size_kib):
    _full_disk(tmp_path, reference, size_kib)


@pytest.mark.slow
@pytest.mark.parametrize("size_kib", _full_disk_sizes(5)[1:])
def test_a_disk_full_at_more_seeded_points(tmp_path, reference, size_kib):
    _full_disk(tmp_path, reference, size_kib)


def _on_a_small_disk(tmp_path: Path, size_kib: int, fill_kib: int = 0,
                     again: str = "") -> tuple[int, str, Path]:
    """The fit (spring1d, 2 iterations) into a run directory on a tmpfs of ``size_kib``
    KiB, ``fill_kib`` of it taken first; then the space freed and the same command again.
    Returns the first run's exit status, its stderr and the folder of what was left
    (``left/``: the run directory after the first run, if any; ``rc2``, ``second.err`` of
    the command again, with ``again`` added)."""
    if not _private_mounts():
        pytest.skip("this machine does not allow a tmpfs in a private mount namespace")
    mount, out = tmp_path / "disk", tmp_path / "out"
    mount.mkdir()
    out.mkdir()
    run_dir = mount / "run"
    q = subprocess.list2cmdline
    command = q([*_command(run_dir)[:3], "problem=spring1d", "problem.n=16", "solver.max_iter=2"])
    script = "\n".join([
        f"mount -t tmpfs -o size={size_kib}k tmpfs {mount}",
        f"dd if=/dev/zero of={mount}/fill bs=1k count={fill_kib} 2>/dev/null" if fill_kib else "true",
        f"{command} > {out}/first.out 2> {out}/first.err; echo $? > {out}/first.rc",
        f"if [ -d {run_dir} ]; then cp -a {run_dir} {out}/left; fi",
        f"rm -f {mount}/fill; mount -o remount,size=16m {mount}",
        f"{command} {again} > {out}/second.out 2> {out}/second.err; echo $? > {out}/rc2",
    ])
    subprocess.run(["unshare", "-rm", "sh", "-c", script], cwd=REPO, env=_env(), check=True,
                   timeout=600)
    return int((out / "first.rc").read_text()), (out / "first.err").read_text(), out


@pytest.mark.parametrize("size_kib,fill_kib,written", [(64, 64, LOCK_FILE), (8, 0, ".hydra/")])
def test_a_disk_full_at_the_start_leaves_no_lock_and_the_next_run_proceeds(
        tmp_path, size_kib, fill_kib, written):
    """No room for the lock (a full disk), or for Hydra's ``.hydra/`` (8 KiB): one line
    naming the file, no Hydra traceback, nothing left (no 0-byte lock that would block the
    next run), and the same command runs once there is space."""
    rc, err, out = _on_a_small_disk(tmp_path, size_kib, fill_kib=fill_kib)
    run_dir = tmp_path / "disk" / "run"
    line = _one_error_line(err)
    assert rc == 2 and "no space left" in line, err
    assert f"while writing {run_dir / written}" in line and "run the same command" in line
    assert not (out / "left").exists(), "the run directory made for the lock is gone"
    assert int((out / "rc2").read_text()) == 0, (out / "second.err").read_text()[-2000:]


@pytest.mark.parametrize("size_kib", [20, 44])
def test_a_disk_full_partway_is_one_line_naming_the_file(tmp_path, size_kib):
    """A disk that fills during the fit (at 20 KiB as TensorBoard writes its event file's
    header, at 44 KiB as it writes the iterations): exactly one ``error:`` line, naming a
    file of the run directory and the resume command, no traceback (it is in fit.log)."""
    rc, err, out = _on_a_small_disk(tmp_path, size_kib, again="resume=true")
    run_dir = tmp_path / "disk" / "run"
    assert rc == 2, err[-2000:]
    line = _one_error_line(err)
    assert "Exception in thread" not in err
    assert f" while writing {run_dir}/" in line and f"hydra.run.dir={run_dir} resume=true" in line
    named = line.split(" while writing ", 1)[1].split(";", 1)[0]
    assert Path(named).parent in (run_dir, run_dir / "tb"), named
    assert "Traceback" in (out / "left" / "fit.log").read_text()
    assert not (out / "left" / LOCK_FILE).exists()
    assert int((out / "rc2").read_text()) == 0, (out / "second.err").read_text()[-2000:]


@pytest.mark.slow       # the arm's 48 frames, one iteration, twice (about a minute)
def test_a_file_size_limit_at_the_usd_outputs_stops_in_one_line_and_the_resume_writes_them(
        tmp_path):
    """Issue 50: EFBIG while writing ``usd/frames.usda`` (the largest file: 3.5 MB for the
    arm's 48 frames) ended "done", exit 0, ``usd/`` missing, and a resume did not write it.
    Now the guard of the outputs lets a failed write through: one line saying what to do, exit
    2, the run not final; the resume (no limit) writes every USD file."""
    import resource

    pytest.importorskip("pxr")
    arm = tmp_path / "my_arm"
    subprocess.run([sys.executable, "scripts/write_arm.py", str(arm)], cwd=REPO, env=_env(),
                   check=True, capture_output=True, timeout=300)
    run_dir = tmp_path / "run"
    command = [sys.executable, "experiments/fit.py", f"hydra.run.dir={run_dir}",
               "problem=animation", f"problem.path={arm}", "solver.max_iter=1",
               "problem.tet_count=1500", f"problem.cache_dir={tmp_path / 'cache'}", "threads=1"]
    limit = 2500 * 1024          # above body.vtu (2.0 MB) and frames.npz (1.7 MB)

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))

    first = subprocess.run(command, cwd=REPO, env=_env(), capture_output=True, text=True,
                           timeout=900, preexec_fn=limited)
    assert first.returncode == 2, first.stderr[-3000:]
    line = _one_error_line(first.stderr)
    assert line.startswith(f"error: a file of {run_dir} reached the file-size limit; raise the "
                           "file-size limit (ulimit -f)"), line
    assert f"hydra.run.dir={run_dir} resume=true" in line
    assert not (run_dir / "usd" / "frames.usda").exists()
    again = subprocess.run(command + ["resume=true"], cwd=REPO, env=_env(), capture_output=True,
                           text=True, timeout=900)
    assert again.returncode == 0, again.stderr[-3000:]
    assert {p.name for p in (run_dir / "usd").iterdir()} >= {"frames.usda", "body.usda",
                                                              "material.usda"}
    assert (run_dir / "usd" / "frames.usda").stat().st_size > limit
