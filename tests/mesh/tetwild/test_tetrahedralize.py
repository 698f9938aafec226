"""Tetrahedralisation with the real fTetWild (pytetwild), its disk cache and its checks."""
from __future__ import annotations

import importlib
import logging
import os
import time

import numpy as np
import pytest
import trimesh

from torchfit.mesh import (MeshError, TetOptions, TetrahedralizationError, default_cache_dir,
                           tetrahedralize)
from torchfit.mesh.surface import surface_volume
from helpers.log_records import warned

FAST = TetOptions(edge_length_fac=0.1)
tetrahedralize_module = importlib.import_module("torchfit.mesh.tetwild.tetrahedralize")


def capsule() -> trimesh.Trimesh:
    return trimesh.creation.capsule(height=0.58, radius=0.045, count=[8, 8])


@pytest.fixture
def cwd(tmp_path, monkeypatch):
    """A clean working directory (to see what fTetWild leaves behind)."""
    path = tmp_path / "cwd"
    path.mkdir()
    monkeypatch.chdir(path)
    return path


def test_capsule_is_filled_with_positive_tetrahedra_and_cached(tmp_path, cwd):
    surface = capsule()
    cache = tmp_path / "cache"
    first = tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=cache)
    assert not first.from_cache and first.build_seconds > 0
    assert first.points.dtype == np.float64 and first.points.shape[1] == 3
    assert first.cells.dtype == np.int64 and first.cells.shape[1] == 4
    assert 100 < len(first.cells) < 5000
    assert (first.volumes > 0).all()
    assert np.array_equal(np.unique(first.cells), np.arange(len(first.points)))  # all used
    # fTetWild's boundary stays within its envelope: the volume within a few per cent
    assert first.volumes.sum() == pytest.approx(surface_volume(surface), rel=0.03)
    assert first.path == cache / f"{first.key}.npz" and first.path.is_file()
    assert len(first.key) == 64
    assert os.listdir(cwd) == []                                  # no __tracked_surface.stl
    assert [p.name for p in cache.iterdir()] == [first.path.name]  # no temporary file left

    second = tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=cache)
    assert second.from_cache and second.key == first.key and second.path == first.path
    assert np.array_equal(second.points, first.points)            # bit for bit
    assert np.array_equal(second.cells, first.cells)
    assert second.build_seconds == first.build_seconds
    assert second.seconds < 0.25 * first.build_seconds

    # the key follows the options and the input
    other = tetrahedralize(surface.vertices, surface.faces,
                           TetOptions(edge_length_fac=0.1, epsilon=2e-3), cache_dir=cache)
    assert not other.from_cache and other.key != first.key
    moved = tetrahedralize(surface.vertices + [0.0, 0.0, 1e-9], surface.faces, FAST,
                           cache_dir=cache, use_cache=False)
    assert moved.key not in (first.key, other.key) and moved.path is None
    assert len(list(cache.glob("*.npz"))) == 2                    # use_cache=False wrote none


@pytest.mark.parametrize("damage", ["torn", "flipped byte"])
def test_a_corrupt_cache_entry_is_rebuilt_with_a_warning(tmp_path, cwd, damage, caplog):
    surface = capsule()
    first = tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=tmp_path)
    data = bytearray(first.path.read_bytes())
    if damage == "torn":
        data = data[:200]
    else:                                                         # caught by the zip CRC
        data[len(data) // 2] ^= 0xFF
    first.path.write_bytes(bytes(data))
    rebuilt = tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=tmp_path)
    assert len(warned(caplog, "cache file .* is unreadable .*rebuilding it")) == 1
    assert not rebuilt.from_cache and (rebuilt.volumes > 0).all()
    caplog.clear()
    again = tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=tmp_path)
    assert not warned(caplog, "")
    assert again.from_cache and np.array_equal(again.cells, rebuilt.cells)
    assert np.array_equal(again.points, rebuilt.points)


def test_an_open_surface_warns_and_still_gives_a_sane_mesh(tmp_path, cwd, caplog):
    surface = capsule()
    faces = surface.faces[surface.triangles_center[:, 2] < 0.25]  # one end cap removed
    assert len(faces) < len(surface.faces)
    mesh = tetrahedralize(surface.vertices, faces, FAST, cache_dir=tmp_path)
    (line,) = warned(caplog, r"not watertight: it is open, with \d+ boundary")
    assert "\n" not in line
    assert (mesh.volumes > 0).all()
    # fTetWild closes the hole: about the whole capsule, never more than its hull
    assert mesh.volumes.sum() == pytest.approx(surface.volume, rel=0.1)
    caplog.clear()
    tetrahedralize(surface.vertices, faces, FAST, cache_dir=tmp_path, warn=False)
    assert not warned(caplog, "")                                 # warn=False: silent


def test_an_inside_out_surface_is_reported_and_meshed(tmp_path, cwd, caplog):
    surface = capsule()
    mesh = tetrahedralize(surface.vertices, surface.faces[:, ::-1], FAST, cache_dir=tmp_path)
    assert len(warned(caplog, "inside out")) == 1
    assert (mesh.volumes > 0).all()
    assert mesh.volumes.sum() == pytest.approx(surface.volume, rel=0.03)


NO_TETS = ("tetrahedralisation produced no tetrahedra: the surface is too broken to enclose "
           "a volume")


@pytest.mark.parametrize("case", ["flat box", "single triangle", "collinear"])
def test_a_degenerate_surface_is_refused_in_one_line(tmp_path, cwd, case):
    if case == "flat box":                       # all vertices on a plane
        box = trimesh.creation.box((1.0, 1.0, 1.0))
        vertices, faces = box.vertices * [1.0, 1.0, 0.0], box.faces
    elif case == "single triangle":
        vertices, faces = np.eye(3), np.array([[0, 1, 2]])
    else:                                        # fTetWild crashes on this one
        vertices = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 1]])
        faces = np.array([[0, 1, 2]])
    with pytest.raises(TetrahedralizationError, match=NO_TETS) as info:
        tetrahedralize(vertices, faces, FAST, cache_dir=tmp_path, warn=False)
    assert "\n" not in str(info.value) and "raise epsilon" in str(info.value)
    assert os.listdir(cwd) == [] and list(tmp_path.glob("*.npz")) == []


@pytest.fixture
def fake_tetwild(monkeypatch):
    """Replace fTetWild's child process by a function returning given arrays (to reach
    every check)."""
    result = {}

    def fake(folder, progress):
        assert (folder / "surface.npz").is_file() and (folder / "options.json").is_file()
        return result["points"], result["cells"]

    monkeypatch.setattr(tetrahedralize_module, "_run_worker", fake)
    return result


def unit_box_tets():
    """The unit cube as 6 positive tetrahedra (Kuhn) plus two unused vertices."""
    from torchfit.mesh import box_tetrahedra

    box = box_tetrahedra(1, 1, 1)
    points = np.vstack([[[9.0, 9.0, 9.0]], box.points, [[7.0, 7.0, 7.0]]])
    return points, (box.cells + 1).astype(np.int32)


def test_checks_after_tetwild(tmp_path, cwd, fake_tetwild, caplog):
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.vertices += 0.5                                            # [0, 1]^3
    points, cells = unit_box_tets()
    fake_tetwild.update(points=points, cells=cells)
    mesh = tetrahedralize(box.vertices, box.faces, FAST, use_cache=False)
    assert len(mesh.points) == 8 and mesh.cells.min() == 0 and mesh.cells.max() == 7
    np.testing.assert_array_equal(mesh.points, points[1:-1])      # unused dropped, order kept
    assert mesh.volumes.sum() == pytest.approx(1.0)

    fake_tetwild.update(cells=np.zeros((0, 4), np.int32))
    with pytest.raises(TetrahedralizationError, match=NO_TETS + r"; repair it \(close holes"):
        tetrahedralize(box.vertices, box.faces, FAST, use_cache=False)
    inverted = cells.copy()
    inverted[[1, 4]] = inverted[[1, 4]][:, [0, 2, 1, 3]]
    fake_tetwild.update(cells=inverted)
    with pytest.raises(TetrahedralizationError, match="2 of 6 tetrahedra with non-positive"):
        tetrahedralize(box.vertices, box.faces, FAST, use_cache=False)
    fake_tetwild.update(cells=cells[:3])                           # half the cube
    with pytest.raises(TetrahedralizationError, match=r"volume 0\.5 is 0\.5 times the volume"):
        tetrahedralize(box.vertices, box.faces, FAST, use_cache=False)
    # an open surface (the cube without its top) may not grow beyond its hull
    open_faces = box.faces[box.triangles_center[:, 2] < 0.99]
    fake_tetwild.update(points=points * 1.2, cells=cells)
    with pytest.raises(TetrahedralizationError, match="convex hull"):
        tetrahedralize(box.vertices, open_faces, FAST, use_cache=False)
    assert warned(caplog, "not watertight")


def test_options_are_checked_and_the_cache_directory_follows_the_environment(monkeypatch,
                                                                             tmp_path):
    for bad in ({"edge_length_fac": 0.0}, {"edge_length_fac": 2.0},
                {"epsilon": float("nan")}, {"stop_energy": -1.0},
                {"edge_length_abs": float("inf")}, {"num_opt_iter": 0}, {"optimize": 1}):
        with pytest.raises(ValueError, match=f"TetOptions.{next(iter(bad))}"):
            TetOptions(**bad)
    assert TetOptions(edge_length_abs=0.01).as_dict() == {
        "edge_length_fac": 0.05, "edge_length_abs": 0.01, "optimize": True, "epsilon": 1e-3,
        "stop_energy": 10.0, "num_opt_iter": 80, "coarsen": False}
    monkeypatch.setenv("TORCHFIT_CACHE_DIR", str(tmp_path))
    assert default_cache_dir() == tmp_path / "tetmesh"
    monkeypatch.delenv("TORCHFIT_CACHE_DIR")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "torchfit" / "tetmesh"
    with pytest.raises(MeshError, match="out of range"):
        tetrahedralize(np.eye(3), np.array([[0, 1, 3]]), use_cache=False)


def test_a_concurrent_build_gets_the_entry_stored_first(tmp_path, monkeypatch):
    """Two processes building the same key: the one that stores second returns the first's
    arrays (never overwriting them), so both fit on the same tetrahedra."""
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.vertices += 0.5
    points, cells = unit_box_tets()
    calls = []

    def racing(folder, progress):
        calls.append(len(calls))
        if len(calls) == 1:           # another process finishes first, while this one runs
            winner = tetrahedralize(box.vertices, box.faces, FAST, cache_dir=tmp_path)
            assert not winner.from_cache
        return points * (1.0 + 1e-3 * len(calls)), cells       # fTetWild varies run to run

    monkeypatch.setattr(tetrahedralize_module, "_run_worker", racing)
    late = tetrahedralize(box.vertices, box.faces, FAST, cache_dir=tmp_path)
    assert len(calls) == 2 and late.from_cache
    np.testing.assert_array_equal(late.points, points[1:-1] * 1.002)   # the winner's
    assert [p.suffix for p in tmp_path.iterdir()] == [".npz"]


def test_the_worker_hands_pytetwild_the_surface_and_options(tmp_path, monkeypatch):
    """The child's script (run here in-process, pytetwild replaced): vtk ordering, quiet,
    int32 faces and the options as given."""
    import pytetwild

    worker = importlib.import_module("torchfit.mesh.tetwild.worker")
    seen = {}

    def fake(vertices, faces, **kwargs):
        seen.update(kwargs, faces_dtype=faces.dtype, n=len(vertices))
        return np.eye(4, 3), np.array([[0, 1, 2, 3]])

    monkeypatch.setattr(pytetwild, "tetrahedralize", fake)
    np.savez(tmp_path / "surface.npz", vertices=np.eye(3), faces=np.array([[0, 1, 2]], np.int32))
    (tmp_path / "options.json").write_text('{"edge_length_fac": 0.07, "epsilon": 0.002}')
    worker.main(tmp_path)
    assert seen["vtk_ordering"] and seen["quiet"] and seen["faces_dtype"] == np.int32
    assert seen["edge_length_fac"] == 0.07 and seen["epsilon"] == 0.002 and seen["n"] == 3
    with np.load(tmp_path / "mesh.npz") as mesh:
        assert mesh["cells"].tolist() == [[0, 1, 2, 3]]


def test_a_crash_of_pytetwild_is_one_line_and_the_run_goes_on(tmp_path, cwd, monkeypatch):
    """A segmentation fault of fTetWild ends its child process only: one line naming it."""
    crash = tmp_path / "crash.py"
    crash.write_text("import os, signal, sys\nprint('fTetWild: bad things')\n"
                     "sys.stdout.flush()\nos.kill(os.getpid(), signal.SIGSEGV)\n")
    monkeypatch.setattr(tetrahedralize_module, "WORKER", crash)
    surface = capsule()
    with pytest.raises(TetrahedralizationError, match=r"^pytetwild failed \(signal SIGSEGV: "
                       r"fTetWild: bad things\); repair the surface") as info:
        tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=tmp_path / "cache")
    assert "\n" not in str(info.value) and os.listdir(cwd) == []
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").iterdir())


def test_progress_starts_at_once_beats_while_pytetwild_runs_and_names_the_result(
        tmp_path, cwd, monkeypatch, caplog):
    """The start line comes before pytetwild is done (well within a second), heartbeats
    while it runs, and the tetrahedron count and cache file at the end."""
    monkeypatch.setattr(tetrahedralize_module, "HEARTBEAT_S", 0.1)
    surface = trimesh.creation.capsule(height=0.58, radius=0.045, count=[16, 16])
    stamps = []

    class Stamp(logging.Handler):
        def emit(self, record):
            stamps.append((time.perf_counter(), record.getMessage()))

    handler = Stamp()
    logging.getLogger("torchfit.setup").addHandler(handler)
    caplog.set_level(logging.INFO, logger="torchfit.setup")
    try:
        start = time.perf_counter()
        mesh = tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=tmp_path)
    finally:
        logging.getLogger("torchfit.setup").removeHandler(handler)
    lines = [m for _, m in stamps]
    assert lines[0] == (f"tetrahedralising a surface of {len(surface.faces):,} faces (pytetwild: "
                        "edge length 0.1 of the diagonal, envelope 0.001) ...")
    assert stamps[0][0] - start < 1.0
    assert any("pytetwild running" in m for m in lines[1:-1])
    assert lines[-1].startswith(f"tetrahedralising a surface of {len(surface.faces):,} faces")
    assert f": {len(mesh.cells):,} tetrahedra, {len(mesh.points):,} vertices, built and cached "\
           f"in {mesh.path}, " in lines[-1]
    stamps.clear()
    logging.getLogger("torchfit.setup").addHandler(handler)
    try:
        tetrahedralize(surface.vertices, surface.faces, FAST, cache_dir=tmp_path)
    finally:
        logging.getLogger("torchfit.setup").removeHandler(handler)
    assert f"read from the cache {mesh.path}" in stamps[-1][1] and len(stamps) == 2
