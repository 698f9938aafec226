"""What a run reports of a body (torchfit.problems.body.report), on a tetrahedral box."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchfit.mesh import box_tetrahedra
from torchfit.problems.body.report import (BODY_METRICS, body_metrics, frame_report,
                                           frame_volumes, inverted_counts, min_volume_ratios,
                                           region_summary, surface_distances, volume_change)


@pytest.fixture()
def box():
    mesh = box_tetrahedra(2, 1, 1)                    # 12 tetrahedra of volume 1/12
    squashed = mesh.points * [1.0, 1.0, 0.5]
    flipped = mesh.points.copy()
    flipped[mesh.points[:, 0] > 0.5, 0] = 0.9 - flipped[mesh.points[:, 0] > 0.5, 0] + 0.5
    return mesh, np.stack([mesh.points, squashed, 2.0 * mesh.points, flipped])


def test_volumes_change_and_inversions_per_frame(box):
    mesh, frames = box
    volumes = frame_volumes(frames, mesh.cells)
    assert volumes.shape == (4, 12)
    assert np.allclose(volumes[0], 1.0 / 12) and np.allclose(volumes[2], 8.0 / 12)
    change = volume_change(frames, mesh.points, mesh.cells)
    assert np.allclose(change[:3], [0.0, -0.5, 7.0])
    assert np.allclose(volume_change(frames, mesh.points, mesh.cells[:6])[:3], [0.0, -0.5, 7.0])
    inverted = inverted_counts(frames, mesh.cells)
    assert inverted[:3].tolist() == [0, 0, 0] and inverted[3] == 6     # the right cube folds
    ratios = min_volume_ratios(frames, mesh.points, mesh.cells)
    assert np.allclose(ratios[:3], [1.0, 0.5, 8.0]) and ratios[3] < 0


def test_metrics_and_per_frame_curves_in_the_metric_order():
    errors = torch.tensor([[0.0, 2.0], [1.0, 3.0]])
    change, inverted = np.array([0.1, -0.2]), np.array([0, 4])
    metrics = body_metrics(errors, 3.0, change, inverted, reference_frame=1)
    assert tuple(metrics) == BODY_METRICS
    assert metrics == {"surface_err_mean": 1.5, "surface_err_max": 3.0,
                       "surface_err_reduction": 2.0, "joint_volume_change": -0.2,
                       "inverted_tets": 4.0}
    assert body_metrics(torch.zeros(2, 2), 3.0, change, inverted, 0)["surface_err_reduction"] \
        == math.inf
    curves = frame_report(errors, change, inverted)
    assert curves["surface_err_mean"].tolist() == [1.0, 2.0]
    assert curves["surface_err_max"].tolist() == [2.0, 3.0]
    assert curves["joint_volume_change"] is change and curves["inverted_tets"] is inverted
    assert surface_distances(torch.zeros(2, 1, 3), torch.tensor([[[3.0, 4.0, 0.0]]]) \
                             .expand(2, 1, 3)).tolist() == [[5.0], [5.0]]


def test_region_summary():
    values, volumes = np.array([1.0, 2.0, 4.0, 8.0]), np.array([1.0, 1.0, 2.0, 4.0])
    summary = region_summary(values, volumes, np.array([0, 0, 2, 2]), ["bone", "muscle", "fat"])
    assert list(summary) == ["bone", "fat"]                    # no cell labelled muscle
    assert summary["bone"] == {"tets": 2, "volume": 2.0, "mean": 1.5, "min": 1.0, "max": 2.0,
                               "volume_mean": 1.5}
    assert summary["fat"]["volume_mean"] == pytest.approx((8.0 + 32.0) / 6.0)
    whole = region_summary(values, volumes, None, [])
    assert list(whole) == ["body"] and whole["body"]["tets"] == 4
