"""The settings of a run: every check names its setting in one line."""
from __future__ import annotations

import dataclasses
import enum

import pytest

from torchfit.problems import build_problem
from torchfit.run import FitConfigError, FitOptions, VerifyOptions
from torchfit.run.options import plain_settings


@pytest.mark.parametrize("options,match", [
    (FitOptions(progress=1), "progress=1 must be true or false"),
    (FitOptions(log_every=0), "log_every=0 must be an integer >= 1"),
    (FitOptions(snapshot_every=-1), "snapshot_every=-1"),
    (FitOptions(threads=True), "threads=True"),
    (FitOptions(snapshot_iterations=[1, -2]), "snapshot_iterations"),
    (FitOptions(objective_metric="k_err_rel_aligned"), "not reported by spring1d"),
    (FitOptions(sheet_frame=0), "not a frame of spring1d .it has no frames to draw"),
])
def test_fit_options_name_the_bad_setting(options, match):
    problem = build_problem("spring1d", {"n": 4})
    with pytest.raises(FitConfigError, match=match) as info:
        options.check(problem)
    assert "\n" not in str(info.value)
    FitOptions().check(problem)


@pytest.mark.parametrize("settings,match", [
    ({"at": "nowhere"}, "at='nowhere' is not a point"),
    ({"perturbation": -0.5}, "perturbation"),
    ({"taylor_tol": float("nan")}, "taylor_tol"),
    ({"fd_tol": 0.0}, "fd_tol"),
    ({"threads": -1}, r"threads=-1 must be an integer from 0 \(torch's default\) to 4096"),
])
def test_verify_options_name_the_bad_setting(settings, match):
    with pytest.raises(FitConfigError, match=match):
        dataclasses.replace(VerifyOptions(), **settings).check()
    VerifyOptions(at="truth", fd_tol=None).check()


def test_plain_settings_are_json_values():
    class Kind(str, enum.Enum):
        a = "a"

    @dataclasses.dataclass
    class Settings:
        kind: Kind = Kind.a
        sizes: tuple = (1, 2)

    assert plain_settings(Settings()) == {"kind": "a", "sizes": [1, 2]}
    assert plain_settings({"x": float("nan")}) == {"x": None}


def test_threads_are_an_integer_from_0_to_the_limit():
    """``threads=1e12`` reached torch as an overflow (the settings probe's one fail)."""
    import pytest as _pytest

    from torchfit.run.options import MAX_THREADS, FitConfigError, check_threads

    for good in (0, 1, MAX_THREADS):
        check_threads(good)
    for bad in (-1, MAX_THREADS + 1, 10 ** 12, 1.5, "2", True):
        with _pytest.raises(FitConfigError, match="threads="):
            check_threads(bad)
