"""Problem settings (torchfit.problems.config): the generic checks of every problem's config,
one line each naming the setting; the choice enums and what OmegaConf makes of them."""
from __future__ import annotations

import dataclasses
import json
import math
import typing

import pytest
import torch
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError

from helpers.small_problems import SMALL
from torchfit.reporting.results import jsonable, write_json
from torchfit.physics.elasticity import ALIASES, MATERIALS
from torchfit.problems import (PROBLEMS, Membrane2DConfig, ProblemConfigError, Spring1D,
                               Spring1DConfig, build_problem)
from torchfit.problems.config import Backend, DataMode, DType
from torchfit.problems.membrane2d import Model
from torchfit.settings import choice_fields


def numeric_fields(config_class: type) -> list[tuple[str, bool]]:
    """``(field, is_list)`` of every numeric setting of a config dataclass."""
    hints = typing.get_type_hints(config_class)
    out = []
    for f in dataclasses.fields(config_class):
        hint = hints[f.name]
        if hint in (int, float):
            out.append((f.name, False))
        elif typing.get_origin(hint) is list and typing.get_args(hint)[0] in (int, float):
            out.append((f.name, True))
    return out


BAD_NUMBERS = [(name, key, is_list, value)
               for name, entry in PROBLEMS.items()
               for key, is_list in numeric_fields(entry.config_class)
               for value in (math.inf, -math.inf, math.nan)]
BAD_CHOICES = [(name, key) for name, entry in PROBLEMS.items()
               for key in choice_fields(entry.config_class)]


def one_line_error(name: str, overrides: dict) -> str:
    with pytest.raises(ProblemConfigError) as info:
        build_problem(name, {**SMALL[name], **overrides})
    message = str(info.value)
    assert "\n" not in message, message
    return message


# -- generic checks ---------------------------------------------------------------------
def test_every_problem_has_numeric_settings_to_check():
    assert {name for name, *_ in BAD_NUMBERS} == set(PROBLEMS)
    keys = {(name, key) for name, key, *_ in BAD_NUMBERS}
    assert {("spring1d", "noise"), ("spring1d", "k0"), ("spring1d", "k_background"),
            ("spring1d", "loads"), ("poisson2d", "s"), ("membrane2d", "newton_atol")} <= keys


@pytest.mark.parametrize("name, key, is_list, value", BAD_NUMBERS,
                         ids=[f"{n}-{k}-{v}" for n, k, _, v in BAD_NUMBERS])
def test_non_finite_numbers_name_the_setting(name, key, is_list, value):
    default = getattr(PROBLEMS[name].config_class(), key)
    bad = [*default[:-1], value] if is_list else value
    message = one_line_error(name, {key: bad})
    assert message.startswith(f"problem.{key}="), message
    assert str(value) in message and "finite" in message


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_negative_noise_and_wrong_number_types(name):
    assert one_line_error(name, {"noise": -0.1}).startswith("problem.noise=-0.1: must be >= 0")
    assert one_line_error(name, {"seed": 1.5}).startswith("problem.seed=1.5: must be an integer")
    assert one_line_error(name, {"noise": "big"}).startswith("problem.noise=big: must be a number")


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_unknown_device_lists_the_allowed_ones(name):
    message = one_line_error(name, {"device": "gpu"})
    assert message.startswith("problem.device=gpu: is not a device")
    assert "cpu" in message and "cuda:N" in message


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_cuda_without_cuda_says_so(name, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for device in ("cuda", "cuda:1"):
        message = one_line_error(name, {"device": device, "backend": "cg"})
        assert message.startswith(f"problem.device={device}: ")
        assert "has no CUDA here" in message and "problem.device=cpu" in message


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_direct_backend_on_cuda_is_refused(name):
    message = one_line_error(name, {"device": "cuda", "backend": "scipy"})
    assert message.startswith("problem.backend=scipy: runs on the CPU only")


@pytest.mark.parametrize("name, key", BAD_CHOICES, ids=[f"{n}-{k}" for n, k in BAD_CHOICES])
def test_bad_choice_strings_list_the_choices(name, key):
    kind = choice_fields(PROBLEMS[name].config_class)[key]
    message = one_line_error(name, {key: "bogus"})
    assert message.startswith(f"problem.{key}=bogus is not a {key} choice; choose one of ")
    assert message.endswith(", ".join(kind.choices()))
    with pytest.raises(ProblemConfigError, match=f"problem.{key}=bogus"):
        PROBLEMS[name].config_class(**{key: "bogus"})          # programmatic construction


def test_unknown_settings_are_named():
    with pytest.raises(ProblemConfigError, match="problem.bogus"):
        Spring1D(bogus=1)
    with pytest.raises(ProblemConfigError, match="problem.bogus"):
        build_problem("poisson2d", {"N": 5, "bogus": 1})


# -- choices ------------------------------------------------------------------------------
def test_choice_settings_are_enums_and_accept_plain_strings():
    cfg = Spring1DConfig(data="sparse", backend="cg", dtype="float32", transform="identity")
    assert cfg.data is DataMode.sparse and cfg.data == "sparse" and str(cfg.data) == "sparse"
    assert cfg.backend is Backend.cg and cfg.dtype is DType.float32
    assert f"{cfg.data}" == "sparse"
    assert dataclasses.replace(cfg, data="dense").data is DataMode.dense
    covered = {kind for entry in PROBLEMS.values()
               for kind in choice_fields(entry.config_class).values()}
    assert {DataMode, Backend, DType, Model}.issubset(covered)
    assert {"pattern", "transform"} <= set(choice_fields(PROBLEMS["poisson2d"].config_class))
    for kind in covered:                       # OmegaConf converts strings by member name
        assert all(member.name == member.value for member in kind)


def test_membrane_models_are_the_physics_materials():
    assert set(Model.choices()) == set(MATERIALS) | set(ALIASES)


@pytest.mark.parametrize("name, key", BAD_CHOICES, ids=[f"{n}-{k}" for n, k in BAD_CHOICES])
def test_omegaconf_rejects_a_bad_choice_at_compose_time(name, key):
    schema = OmegaConf.structured(PROBLEMS[name].config_class)
    kind = choice_fields(PROBLEMS[name].config_class)[key]
    with pytest.raises(ValidationError) as info:
        OmegaConf.merge(schema, OmegaConf.from_dotlist([f"{key}=bogus"]))
    assert f"expected one of [{', '.join(kind.choices())}]" in str(info.value)
    good = OmegaConf.merge(schema, OmegaConf.from_dotlist([f"{key}={kind.choices()[-1]}"]))
    assert good[key] == kind.choices()[-1]


def test_omegaconf_node_builds_the_problem():
    node = OmegaConf.merge(OmegaConf.structured(Spring1DConfig),
                           OmegaConf.from_dotlist(["n=16", "data=sparse", "loads=[0.0,1.0]"]))
    problem = build_problem("spring1d", node)
    assert problem.cfg.data is DataMode.sparse and problem.observed_nodes.tolist() == [8, 16]
    assert problem.n_frames == 2


def test_configs_serialise_choices_by_value(tmp_path):
    plain = jsonable(Membrane2DConfig())
    assert type(plain["model"]) is str and plain["model"] == "corotated"
    assert plain["data"] == "dense" and plain["dtype"] == "float64"
    path = write_json(tmp_path / "cfg.json", {"problem": Spring1DConfig(data="sparse")})
    text = path.read_text()
    assert '"data": "sparse"' in text and "DataMode" not in text
    assert json.loads(text)["problem"]["backend"] == "scipy"


def test_float32_nonlinear_sheet_needs_a_float32_newton_tolerance():
    message = one_line_error("membrane2d", {"dtype": "float32"})
    assert message.startswith("problem.newton_atol=1e-13: is below what float32 reaches")
