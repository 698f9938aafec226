"""``simulate``'s picture (torchfit.reporting.simulation.comparison_picture): through the
body's camera (the file's up axis up), with a colour bar in millimetres."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
import trimesh


def test_the_simulation_picture_uses_the_bodys_camera_and_a_colour_bar(tmp_path, monkeypatch):
    import torchfit.reporting.simulation as simulation

    mesh = trimesh.creation.icosphere(1)
    vertices = torch.as_tensor(np.asarray(mesh.vertices))
    frames = torch.stack([vertices, vertices * 1.01])
    view = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])      # Y up
    observation = SimpleNamespace(
        surface=lambda x: x, clean_surface=lambda x_true: frames,
        surface_error_field=lambda x, x_true: torch.linalg.norm(x - frames, dim=-1))
    problem = SimpleNamespace(animation=SimpleNamespace(faces=np.asarray(mesh.faces)),
                              view_axes=view, observation=observation, x_true=None)
    drawn = {}
    original = simulation.surface_figure

    def keep(*args, **kwargs):
        drawn["view"] = kwargs.get("view")
        drawn["fig"] = original(*args, **kwargs)
        return drawn["fig"]

    monkeypatch.setattr(simulation, "surface_figure", keep)
    path = simulation.comparison_picture(tmp_path, problem, frames * 1.002, 1, ["a", "b"])
    assert path.is_file() and drawn["view"] is view
    bars = [ax for ax in drawn["fig"].axes if ax.name != "3d"]
    assert len(bars) == 1 and bars[0].get_ylabel() == "surface error (mm)"
    top = 1e3 * float(torch.linalg.norm(frames[1] * 0.002, dim=-1).max())
    assert abs(bars[0].get_ylim()[1] - top) < 1e-9
