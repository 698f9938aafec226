"""The independent test vectors (tests/data/vectors) are complete: every file the tests read
is there, and nothing is there that no test reads."""
from __future__ import annotations

from helpers.vectors import VECTOR_FILES, VECTORS


def test_vendored_vectors_are_all_there():
    missing = [name for name in VECTOR_FILES if not (VECTORS / name).is_file()]
    assert not missing, f"missing from {VECTORS}: {missing}"


def test_no_vector_is_left_unread():
    present = sorted(p.name for p in VECTORS.iterdir() if p.is_file())
    assert present == sorted(VECTOR_FILES), f"{VECTORS} holds {present}"
