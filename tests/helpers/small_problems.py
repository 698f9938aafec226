"""Small, quick instances of every registered problem: settings for ``build_problem``."""
from __future__ import annotations

import tempfile
from pathlib import Path

from helpers.capsule_animation import write_capsule

#: Where the 3-D problems keep their meshes and animations during a test session.
CACHE = Path(tempfile.mkdtemp(prefix="torchfit-test-cache-"))
#: Small, quick instances of every registered problem.
SMALL = {"spring1d": {"n": 8}, "poisson2d": {"N": 6}, "membrane2d": {"nx": 4, "ny": 2},
         "arm3d": {"tet_edge_length": 0.12, "frames": [0, 3], "grid": [2, 2, 3],
                   "cache_dir": str(CACHE)},
         "animation": {"path": str(write_capsule(CACHE / "capsule")), "tet_edge_length": 0.15,
                       "grid": [2, 2, 2], "cache_dir": str(CACHE)}}
