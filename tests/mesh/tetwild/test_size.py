"""A target tetrahedron count (torchfit.mesh.tetwild.size): the edge length and envelope chosen
for it, a build off target built again, the target in the cache key; with real pytetwild,
half the target gives about half the tetrahedra."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from torchfit.mesh import TetOptions, tetrahedralize
from torchfit.mesh.tetwild import size as tet_size
from torchfit.mesh.tetwild.size import body_volume, build_for_count, edge_for_count


def test_the_edge_fills_the_volume_with_the_target_count():
    box = trimesh.creation.box((1.0, 2.0, 3.0))
    assert body_volume(box.vertices, box.faces) == pytest.approx(6.0)
    open_faces = box.faces[box.triangles_center[:, 2] < 1.49]   # no top: the hull's volume
    assert body_volume(box.vertices, open_faces) == pytest.approx(6.0)
    diagonal = math.sqrt(14.0)
    edge = edge_for_count(6.0, diagonal, 1000) * diagonal
    regular = edge ** 3 / (6 * math.sqrt(2))
    assert tet_size.TETS_PER_REGULAR * 6.0 / regular == pytest.approx(1000)
    assert edge_for_count(6.0, diagonal, 8000) == pytest.approx(
        edge_for_count(6.0, diagonal, 1000) / 2)


def test_a_build_off_target_is_built_again_and_the_closest_kept():
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    made = []

    def fake(options):              # a mesher making 3x the tets the volume model expects
        expected = tet_size.TETS_PER_REGULAR / (
            (options.edge_length_fac * math.sqrt(3)) ** 3 / (6 * math.sqrt(2)))
        n = int(round(3 * expected))
        made.append(options)
        return np.zeros((4, 3)), np.zeros((n, 4), dtype=np.int64), 1.0

    points, cells, seconds, options = build_for_count(fake, box.vertices, box.faces,
                                                      TetOptions(count=1000))
    assert len(made) == 3 and seconds == 3.0 and options is made[2]
    # the fake's count goes as edge ** -3: the second build (exponent assumed) misses,
    # the third (the exponent measured by the first two) is on target
    assert made[1].edge_length_fac == pytest.approx(
        made[0].edge_length_fac * 3 ** (1 / tet_size.COUNT_EXPONENT), rel=1e-3)
    assert options.epsilon == pytest.approx(tet_size.ENVELOPE_PER_EDGE * options.edge_length_fac)
    assert abs(len(cells) / 1000 - 1) <= tet_size.COUNT_TOLERANCE


def test_the_count_is_part_of_the_key_only_when_given():
    assert "count" not in TetOptions().as_dict()
    assert TetOptions(count=500).as_dict()["count"] == 500
    with pytest.raises(ValueError, match="TetOptions.count must be a positive integer"):
        TetOptions(count=0)


@pytest.mark.slow
def test_half_the_target_gives_about_half_the_tetrahedra(tmp_path, monkeypatch):
    """The test capsule (800 faces), real pytetwild, twice per target at most: asked for
    3,000 and 1,500 (docs/notes/tet_size.md has the measured table)."""
    monkeypatch.chdir(tmp_path)
    surface = trimesh.creation.capsule(height=0.5, radius=0.05, count=[20, 20])
    counts = {}
    for target in (3000, 1500):
        mesh = tetrahedralize(surface.vertices, surface.faces, TetOptions(count=target),
                              cache_dir=tmp_path / "cache")
        counts[target] = len(mesh.cells)
        assert abs(math.log(counts[target] / target)) < math.log(1.5), counts
    assert 0.35 < counts[1500] / counts[3000] < 0.7, counts
    again = tetrahedralize(surface.vertices, surface.faces, TetOptions(count=1500),
                           cache_dir=tmp_path / "cache")
    assert again.from_cache and len(again.cells) == counts[1500]
