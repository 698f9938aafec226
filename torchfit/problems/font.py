"""The 5x7 block font of docs/problems.md and the raster of the word ``IPAM``.

Shared by ``poisson2d`` (pattern ``ipam``) and ``membrane2d``: the word is laid out as
one bitmap (glyphs of 5 columns, one blank column between letters, 7 rows, row 0 at the
top), stretched over a box of the unit square, and a point takes the pixel under it.
"""
from __future__ import annotations

import numpy as np

#: Glyph rows, top (row 0) to bottom, ``#`` = ink (docs/problems.md, poisson2d).
GLYPHS: dict[str, tuple[str, ...]] = {
    "I": ("#####", "..#..", "..#..", "..#..", "..#..", "..#..", "#####"),
    "P": ("####.", "#...#", "#...#", "####.", "#....", "#....", "#...."),
    "A": (".###.", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"),
    "M": ("#...#", "##.##", "#.#.#", "#.#.#", "#...#", "#...#", "#...#"),
}

#: The box of the unit square the word is stretched over: ``[x0, x1) x [y0, y1)``.
IPAM_BOX = ((0.10, 0.90), (0.35, 0.65))


def word_bitmap(word: str = "IPAM", spacing: int = 1) -> np.ndarray:
    """Boolean bitmap ``(7, 5 n + spacing (n - 1))`` of ``word``, row 0 at the top."""
    if not word:
        raise ValueError("the word is empty")
    missing = sorted({c for c in word if c not in GLYPHS})
    if missing:
        raise ValueError(f"no glyph for {missing}; the font has {sorted(GLYPHS)}")
    blank = np.zeros((7, spacing), dtype=bool)
    columns: list[np.ndarray] = []
    for i, letter in enumerate(word):
        if i:
            columns.append(blank)
        columns.append(np.array([[c == "#" for c in row] for row in GLYPHS[letter]]))
    return np.concatenate(columns, axis=1)


def bitmap_mask(points: np.ndarray, bitmap: np.ndarray,
                box: tuple[tuple[float, float], tuple[float, float]]) -> np.ndarray:
    """Whether each point lies on an ink pixel of ``bitmap`` stretched over ``box``.

    Args:
        points: ``(n, 2)`` points of the unit square (``(x, y)``, y up).
        bitmap: ``(rows, cols)`` booleans, row 0 at the top.
        box: ``((x0, x1), (y0, y1))``; half-open ``[x0, x1) x [y0, y1)``.
    Returns:
        ``(n,)`` booleans; points outside the box are ``False``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    (x0, x1), (y0, y1) = box
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"the box must have positive extent, got {box}")
    rows, cols = bitmap.shape
    inside = (p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1)
    col = np.floor((p[:, 0] - x0) / (x1 - x0) * cols).astype(np.int64)
    row_from_bottom = np.floor((p[:, 1] - y0) / (y1 - y0) * rows).astype(np.int64)
    col = np.clip(col, 0, cols - 1)
    row = np.clip(rows - 1 - row_from_bottom, 0, rows - 1)
    return inside & bitmap[row, col]


def ipam_mask(points_in_unit_box: np.ndarray,
              box: tuple[tuple[float, float], tuple[float, float]] = IPAM_BOX) -> np.ndarray:
    """``True`` where a point of the unit square lies on the ink of the word ``IPAM``.

    The rule of docs/problems.md (poisson2d ``ipam``, reused by membrane2d): the 7 x 23 bitmap
    of ``IPAM`` (5x7 glyphs, one blank column between letters, row 0 at the top) is
    stretched over ``box`` (default ``[0.10, 0.90) x [0.35, 0.65)``) and a point takes
    the pixel under it. Pass cell centres (poisson2d) or triangle centroids (membrane2d),
    normalised to the unit square.
    """
    return bitmap_mask(points_in_unit_box, word_bitmap("IPAM"), box)
