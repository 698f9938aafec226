"""Bad input refused with one line (issue 27, item 6): files that are not what a setting
says, settings out of range. Each is a :class:`ConfigurationError` (the app: exit 2, one
``error:`` line, nothing written); the app-level cases are in tests/experiments."""
from __future__ import annotations

import os

import numpy as np
import pytest

from helpers.capsule_animation import write_capsule
from helpers.log_records import warned
from torchfit import build_problem
from torchfit.errors import ConfigurationError


def refused(name, settings, match):
    with pytest.raises(ConfigurationError, match=match) as info:
        build_problem(name, settings)
    text = str(info.value)
    assert "\n" not in text and "pickle" not in text and "Traceback" not in text
    return text


def test_targets_files_that_are_not_arrays_of_numbers(tmp_path):
    good = np.linspace(0, 1, 3 * 65).reshape(3, 65)
    np.save(tmp_path / "good.npy", good)
    (tmp_path / "random.npy").write_bytes(np.random.default_rng(0).bytes(1000))
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}, None], dtype=object))
    (tmp_path / "short.npy").write_bytes((tmp_path / "good.npy").read_bytes()[:300])
    refused("spring1d", {"targets": str(tmp_path / "random.npy")},
            r"^problem.targets=.*random.npy: not a numpy .npy array")
    refused("spring1d", {"targets": str(tmp_path / "objects.npy")},
            r"^problem.targets=.*objects.npy: holds Python objects")
    refused("spring1d", {"targets": str(tmp_path / "short.npy")},
            r"^problem.targets=.*short.npy: the file is truncated \(300 bytes, its header "
            r"declares 1688")
    problem = build_problem("spring1d", {"targets": str(tmp_path / "good.npy")})
    assert problem.data.numel() == 3 * 64      # every free node of the 3 frames


def test_manifest_not_utf8(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    manifest = folder / "animation.yaml"
    manifest.write_bytes(manifest.read_bytes() + "# caf\xe9\n".encode("latin-1"))
    refused("animation", {"path": str(folder)}, r"animation.yaml: not UTF-8 "
            r"text \(byte \d+\); save it as UTF-8")


def test_tet_edge_length_above_one(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    refused("animation", {"path": str(folder), "tet_edge_length": 1.5},
            r"^problem.tet_edge_length=1.5: .* must lie in \(0, 1\]")
    refused("arm3d", {"tet_edge_length": 2.0}, r"^problem.tet_edge_length=2.0")


def test_tetwild_envelope_and_stop_energy_out_of_range(tmp_path):
    """An envelope of 10^12 diagonals made no tetrahedra (the error named the file), a stop
    energy of 10^12 a mesh Newton could not solve on (exit 1): both refused by name."""
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    refused("animation", {"path": str(folder), "tet_epsilon": 1e12},
            r"^problem.tet_epsilon=1000000000000.0: is the envelope .* must lie in \(0, 0.05\]")
    refused("animation", {"path": str(folder), "tet_stop_energy": 1e12},
            r"^problem.tet_stop_energy=1000000000000.0: must lie in \(0, 1000\]")


def test_duplicate_frames_refused(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    refused("animation", {"path": str(folder), "frames": [1, 1]},
            r"^problem.frames=\[1, 1\]: lists a frame twice")
    refused("arm3d", {"frames": [3, 3, 3]}, r"^problem.frames=\[3, 3, 3\]: lists a frame twice")


def test_corrupt_arm_animation_cache_is_rebuilt(tmp_path, caplog):
    settings = {"cache_dir": str(tmp_path), "tet_edge_length": 0.1, "grid": [3, 3, 4],
                "frames": [0, 11]}
    first = build_problem("arm3d", settings)
    (folder,) = (tmp_path / "animations").iterdir()
    frames = np.load(folder / "frames.npz")["frames"]
    (folder / "frames.npz").write_bytes(b"\0" * 100)          # a corrupt copy
    again = build_problem("arm3d", settings)
    assert len(warned(caplog, r"arm3d animation cache .* is unreadable .* rebuilding")) == 1
    assert np.array_equal(np.load(folder / "frames.npz")["frames"], frames)
    assert np.array_equal(again.animation.frames, first.animation.frames)
    caplog.clear()
    build_problem("arm3d", settings)                            # rebuilt once, then read
    assert not warned(caplog, "")


# -- sizes checked before allocation (issue 27, item 5) ----------------------------------
def test_memory_limit_from_the_environment(monkeypatch):
    from torchfit.memory import LIMIT_VARIABLE, memory_limit

    monkeypatch.setenv(LIMIT_VARIABLE, "1.5G")
    assert memory_limit() == int(1.5 * 2 ** 30)
    monkeypatch.setenv(LIMIT_VARIABLE, "4096")
    assert memory_limit() == 4096
    monkeypatch.setenv(LIMIT_VARIABLE, "lots")
    with pytest.raises(ConfigurationError, match="TORCHFIT_MEMORY_LIMIT=lots: not a size"):
        memory_limit()
    monkeypatch.delenv(LIMIT_VARIABLE)
    assert memory_limit() > 2 ** 20          # MemAvailable here


@pytest.mark.parametrize("name,settings,match", [
    ("spring1d", {"n": 10 ** 10}, r"^problem.n=10000000000: needs about 2.3 TiB for "
     r"10000000001 nodes x 3 frames, more than the 1.0 GiB of TORCHFIT_MEMORY_LIMIT"),
    ("spring1d", {"dynamic": True, "dt": 1e-9},
     r"^problem.dt=1e-09 to problem.duration=6.0 at problem.frames=60: "
     r"needs about 1.4 TiB for 6e\+09 time steps to t = 6 s, .* choose a larger problem.dt or "
     r"an earlier end time"),
    ("spring1d", {"dynamic": True, "dt": 1e-5, "checkpoint_every": 0},  # the step grid
     r"^problem.dt=1e-05 to problem.duration=6.0 at problem.frames=60: needs about 146.5 MiB "
     r"for 6e\+05 time steps"),
    ("spring1d", {"dynamic": True, "dt": 5e-324, "checkpoint_every": 0},   # not a crash
     r"^problem.dt=5e-324 to problem.duration=6.0 at problem.frames=60: needs about inf TiB "
     r"for inf time steps"),
    ("spring1d", {"dynamic": True, "duration": 1e12},        # names the end time
     r"^problem.dt=0.01 to problem.duration=1000000000000.0 at problem.frames=60: needs about "
     r".* TiB for 1e\+14 time steps"),
    ("spring1d", {"dynamic": True, "frames": 10 ** 12},
     r"^problem.n=64 x problem.frames=1000000000000: needs about .* TiB for 65 nodes x "
     r"1000000000000 output times"),
    ("poisson2d", {"N": 10 ** 5}, r"^problem.N=100000: needs about 2.9 TiB for 100000 x "
     r"100000 = 1e\+10 grid nodes"),
    ("membrane2d", {"nx": 10 ** 5, "ny": 10 ** 4}, r"^problem.nx=100000 problem.ny=10000: "
     r"needs about 447"),
    ("membrane2d", {"dynamic": True, "dt": 1e-9}, r"^problem.dt=1e-09 to problem.duration=2.0 at "
     r"problem.frames=\d+: needs about"),
    ("arm3d", {"grid": [1000, 1000, 1000]}, r"^problem.grid=\[1000, 1000, 1000\]: needs "
     r"about 59.6 GiB for 1e\+09 grid nodes"),
])
def test_sizes_refused_before_allocation(monkeypatch, tmp_path, name, settings, match):
    monkeypatch.setenv("TORCHFIT_MEMORY_LIMIT", "1G" if "1e-05" not in match else "100M")
    refused(name, {**settings, **({"cache_dir": str(tmp_path)} if name == "arm3d" else {})},
            match)
    assert not any(tmp_path.iterdir())          # the arm wrote no animation


def test_a_checkpoint_interval_beyond_the_steps_stores_one_segment(monkeypatch):
    """checkpoint_every larger than the steps keeps the start and one recomputed segment of
    every step: the states of checkpoint_every = steps, not 10^12 (a legal setting)."""
    from torchfit.problems.dynamic import time_steps_allocation
    from torchfit.problems.spring1d import Spring1DConfig
    steps = 600 + 60
    huge = time_steps_allocation(Spring1DConfig(dynamic=True, checkpoint_every=10 ** 12), 65)
    same = time_steps_allocation(Spring1DConfig(dynamic=True, checkpoint_every=steps), 65)
    every = time_steps_allocation(Spring1DConfig(dynamic=True, checkpoint_every=1), 65)
    assert huge[1][1] == same[1][1] == (2 + steps) * 65 * 16
    assert huge[1][0] == "problem.checkpoint_every=1000000000000"
    assert every[1][1] == (steps + 1) * 65 * 16


def test_default_problems_fit_in_a_small_limit():
    # what the canonical settings state is far below any machine (64 MiB), and the presets'
    # dynamic runs too: no normal run is refused
    from torchfit.problems import PROBLEMS
    from torchfit.problems.config import make_config

    for name, settings in [("spring1d", {}), ("poisson2d", {}), ("membrane2d", {}),
                           ("spring1d", {"dynamic": True}), ("membrane2d", {"dynamic": True}),
                           ("arm3d", {}), ("animation", {"path": "x"})]:
        entry = PROBLEMS[name]
        cls = entry.dynamic_class if settings.get("dynamic") else entry.problem_class
        cfg = make_config(entry.config_class, settings)
        sizes = cls.allocation(cls.__new__(cls), cfg)
        assert sizes and all(entry[1] < 2 ** 26 for entry in sizes), (name, sizes)


def _declaring_npz(path, shape):
    """A .npz whose frames.npy header declares ``shape`` (float64) but holds no data."""
    import io
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False,
                                                  "shape": shape})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("frames.npy", header.getvalue() + bytes(1000))


def test_animation_files_checked_by_their_headers(monkeypatch, tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    n_vertices = np.load(folder / "frames.npz")["frames"].shape[1]
    # 8.6 GiB declared in a small file: refused from its header, the data never read
    frames = int(8.6 * 2 ** 30 / (n_vertices * 3 * 8))
    _declaring_npz(folder / "frames.npz", (frames, n_vertices, 3))
    monkeypatch.setenv("TORCHFIT_MEMORY_LIMIT", "16G")
    text = refused("animation", {"path": str(folder)},
                   r"frames.npz: needs about 34.[0-9] GiB for its array \(\d+, \d+, 3\) of "
                   r"float64, more than the 16.0 GiB of TORCHFIT_MEMORY_LIMIT")
    assert "problem.path=" in text
    # a region label of 1e9: one per rest vertex at most, refused before any name is made
    folder = write_capsule(tmp_path / "d", "skeleton", "npz")
    labels = np.zeros(n_vertices, dtype=np.int64)
    labels[5] = 10 ** 9
    np.save(folder / "regions.npy", labels)
    manifest = folder / "animation.yaml"
    manifest.write_text(manifest.read_text() + "regions:\n  labels: regions.npy\n")
    refused("animation", {"path": str(folder)}, r"regions.npy: region labels must lie in "
            rf"0..{n_vertices - 1} \(one per rest vertex at most\), got 0..1000000000")


def test_frames_given_as_a_glob_of_meshes_are_sized_before_they_are_read(monkeypatch, tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "obj")
    files = [p for p in folder.rglob("*.obj") if p.name != "rest.obj"]
    assert len(files) >= 2, "the capsule writes its frames as OBJ files"
    # above the grid's few KiB, below four float64 copies of the stacked frames
    monkeypatch.setenv("TORCHFIT_MEMORY_LIMIT", "100K")
    refused("animation", {"path": str(folder)},
            rf"\*\.obj: needs about .* for {len(files)} frame files x \d+ vertices, more than "
            r"the 100.0 KiB of TORCHFIT_MEMORY_LIMIT")


def test_a_tet_count_or_edge_length_too_large_for_memory_is_refused_before_tetwild(
        monkeypatch, tmp_path):
    """Issue 38: problem.tet_count=1e9 ran pytetwild for minutes; now refused at once, the
    largest count that fits named, no mesh built or cached."""
    import time

    monkeypatch.setenv("TORCHFIT_MEMORY_LIMIT", "1G")
    started = time.perf_counter()
    text = refused("arm3d", {"tet_count": 10 ** 9, "cache_dir": str(tmp_path),
                             "frames": [0, 3]},
                   r"^problem.tet_count=1000000000: needs about 636.3 GiB for 1e\+09 "
                   r"tetrahedra x 2 frame\(s\), more than the 1.0 GiB of TORCHFIT_MEMORY_LIMIT")
    assert "at most about 1.6e+06 tetrahedra over 2 frame(s); choose a smaller value" in text
    assert time.perf_counter() - started < 5 and not any(tmp_path.iterdir())
    text = refused("arm3d", {"tet_edge_length": 1e-4, "cache_dir": str(tmp_path),
                             "frames": [0, 3]},
                   r"^problem.tet_edge_length=0.0001: needs about .* TiB for at least .* "
                   r"tetrahedra x 2 frames")
    assert "choose a larger value" in text and "nothing was tetrahedralised" in text
    assert time.perf_counter() - started < 10 and not (tmp_path / "tetmesh").exists()


@pytest.mark.parametrize("settings, match", [
    ({"max_flexion": 1000}, r"^problem.max_flexion=1000: must lie in \(0, 150\] degrees"),
    ({"max_flexion": 0}, r"^problem.max_flexion=0: must lie in \(0, 150\]"),
    ({"max_extension": 90}, r"^problem.max_extension=90: must lie in \[0, 90\)")])
def test_the_arms_animation_settings_are_range_checked(tmp_path, settings, match):
    """Issue 38: problem.max_flexion=1000 was accepted (the forearm turned through itself)."""
    refused("arm3d", {**settings, "cache_dir": str(tmp_path)}, match)
    assert not any(tmp_path.iterdir())          # no animation written


@pytest.mark.parametrize("settings, match", [
    ({"upper": 1e12}, r"^problem.upper=1000000000000.0: must be at most 1000 times the "
                      r"thinner radius"),
    ({"fore": 100.0}, r"^problem.fore=100.0: must be at most 1000 times"),
    ({"r_wrist": 1e12}, r"^problem.r_wrist=1000000000000.0: must be at most half the shorter "
                        r"segment \(0.28 m"),
    ({"r_shoulder": 0.2}, r"^problem.r_shoulder=0.2: must be at most half"),
    ({"bicep_bulge": 1e12}, r"^problem.bicep_bulge=1000000000000.0: must be at most the "
                            r"wrist's radius"),
    ({"tricep_bulge": -0.5}, r"^problem.tricep_bulge=-0.5: must be at most the wrist's radius"),
    ({"n_frames": 10 ** 12}, r"^problem.n_frames=1000000000000: needs about .* TiB for "
                             r"1000000000000 frames of the arm's 1920 surface vertices"),
])
def test_the_procedural_arm_refuses_a_shape_it_cannot_mesh(tmp_path, settings, match):
    """Each of these made the tetrahedralisation flatten the arm (no tetrahedra, the error
    naming a cache file), a frame 10^11 times the rest's size, or an allocation of 7 TiB
    (exit 1): refused by name before anything is written."""
    refused("arm3d", {**settings, "cache_dir": str(tmp_path)}, match)
    assert not any(tmp_path.iterdir())
