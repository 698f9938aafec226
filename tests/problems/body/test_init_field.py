"""torchfit.problems.body.init_field: a body's fit starts from a material layer; a field past
the modulus bounds is clipped into them (issue 50: a run's own layer was refused)."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from helpers.capsule_animation import write_capsule
from torchfit.problems import build_problem

pytest.importorskip("pxr")


@pytest.fixture(scope="module")
def capsule(tmp_path_factory) -> dict:
    """The capsule's settings with one tet per parameter, its mesh cached once."""
    root = tmp_path_factory.mktemp("init_field")
    return {"path": str(write_capsule(root / "capsule")), "cache_dir": str(root / "cache"),
            "tet_count": 600, "parameters": "tet"}


@pytest.mark.parametrize("low, high, factor", [(0.5, 1e3, "10x"), (2e-3, 2.0, "5x")])
def test_a_layer_past_the_bounds_starts_clipped_into_them_and_says_so(capsule, tmp_path, caplog,
                                                                      low, high, factor):
    """A field on a bound (a rig target's fit: ``[E0/100, 100 E0]``) projects a little past it;
    the start was refused ("parameter 190 is 4.654..., outside [-4.605..., 4.605...]"). Now the
    values outside are clipped, one warning says how many and by how much, and the layer read
    is logged."""
    from torchfit.mesh.formats.usd.writer import write_tet_mesh_usd

    settings = capsule
    base = build_problem("animation", settings)
    points, cells = np.asarray(base.mesh.points), np.asarray(base.mesh.cells)
    values = np.geomspace(low, high, len(cells))               # past the upper, the lower
    layer = write_tet_mesh_usd(tmp_path / "material.usda", points, cells,
                               material={"youngsModulus": values, "poissonsRatio":
                                         np.full(len(cells), 0.45), "density":
                                         np.full(len(cells), 1000.0)},
                               units={"youngsModulus": "relative to problem.E0"})
    with caplog.at_level(logging.INFO, logger="torchfit.problems"):
        problem = build_problem("animation", {**settings, "init_field": str(layer)})
    field = problem.field(problem.theta0).numpy()
    inside = (values >= 0.01) & (values <= 100)
    assert field.min() == pytest.approx(max(0.01, low), rel=1e-6)
    assert field.max() == pytest.approx(min(100, high), rel=1e-6)
    assert np.abs(field[inside] / values[inside] - 1).max() < 1e-6     # float32 in the layer
    lower, upper = problem.theta_bounds()
    assert bool(((problem.theta0 >= lower) & (problem.theta0 <= upper)).all())
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING
                and "init_field" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].startswith(
        f"problem.init_field: {int((~inside).sum())} of {len(cells)} start values lie outside "
        f"the modulus bounds [0.01, 100] (by up to {factor}")
    assert any(r.getMessage().startswith(f"start: problem.init_field={layer}") and
               f"{len(cells)} values per tetrahedron" in r.getMessage() for r in caplog.records)
