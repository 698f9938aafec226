"""One run per run directory: an exclusive lock file held for the whole run.

:func:`hold` creates ``<run_dir>/.torchfit.lock`` with ``O_CREAT | O_EXCL`` (atomic, also
between hosts on a shared file system) holding ``pid host`` of the run, and removes it when
the run ends (normally, by an exception, Ctrl-C, or SIGTERM where the app turns it into an
exception). A second run into the same directory, started at the same moment or later, is
refused at once with :class:`RunLockedError` (an ``OSError``: bad input, exit 2 in the app)
naming the directory and the pid and host that hold it. A lock left by a process that no
longer runs (SIGKILL, a crash of the interpreter) on this host is stale: the next run takes
it over with a log line. A lock of another host cannot be checked and is refused; the
message says which file to delete when no run uses it. A lock is written whole before it
takes its name (:func:`_create`), so one that is empty or does not say ``pid host`` (left
by a full disk, or an older version) is stale too; a lock that cannot be written (a full
disk) is not left behind, and the ``OSError`` names the lock file.

The lock is re-entrant within a process (the app holds it before Hydra writes ``.hydra/``,
and :func:`~.fitting.fit` holds it again for the run), counted per resolved path. The
directory (and its missing parents) is created for the lock and removed again on release
when the lock was all that was put there.
"""
from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
from pathlib import Path
from typing import Iterator

log = logging.getLogger("torchfit.run")

LOCK_FILE = ".torchfit.lock"

_held: dict[Path, int] = {}
_created: dict[Path, list[Path]] = {}     # the directories made for a lock
_mutex = threading.Lock()


class RunLockedError(OSError):
    """Another run holds the run directory (the message names it and the holder)."""


def _host() -> str:
    return socket.gethostname()


def _read(path: Path) -> tuple[int | None, str]:
    """``(pid, host)`` of a lock file (``None`` and ``'?'`` where unreadable)."""
    try:
        fields = path.read_text(encoding="utf-8").split()
        return int(fields[0]), fields[1]
    except (OSError, ValueError, IndexError, UnicodeDecodeError):
        return None, "?"


def _damaged(path: Path) -> bool:
    """Whether the lock file can be read but does not say ``pid host`` (empty, torn or
    garbage): left by a failure (a full disk) or an older version, never by a run that
    holds it, since :func:`_create` puts a lock in place only once written whole."""
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return True
    except OSError:
        return False        # gone, or not ours to read: not known to be stale
    fields = text.split()
    return not (len(fields) == 2 and fields[0].isdigit() and text.endswith("\n"))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:    # a zombie (exited, not yet reaped by its parent) runs no more
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def _create(path: Path) -> bool:
    """Create the lock file exclusively with our pid and host; ``False`` if it exists.

    The content is written whole to a file of our own first, then hard-linked to the
    lock's name (atomic, and exclusive also on NFS): a lock is never seen empty or torn. A
    write that fails (a full disk: the ``OSError`` names the lock file) leaves nothing."""
    own = path.with_name(f"{LOCK_FILE}.{_host()}.{os.getpid()}.{threading.get_ident()}")
    try:
        fd = os.open(own, os.O_CREAT | os.O_TRUNC | os.O_WRONLY, 0o644)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(f"{os.getpid()} {_host()}\n")
        os.link(own, path)
    except FileExistsError:
        return False
    except OSError as error:
        if error.errno is not None and error.filename != str(path):
            raise OSError(error.errno, error.strerror or str(error), str(path)) from error
        raise
    finally:
        with contextlib.suppress(OSError):
            os.unlink(own)
    return True


def _take_over_stale(path: Path, pid: int | None, host: str) -> bool:
    """Move a stale lock (``pid`` no longer runs on this host) aside; ``True`` when it was
    the stale one that moved (another run may have taken it over first: then ``False``)."""
    aside = path.with_name(f"{LOCK_FILE}.stale.{os.getpid()}")
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return True         # taken over and released by another run: try to create again
    if _read(aside) == (pid, host) and (pid is not None or _damaged(aside)):
        os.unlink(aside)
        if pid is None:
            log.warning("run directory %s: taking over a lock that does not say which run "
                        "holds it (empty or damaged: left by a full disk?)", path.parent)
        else:
            log.warning("run directory %s: taking over the lock of process %s on %s, which "
                        "no longer runs", path.parent, pid, host)
        return True
    try:            # a live run's fresh lock: put it back
        os.link(aside, path)
    except FileExistsError:
        pass
    os.unlink(aside)
    return False


def acquire(run_dir: str | Path) -> Path:
    """Hold ``run_dir`` for this process (re-entrant); raises :class:`RunLockedError`."""
    run_dir = Path(run_dir).resolve()
    with _mutex:
        if run_dir in _held:
            _held[run_dir] += 1
            return run_dir
        missing = [run_dir, *run_dir.parents]
        missing = missing[:next(i for i, d in enumerate(missing) if d.exists())]
        created = []
        for directory in reversed(missing):
            try:
                directory.mkdir()
                created.append(directory)
            except FileExistsError:
                pass
        path = run_dir / LOCK_FILE
        for _ in range(5):
            try:
                created_now = _create(path)
            except OSError:         # a full disk: nothing left, the directories made go too
                for directory in reversed(created):
                    with contextlib.suppress(OSError):
                        directory.rmdir()
                raise
            if created_now:
                break
            pid, host = _read(path)
            if pid is None and not path.exists():
                continue
            if pid is None and _damaged(path):      # a full disk's leftover: not held
                _take_over_stale(path, pid, host)
                continue
            if pid is not None and host == _host() and pid != os.getpid() and not _alive(pid):
                _take_over_stale(path, pid, host)
                continue
            holder = f"process {pid} on {host}" if pid is not None else "an unreadable lock"
            raise RunLockedError(f"{run_dir} is in use by another run ({holder}, "
                                 f"{path}); wait for it to end or choose another run directory"
                                 + (f" (if no run uses it, delete {path})"
                                    if pid is None or host != _host() else ""))
        else:
            raise RunLockedError(f"{run_dir} is in use by another run (its lock "
                                 f"{path} keeps changing); choose another run directory")
        _held[run_dir] = 1
        _created[run_dir] = created
        return run_dir


def release(run_dir: str | Path) -> None:
    """Undo one :func:`acquire`; the last one removes the lock (and the directory when it was
    created for the lock and holds nothing else)."""
    run_dir = Path(run_dir).resolve()
    with _mutex:
        if run_dir not in _held:
            return
        _held[run_dir] -= 1
        if _held[run_dir] > 0:
            return
        del _held[run_dir]
        path = run_dir / LOCK_FILE
        if _read(path) == (os.getpid(), _host()):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        for directory in reversed(_created.pop(run_dir, [])):
            with contextlib.suppress(OSError):
                directory.rmdir()       # only when empty


def release_all() -> None:
    """Release every lock this process holds (the app at exit)."""
    for run_dir in list(_held):
        _held[run_dir] = 1
        release(run_dir)


@contextlib.contextmanager
def hold(run_dir: str | Path | None) -> Iterator[None]:
    """Hold ``run_dir`` for the ``with`` block (``None``: nothing to hold)."""
    if run_dir is None:
        yield
        return
    acquire(run_dir)
    try:
        yield
    finally:
        release(run_dir)
