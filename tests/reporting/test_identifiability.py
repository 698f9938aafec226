"""The files of the identifiability report (torchfit.reporting.identifiability): the JSON as
handed over, the VTU cell fields on a mesh, the picture; a problem without a mesh gets no VTU."""
from __future__ import annotations

import json
from types import SimpleNamespace

import meshio
import numpy as np
import torch

from torchfit.reporting.guard import PlotGuard
from torchfit.reporting.identifiability import write_identifiability
from torchfit.run.identifiability import from_jacobian


def report():
    J = torch.tensor([[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    return from_jacobian(J, torch.zeros(3, dtype=torch.float64),
                         torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)).as_json()


def test_json_vtu_and_picture_of_a_tetrahedral_body(tmp_path):
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=float)
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    guard = PlotGuard()
    files = write_identifiability(tmp_path, SimpleNamespace(points=points, cells=cells),
                                  np.array([0, 1]), report(),
                                  {"sensitivity": np.array([1.0, 0.25]),
                                   "determined": np.array([1.0, 0.5])}, guard)
    assert [f.name for f in files] == ["identifiability.json", "identifiability.vtu",
                                       "identifiability.png"]
    assert not guard.failures
    saved = json.loads((tmp_path / "identifiability.json").read_text())
    assert saved["n_determined"] == 2 and saved["effective_rank"] == 2
    assert saved["parameters"]["determined"] == [True, True, False]
    mesh = meshio.read(tmp_path / "identifiability.vtu")
    assert mesh.cells[0].type == "tetra" and mesh.cells[0].data.tolist() == cells.tolist()
    assert mesh.cell_data["sensitivity"][0].tolist() == [1.0, 0.25]
    assert mesh.cell_data["determined"][0].tolist() == [1.0, 0.5]
    assert mesh.cell_data["region"][0].tolist() == [0, 1]
    assert (tmp_path / "identifiability.png").stat().st_size > 10_000


def test_no_vtu_without_a_mesh(tmp_path):
    files = write_identifiability(tmp_path, None, None, report(),
                                  {"sensitivity": np.ones(3), "determined": np.ones(3)},
                                  PlotGuard())
    assert [f.name for f in files] == ["identifiability.json", "identifiability.png"]
