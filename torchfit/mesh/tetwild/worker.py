"""pytetwild in a child process: ``python worker.py <folder>``.

:func:`torchfit.mesh.tetwild.tetrahedralize.tetrahedralize` runs fTetWild here, not in its own
process: pytetwild holds the GIL for the whole call (no thread of the parent could report
progress) and crashes on some surfaces (a segmentation fault would end the whole run). The
parent writes ``surface.npz`` (``vertices`` float64, ``faces`` int32) and ``options.json``
(pytetwild's keyword arguments) into ``<folder>``, runs this script with ``<folder>`` as its
working directory (fTetWild leaves ``__tracked_surface.stl`` there) and reads ``mesh.npz``
(``points``, ``cells``) back. Run as a script: it imports numpy and pytetwild only.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(folder: Path) -> None:
    import pytetwild

    with np.load(folder / "surface.npz", allow_pickle=False) as surface:
        vertices, faces = surface["vertices"], surface["faces"]
    options = json.loads((folder / "options.json").read_text())
    points, cells = pytetwild.tetrahedralize(vertices, faces, loglevel=6, quiet=True,
                                             vtk_ordering=True, **options)
    np.savez(folder / "mesh.npz", points=np.asarray(points), cells=np.asarray(cells))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
