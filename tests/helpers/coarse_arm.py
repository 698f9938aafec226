"""A coarse procedural arm for tests: a small mesh in a per-module cache directory."""
from __future__ import annotations

import pytest

from torchfit.problems import build_problem

#: the arm's settings that make it small (about 1-2k tetrahedra, 36 grid parameters)
COARSE = {"tet_edge_length": 0.1, "grid": [3, 3, 4]}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A tetrahedralisation cache of the test module's own (import it into the module)."""
    return str(tmp_path_factory.mktemp("arm-cache"))


def arm(cache, **settings):
    """The coarse arm, ``settings`` over :data:`COARSE`."""
    return build_problem("arm3d", {"cache_dir": cache, **COARSE, **settings})
