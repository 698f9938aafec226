"""Whether the peers of a distributed fit still run: a lost rank told from other failures.

A rank is known by its process, ``(host, pid, start time)`` (:func:`identity`), gathered by
rank 0 at the start (:attr:`.session.DistributedSession.peers`). A worker that dies ends
the job, and rank 0 says which one (:func:`lost_rank`): a collective whose peer broke the
connection or never answered (:func:`communication_failure`), or torchrun's SIGTERM once a
worker process of this host is gone. Only a process of this host can be looked at (in
``/proc``, or by its pid where there is no ``/proc``); one elsewhere counts as running.
"""
from __future__ import annotations

import os
import re
import socket
import time
from pathlib import Path
from typing import Any, Sequence

#: what a collective raises when a peer's connection broke or it never answered (gloo)
LOST = re.compile(r"connection (reset|closed|refused)|closed by peer|broken pipe|timed out|"
                  r"timeout|socket closed|end of file|ECONNRESET|EPIPE", re.IGNORECASE)


def identity() -> tuple[str, int, str]:
    """This process: ``(host, pid, start time)`` (the start time in clock ticks after boot,
    from ``/proc``; ``''`` where there is none), so that a reused pid is not taken for it."""
    return socket.gethostname(), os.getpid(), start_time(os.getpid()) or ""


def start_time(pid: int) -> str | None:
    """The start time of process ``pid`` (``/proc/<pid>/stat`` field 22), ``None`` if it is
    gone or a zombie (killed, not yet reaped by torchrun)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()      # after the command name
    return None if fields[0] in ("Z", "X") else fields[19]


def gone(peer: tuple[str, int, str]) -> bool:
    """Whether a rank's process (:func:`identity`) is known to be gone: only a process of
    this host can be looked at; one elsewhere counts as running."""
    host, pid, started = peer
    if host != socket.gethostname():
        return False
    if not Path("/proc/self/stat").exists():       # no /proc: the pid alone
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except OSError:
            pass
        return False
    now = start_time(pid)
    return now is None or bool(started) and now != started


def communication_failure(error: BaseException | None) -> bool:
    """Whether ``error`` (or what it was raised from) is a collective that lost its peer: a
    connection reset or closed, a broken pipe, a timeout (gloo raises ``RuntimeError`` or
    ``torch.distributed.DistError`` with these words)."""
    while error is not None:
        if isinstance(error, RuntimeError) and LOST.search(str(error)):
            return True
        error = error.__cause__ or error.__context__
    return False


def lost_rank(peers: Sequence[Any], size: int, error: BaseException | None,
              wait: float = 1.0) -> str | None:
    """Rank 0 of ``size`` ranks whose processes are ``peers`` (rank order; none before they
    were gathered): ``"rank k of W"`` (or ``"a rank of W"`` where it cannot tell which) when
    the run ended because a worker stopped answering, else ``None``.

    ``error`` is what the fit raised: a :func:`communication_failure` is a lost rank (the
    rank whose process of this host is gone, waiting up to ``wait`` s for the kernel to
    mark it; with 2 ranks it is rank 1). ``None`` stands for torchrun's SIGTERM: it is a
    lost rank only where a worker's process of this host is already gone (torchrun stops
    rank 0 once another rank died; a job cancelled as a whole signals every rank, and the
    workers outlive rank 0: a serving worker notes SIGTERM and goes on until rank 0 stops
    it or is gone)."""
    workers = list(enumerate(peers))[1:]
    lost = error is not None and communication_failure(error)
    if error is not None and not lost:
        return None
    deadline = time.monotonic() + (wait if lost else 0.0)
    while True:
        dead = [r for r, peer in workers if peer is not None and gone(peer)]
        if dead:
            return f"rank {dead[0]} of {size}"
        if time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    if not lost:
        return None
    return f"rank 1 of {size}" if size == 2 else f"a rank of {size}"
