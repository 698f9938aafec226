"""Bad input refused with one line (issue 27, item 6): files that are not what a setting
says, settings out of range. Each is a :class:`ConfigurationError` (the app: exit 2, one
``error:`` line, nothing written); the app-level cases are in tests/experiments."""
from __future__ import annotations

import os

import numpy as np
import pytest

from helpers.capsule_animation import write_capsule
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
    refused("animation", {"path": str(folder)}, r"animation.yaml: the manifest is not UTF-8 "
            r"text \(byte \d+\); save it as UTF-8")


def test_tet_edge_length_above_one(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    refused("animation", {"path": str(folder), "tet_edge_length": 1.5},
            r"^problem.tet_edge_length=1.5: .* must lie in \(0, 1\]")
    refused("arm3d", {"tet_edge_length": 2.0}, r"^problem.tet_edge_length=2.0")
