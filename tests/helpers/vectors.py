"""Where the independent test vectors are: committed under ``tests/data/vectors``."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: The independent test vectors of the canonical problems (docs/problems.md).
VECTORS = REPO / "tests" / "data" / "vectors"
#: Every file the tests read from :data:`VECTORS`.
VECTOR_FILES = ("README.md", "poisson2d_N16_blocks.npz", "poisson2d_N16_ipam.npz",
                "spring1d_n64.npz")
