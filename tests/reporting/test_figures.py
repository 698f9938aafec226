"""Run-directory PNGs (field.png, error_curves.png), and a failing drawing that leaves the
others."""
from __future__ import annotations

import logging

import numpy as np
from PIL import Image

from torchfit.problems import build_problem
from torchfit.reporting.figures import error_curve_keys, field_is_chain, write_run_pngs
from torchfit.reporting.results import history_rows
from torchfit.run.evaluator import Evaluator
from torchfit.solvers import GaussNewtonConfig, gauss_newton


def fitted(problem, max_iter: int = 4):
    return gauss_newton(problem.residual(), problem.theta0, GaussNewtonConfig(max_iter=max_iter),
                        [Evaluator(problem)])


def check_png(path, min_width: int, min_height: int) -> tuple[int, int]:
    """A readable PNG of plausible size that is not one flat colour."""
    assert path.is_file(), path
    with Image.open(path) as image:
        image.verify()
    with Image.open(path) as image:
        assert image.format == "PNG"
        width, height = image.size
        pixels = np.asarray(image.convert("RGB"))
    assert width >= min_width and height >= min_height, (path, image.size)
    assert width <= 4000 and height <= 4000
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 20      # a drawing, not a blank
    return width, height


def test_poisson2d_field_and_error_curves(tmp_path):
    problem = build_problem("poisson2d", {"N": 7})
    result = fitted(problem)
    written = write_run_pngs(tmp_path, problem, problem.field(result.theta),
                             history_rows(result.history))
    assert [p.name for p in written] == ["field.png", "error_curves.png"]
    width, height = check_png(tmp_path / "field.png", 800, 250)
    assert width > 2 * height            # three panels side by side
    check_png(tmp_path / "error_curves.png", 500, 400)


def test_spring1d_chain_field_and_error_curves(tmp_path):
    problem = build_problem("spring1d", {"n": 16, "noise": 1e-4})
    result = fitted(problem)
    written = write_run_pngs(tmp_path, problem, problem.field(result.theta),
                             history_rows(result.history), chain=field_is_chain(problem))
    assert [p.name for p in written] == ["field.png", "error_curves.png"]
    check_png(tmp_path / "field.png", 500, 250)
    check_png(tmp_path / "error_curves.png", 500, 300)


def test_error_curve_keys():
    scale_free = [{"iteration": 0, "misfit": 1.0, "k_err_rel": 0.3, "k_err_rel_aligned": 0.2,
                   "tv": 0.0}, {"iteration": 1, "misfit": 0.1, "tv": 2.0}]
    assert error_curve_keys(scale_free) == ["misfit", "k_err_rel_aligned", "tv"]
    assert error_curve_keys([{"iteration": 0, "misfit": 1.0, "k_err_rel": 0.3}]) == \
        ["misfit", "k_err_rel"]
    assert error_curve_keys([{"iteration": 0, "misfit": 1.0}]) == ["misfit"]


def test_a_failing_field_png_leaves_the_other_png(tmp_path, caplog, monkeypatch):
    problem = build_problem("poisson2d", {"N": 5})
    result = fitted(problem, max_iter=2)
    monkeypatch.setattr(problem, "field_image", lambda field: 1 / 0)
    with caplog.at_level(logging.WARNING, logger="torchfit.reporting.guard"):
        written = write_run_pngs(tmp_path, problem, problem.field(result.theta),
                                 history_rows(result.history))
    assert [p.name for p in written] == ["error_curves.png"]
    assert not (tmp_path / "field.png").exists()
    assert len(caplog.records) == 1 and "field.png" in caplog.records[0].getMessage()
