"""The problem template (torchfit.problems.base): the template constructor, metric_names, the
opt-in protocols, explicit dtypes."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import pytest
import torch

from helpers.fit_app import REPO
from helpers.small_problems import SMALL
from torchfit.problems import (PROBLEMS, BodyProblem, FieldImageProblem, FramedProblem,
                               InverseProblem, MeshProblem, ProblemConfig, ProblemConfigError,
                               Spring1D, build_problem)


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


# -- dtype ----------------------------------------------------------------------------------
DTYPE_SCRIPT = r"""
import torch
assert torch.get_default_dtype() == torch.float32
import torchfit, torchfit.problems, torchfit.solvers, torchfit.verification
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
