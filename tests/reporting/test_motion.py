"""Outputs of a dynamic fit: the output times a strip shows and its two figures (the run
itself: tests/problems/test_dynamic.py)."""
from __future__ import annotations

import numpy as np

from torchfit.reporting.figures import save_png
from torchfit.reporting.motion import frames_strip_figure, strip_frames, time_errors_figure


def test_strip_frames_spread_over_the_output_times():
    assert strip_frames(60) == [0, 12, 24, 35, 47, 59]
    assert strip_frames(3) == [0, 1, 2]
    assert strip_frames(1) == [0]


def test_figures_of_a_chain_and_of_a_sheet(tmp_path):
    times = np.array([0.1, 0.2, 0.3])
    history = {0: np.array([1e-1, 2e-1, 3e-1]), 5: np.array([1e-4, 0.0, 3e-4])}
    save_png(time_errors_figure(times, history, "errors"), tmp_path / "time.png")
    chain = np.random.default_rng(0).normal(size=(3, 5, 1))
    save_png(frames_strip_figure(times, chain, chain + 0.01), tmp_path / "chain.png")
    points = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    sheet = np.stack([points + 0.1 * t for t in times])
    cells = np.array([[0, 1, 2], [1, 3, 2]])
    figure = frames_strip_figure(times, sheet, sheet, cells, np.array([1.0, 2.0]), "E", "sheet")
    save_png(figure, tmp_path / "sheet.png")
    assert all((tmp_path / name).stat().st_size > 5_000
               for name in ("time.png", "chain.png", "sheet.png"))
