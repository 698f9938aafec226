"""One run per run directory (torchfit/run/lock.py): an exclusive lock file, re-entrant in a
process, refused to another, a stale one (its process gone) taken over, released at exit."""
from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys

import pytest

from helpers.runs import QUIET, REPO
from torchfit.problems import build_problem
from torchfit.run import fit
from torchfit.run.lock import LOCK_FILE, RunLockedError, acquire, hold, release

HOLD = """
import sys, time
from torchfit.run.lock import acquire
acquire(sys.argv[1])
print("held", flush=True)
time.sleep(60)
"""


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    return int(proc.stdout)


def test_the_lock_holds_pid_and_host_and_is_reentrant(tmp_path):
    run_dir = tmp_path / "new" / "run"
    with hold(run_dir):
        lock = run_dir / LOCK_FILE
        assert lock.read_text().split() == [str(os.getpid()), socket.gethostname()]
        with hold(run_dir):                 # the app holds it, then fit() again
            pass
        assert lock.is_file(), "an inner release keeps the outer hold"
    assert not lock.exists()
    assert not run_dir.exists(), "a directory created for the lock alone is removed again"
    with hold(tmp_path):
        pass
    assert tmp_path.is_dir() and list(tmp_path.iterdir()) == []


def test_another_process_is_refused_at_once_and_the_lock_is_released_at_its_exit(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path)], cwd=REPO, env=env,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RunLockedError) as refused:
            acquire(tmp_path)
        message = str(refused.value)
        assert str(tmp_path) in message and f"process {holder.pid} on " \
            f"{socket.gethostname()}" in message and "\n" not in message
        with pytest.raises(RunLockedError):        # fit() too, before writing anything
            fit(build_problem("spring1d", {"n": 8}), "gauss_newton", run_dir=tmp_path,
                options=QUIET)
        assert [p.name for p in tmp_path.iterdir()] == [LOCK_FILE]
    finally:
        holder.kill()           # SIGKILL: no clean-up, the lock stays (stale)
        holder.wait()
    assert (tmp_path / LOCK_FILE).is_file()
    acquire(tmp_path)           # its process is gone: taken over
    release(tmp_path)
    assert not (tmp_path / LOCK_FILE).exists()


def test_a_stale_lock_is_taken_over_with_a_log_line(tmp_path, caplog):
    pid = _dead_pid()
    (tmp_path / LOCK_FILE).write_text(f"{pid} {socket.gethostname()}\n")
    problem = build_problem("spring1d", {"n": 8})
    with caplog.at_level(logging.WARNING, logger="torchfit.run"):
        fit(problem, {"name": "gauss_newton", "max_iter": 2}, run_dir=tmp_path, options=QUIET)
    assert any(f"lock of process {pid}" in r.getMessage() and "no longer runs" in r.getMessage()
               for r in caplog.records)
    assert not (tmp_path / LOCK_FILE).exists() and (tmp_path / "result.json").is_file()
    assert not list(tmp_path.glob(f"{LOCK_FILE}*")), "nothing of the takeover left"


def test_a_lock_of_another_host_is_refused_and_named(tmp_path):
    (tmp_path / LOCK_FILE).write_text("12345 some-other-node\n")
    with pytest.raises(RunLockedError, match="process 12345 on some-other-node") as refused:
        acquire(tmp_path)
    assert f"delete {tmp_path / LOCK_FILE}" in str(refused.value)
    assert (tmp_path / LOCK_FILE).read_text() == "12345 some-other-node\n"


def test_the_lock_is_released_when_the_run_fails(tmp_path):
    def boom(record):
        raise KeyboardInterrupt     # Ctrl-C (SIGTERM in the app) inside the run

    with pytest.raises(KeyboardInterrupt):
        fit(build_problem("spring1d", {"n": 8}), "gauss_newton", run_dir=tmp_path,
            callbacks=[boom], options=QUIET)
    assert not (tmp_path / LOCK_FILE).exists() and (tmp_path / "checkpoint.pt").is_file()


# -- a full disk (issue 38) -----------------------------------------------------------------
def test_a_lock_that_cannot_be_written_is_not_left_and_names_the_lock_file(tmp_path,
                                                                          monkeypatch):
    """ENOSPC as the lock's content is written (the file exists, its bytes do not fit):
    no lock file and no directory left, the OSError names the lock, the next run takes it."""
    import errno
    import io

    run_dir = tmp_path / "new" / "run"

    class Full(io.StringIO):
        def close(self):
            raise OSError(errno.ENOSPC, "No space left on device")

    real_fdopen = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda fd, *a, **k: (os.close(fd), Full())[1])
    with pytest.raises(OSError) as full:
        acquire(run_dir)
    monkeypatch.setattr(os, "fdopen", real_fdopen)
    assert full.value.errno == errno.ENOSPC and full.value.filename == str(run_dir / LOCK_FILE)
    assert not (tmp_path / "new").exists(), "the directories made for the lock are gone"
    acquire(run_dir)
    assert (run_dir / LOCK_FILE).read_text() == f"{os.getpid()} {socket.gethostname()}\n"
    release(run_dir)


@pytest.mark.parametrize("content", [b"", b"1234", b"\x00\x00\x00\x00", b"not a lock\n"])
def test_an_empty_or_torn_lock_is_stale_not_held(tmp_path, caplog, content):
    """What a full disk left under an earlier version (a 0-byte lock) or a torn write:
    taken over with a log line; the run proceeds."""
    (tmp_path / LOCK_FILE).write_bytes(content)
    with caplog.at_level(logging.WARNING, logger="torchfit.run"):
        acquire(tmp_path)
    try:
        assert (tmp_path / LOCK_FILE).read_text() == f"{os.getpid()} {socket.gethostname()}\n"
        assert any("does not say which run holds it" in r.getMessage() for r in caplog.records)
    finally:
        release(tmp_path)
    assert not list(tmp_path.iterdir())


def test_an_unreadable_lock_is_still_refused(tmp_path, monkeypatch):
    """A lock this process may not read is not known to be stale: refused as before."""
    (tmp_path / LOCK_FILE).write_text("1 h\n")
    real = type(tmp_path).read_bytes

    def denied(self):
        if self.name == LOCK_FILE:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self)

    monkeypatch.setattr(type(tmp_path), "read_bytes", denied)
    monkeypatch.setattr(type(tmp_path), "read_text", lambda self, **k: denied(self).decode())
    with pytest.raises(RunLockedError, match="an unreadable lock"):
        acquire(tmp_path)
