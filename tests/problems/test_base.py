"""The problem contract of torchfit.problems.base: config base class and its checks, the
choice enums, the template constructor, metric_names, the registry, explicit dtypes."""
from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import tempfile
import typing
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError

from helpers.capsule_animation import write_capsule
from helpers.fit_app import REPO
from torchfit.logging.results import jsonable, write_json
from torchfit.physics.elasticity import ALIASES, MATERIALS
from torchfit.problems import (PROBLEMS, Backend, DataMode, DType,
                               FieldImageProblem, FramedProblem, InverseProblem,
                               Membrane2DConfig, MeshProblem, Model, ProblemConfig,
                               ProblemConfigError, ProblemEntry, Spring1D, Spring1DConfig,
                               build_problem)
from torchfit.problems.base import BodyProblem
from torchfit.settings import choice_fields

#: Where the 3-D problems keep their meshes and animations during this test module.
CACHE = Path(tempfile.mkdtemp(prefix="torchfit-test-cache-"))
#: Small, quick instances of every registered problem.
SMALL = {"spring1d": {"n": 8}, "poisson2d": {"N": 6}, "membrane2d": {"nx": 4, "ny": 2},
         "arm3d": {"tet_edge_length": 0.12, "frames": [0, 3], "grid": [2, 2, 3],
                   "cache_dir": str(CACHE)},
         "animation": {"path": str(write_capsule(CACHE / "capsule")), "tet_edge_length": 0.15,
                       "grid": [2, 2, 2], "cache_dir": str(CACHE)}}


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


# -- the template ---------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_metric_names_are_the_metric_keys(name):
    problem = build_problem(name, SMALL[name])
    assert isinstance(problem, InverseProblem)
    assert list(problem.metrics(problem.theta0)) == problem.metric_names()
    expected = {"misfit"}
    if problem.field_true is not None:
        expected |= {"u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel"}
        if problem.scale_free:
            expected.add("k_err_rel_aligned")
    if isinstance(problem, BodyProblem):     # a body fitted to an animation (arm3d, animation)
        expected |= {"surface_err_mean", "surface_err_max", "surface_err_reduction",
                     "joint_volume_change", "inverted_tets"}
    assert set(problem.metric_names()) == expected


def test_metric_names_without_truth(tmp_path):
    reference = Spring1D(n=4)
    path = tmp_path / "targets.npy"
    import numpy as np
    np.save(path, reference.x_true[..., 0].numpy())
    problem = Spring1D(n=4, targets=str(path))
    assert problem.metric_names() == ["misfit"] == list(problem.metrics(problem.theta0))


def test_protocols_are_opt_in():
    spring, poisson, sheet = (build_problem(n, SMALL[n]) for n in
                              ("spring1d", "poisson2d", "membrane2d"))
    assert not isinstance(spring, (FieldImageProblem, FramedProblem, MeshProblem))
    assert isinstance(poisson, FieldImageProblem)
    assert not isinstance(poisson, (FramedProblem, MeshProblem))
    assert all(isinstance(sheet, p) for p in (FieldImageProblem, FramedProblem, MeshProblem))


class Line(InverseProblem):
    """A new problem is its physics and its data: x_i = c_i * k (one frame, one node each)."""

    @dataclasses.dataclass
    class Config(ProblemConfig):
        name: str = "line"
        n: int = 3
        k0: float = 1.0

    config_class = Config
    name = "line"

    def build_model(self, cfg):
        self.c = torch.arange(1, cfg.n + 1, dtype=self.dtype, device=self.device)

    def build_parameterization(self, cfg):
        from torchfit.params import per_element
        return per_element(cfg.n, None, cfg.transform.value, dtype=self.dtype)

    def build_observation(self, cfg):
        self.observed_nodes = torch.arange(cfg.n)

    def true_field(self, cfg):
        return torch.full((cfg.n,), 2.0, dtype=self.dtype)

    def simulate(self, field):
        return (self.c * field)[None, :, None]

    def observe(self, x):
        return x[0, :, 0]


def test_template_builds_a_minimal_problem():
    problem = Line(noise=0.1, seed=1, dtype="float32")
    assert problem.dtype == torch.float32 and problem.theta0.dtype == torch.float32
    assert torch.allclose(problem.x_true[0, :, 0], torch.tensor([2.0, 4.0, 6.0],
                                                               dtype=torch.float32))
    assert problem.noise_level == pytest.approx(0.1 * math.sqrt(3))
    assert not torch.equal(problem.data, problem.observe(problem.x_true))
    assert problem.metric_names() == list(problem.metrics(problem.theta0))
    with pytest.raises(ProblemConfigError, match=r"^problem.k0=inf: "):
        Line(k0=math.inf)


def test_non_finite_simulated_targets_are_named():
    class Broken(Line):
        def simulate(self, field):
            x = super().simulate(field).clone()
            x[0, 1, 0] = math.nan
            return x

    with pytest.raises(ProblemConfigError, match="simulated target of frame 0, node 1 is nan"):
        Broken()


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


# -- dtype ----------------------------------------------------------------------------------
DTYPE_SCRIPT = r"""
import torch
assert torch.get_default_dtype() == torch.float32
import torchfit, torchfit.problems, torchfit.solvers, torchfit.logging, torchfit.verification
assert torch.get_default_dtype() == torch.float32, "import torchfit changed the default dtype"
from torchfit.problems import build_problem
cases = [("spring1d", {"n": 8}), ("spring1d", {"n": 8, "backend": "cg", "data": "sparse",
                                                "sparse_stride": 2}),
         ("poisson2d", {"N": 6}), ("poisson2d", {"N": 6, "backend": "cg", "pattern": "ipam"}),
         ("membrane2d", {"nx": 4, "ny": 2}),
         ("membrane2d", {"nx": 4, "ny": 2, "model": "linear", "backend": "scipy"}),
         ("membrane2d", {"nx": 4, "ny": 2, "model": "stable_neo_hookean", "backend": "cg"})]
def products(problem):
    lin = problem.residual().linearize(problem.theta0 + 0.1)
    v = torch.linspace(-1, 1, problem.theta0.numel(), dtype=problem.dtype)
    return {"theta0": problem.theta0, "data": problem.data, "x_true": problem.x_true,
            "field_true": problem.field_true, "forward": problem.forward(problem.theta0),
            "Jv": lin.jvp(v), "JTw": lin.vjp(lin.r),
            "D": problem.parameterization.difference_operator()}
for name, cfg in cases:
    problem = build_problem(name, cfg)
    bad = {k: t.dtype for k, t in products(problem).items() if t.dtype != torch.float64}
    assert not bad, (name, cfg, bad)
    problem.metrics(problem.theta0)
for name, cfg in [("spring1d", {"n": 8}), ("spring1d", {"n": 8, "backend": "cg"}),
                  ("poisson2d", {"N": 6}), ("membrane2d", {"nx": 4, "ny": 2, "model": "linear"}),
                  ("membrane2d", {"nx": 4, "ny": 2, "newton_atol": 1e-4})]:
    problem = build_problem(name, {**cfg, "dtype": "float32"})
    bad = {k: t.dtype for k, t in products(problem).items() if t.dtype != torch.float32}
    assert not bad, (name, cfg, bad)
print("ok")
"""


def test_problems_never_use_the_default_dtype():
    """Default dtype float32 (torch's own): import torchfit leaves it; every problem and its
    J v, J^T w are float64; dtype=float32 problems are float32 throughout."""
    env_python = [sys.executable, "-c", DTYPE_SCRIPT]
    done = subprocess.run(env_python, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-3000:]


def test_float32_nonlinear_sheet_needs_a_float32_newton_tolerance():
    message = one_line_error("membrane2d", {"dtype": "float32"})
    assert message.startswith("problem.newton_atol=1e-13: is below what float32 reaches")
