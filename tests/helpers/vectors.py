"""Where the independent test vectors are: vendored under ``tests/data/vectors`` and, when
it is there, ``shared/vectors`` beside the repository."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: The independent test vectors of PROBLEMS.md, vendored (committed) with the tests.
VECTORS = REPO / "tests" / "data" / "vectors"
#: Where they come from: ``shared/vectors`` beside the repository, when it is there.
SHARED_VECTORS = REPO.parent / "shared" / "vectors"
#: Every file the tests read from :data:`VECTORS`.
VECTOR_FILES = ("README.md", "poisson2d_N16_blocks.npz", "poisson2d_N16_ipam.npz",
                "spring1d_n64.npz")
