"""The registry of problems (torchfit.problems): entries, names, and build_problem."""
from __future__ import annotations

import dataclasses

import pytest

from torchfit.problems import (PROBLEMS, ProblemConfig, ProblemConfigError, ProblemEntry,
                               Spring1DConfig, build_problem)


def test_registry_entries():
    for name, entry in PROBLEMS.items():
        assert isinstance(entry, ProblemEntry)
        assert issubclass(entry.config_class, ProblemConfig)
        assert entry.problem_class.config_class is entry.config_class
        assert entry.config_class().name == name == entry.problem_class.name
    with pytest.raises(dataclasses.FrozenInstanceError):
        PROBLEMS["spring1d"].config_class = ProblemConfig
    with pytest.raises(ProblemConfigError, match="spring1d"):
        build_problem("spring2d")
    with pytest.raises(ProblemConfigError, match="Spring1DConfig"):
        build_problem("poisson2d", Spring1DConfig())
    for entry in PROBLEMS.values():
        if entry.dynamic_class is not None:        # the motion of the same problem
            assert issubclass(entry.dynamic_class, entry.problem_class)
            assert "dynamic" in {f.name for f in dataclasses.fields(entry.config_class)}
