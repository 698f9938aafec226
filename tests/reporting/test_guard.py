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
