"""The 5x7 font and the IPAM raster (torchfit.problems.font), and the unit-square normalisation
they are placed with."""
from __future__ import annotations

import numpy as np
import pytest

from torchfit.mesh import normalized_points
from torchfit.problems.font import ipam_mask
from torchfit.problems.font import word_bitmap


def test_ipam_bitmap_glyphs():
    bitmap = word_bitmap("IPAM")
    assert bitmap.shape == (7, 23)
    assert not bitmap[:, 5].any() and not bitmap[:, 11].any() and not bitmap[:, 17].any()
    rows = ["".join("#" if b else "." for b in row[12:17]) for row in bitmap]
    assert rows == [".###.", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"]   # A
    with pytest.raises(ValueError, match="no glyph"):
        word_bitmap("IPAX")


def test_ipam_mask_reproduces_the_independent_poisson2d_vectors(vectors_dir):
    data = np.load(vectors_dir / "poisson2d_N16_ipam.npz")
    centres = data["cell_centres"] / float(data["s"])
    k = np.where(ipam_mask(centres), 5.0, 1.0)
    np.testing.assert_array_equal(k, data["k"])


def test_ipam_mask_placement_rule():
    # top-left pixel of I is ink, the pixel below it is not; the box is half-open
    x0, x1, y0, y1 = 0.10, 0.90, 0.35, 0.65
    px, py = (x1 - x0) / 23, (y1 - y0) / 7
    top_left = [x0 + 0.5 * px, y1 - 0.5 * py]
    below = [x0 + 0.5 * px, y1 - 1.5 * py]
    mask = ipam_mask(np.array([top_left, below, [x0, y1 - 0.5 * py], [x1, 0.5], [0.5, y1]]))
    assert mask.tolist() == [True, False, True, False, False]
    assert np.allclose(normalized_points(np.array([[2.0, 0.5]]), ((0.0, 2.0), (0.0, 0.5))), [[1.0, 1.0]])
