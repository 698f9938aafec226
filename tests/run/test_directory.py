"""A run directory is checked before anything is written."""
from __future__ import annotations

import pytest

from torchfit.run import RunDirectoryError
from torchfit.run.directory import check_writable


def test_a_run_directory_that_cannot_be_written_is_named(tmp_path):
    check_writable(tmp_path / "new" / "run")          # creatable: nothing written
    assert not (tmp_path / "new").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(RunDirectoryError, match="it is a file"):
        check_writable(tmp_path / "file")
    with pytest.raises(RunDirectoryError, match="is a file"):
        check_writable(tmp_path / "file" / "run")
