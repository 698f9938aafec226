"""The vendored test vectors (tests/data/vectors) are complete and, where the shared
originals sit beside the repository (../shared/vectors), byte-identical to them."""
from __future__ import annotations

import pytest

from helpers.vectors import SHARED_VECTORS, VECTOR_FILES, VECTORS


def test_vendored_vectors_are_all_there():
    missing = [name for name in VECTOR_FILES if not (VECTORS / name).is_file()]
    assert not missing, f"missing from {VECTORS}: {missing}"


@pytest.mark.parametrize("name", VECTOR_FILES)
def test_vendored_vectors_match_the_shared_originals(name):
    original = SHARED_VECTORS / name
    if not SHARED_VECTORS.is_dir():
        pytest.skip(f"{SHARED_VECTORS} is not beside the repository; nothing to compare")
    assert original.is_file(), f"{original} is gone from the shared vectors"
    assert (VECTORS / name).read_bytes() == original.read_bytes(), \
        f"tests/data/vectors/{name} differs from {original}: re-copy it"


def test_no_shared_vector_is_left_out():
    if not SHARED_VECTORS.is_dir():
        pytest.skip(f"{SHARED_VECTORS} is not beside the repository")
    shared = sorted(p.name for p in SHARED_VECTORS.iterdir() if p.is_file())
    assert sorted(VECTOR_FILES) == shared
