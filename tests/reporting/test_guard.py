"""The guard that keeps a drawing failure from failing a fit."""
from __future__ import annotations

import logging

import pytest

from torchfit.reporting.guard import PlotGuard


def test_plot_guard_warns_once_and_returns_none(caplog):
    guard = PlotGuard()

    def fail(what):
        raise OSError(f"disk full ({what})")

    with caplog.at_level(logging.WARNING, logger="torchfit.reporting.guard"):
        assert guard.run("a.png", fail, "a") is None
        assert guard.run("b.png", fail, "b") is None
        assert guard.run("c.png", lambda: 7) == 7
    assert guard.failures == ["a.png", "b.png"]
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1
    assert "could not draw a.png" in messages[0] and "disk full (a)" in messages[0]
    with pytest.raises(KeyboardInterrupt):         # only Exception is swallowed
        guard.run("d.png", lambda: (_ for _ in ()).throw(KeyboardInterrupt()))


def test_a_write_the_user_can_act_on_is_not_a_drawing_failure():
    """A full disk, a file-size limit, or USD's error text of one: raised, so the run stops
    in one line and its resume writes the output (issue 50: ``usd/`` went missing, exit 0)."""
    import errno

    guard = PlotGuard()

    class ErrorException(Exception):          # the shape of pxr.Tf.ErrorException
        pass

    for error in (OSError(errno.EFBIG, "File too large", "usd/frames.usda"),
                  OSError(errno.ENOSPC, "No space left on device"),
                  ErrorException("Error in 'Write': 'Error occurred writing file: File too "
                                 "large'")):
        with pytest.raises(type(error)):
            guard.run("USD frames", lambda: (_ for _ in ()).throw(error))
    assert guard.failures == []
