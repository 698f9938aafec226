"""``problem.dynamic=true`` on spring1d and membrane2d: construction, settings, recovery,
derivatives, the run directory's pictures and TensorBoard tags."""
from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from omegaconf import OmegaConf

import torchfit
from torchfit.problems import (Membrane2DConfig, ProblemConfigError, Spring1DConfig,
                               build_problem)
from torchfit.problems.dynamic import DynamicSettings
from torchfit.problems.membrane2d import DynamicMembrane2D, Membrane2D
from torchfit.problems.spring1d import DynamicSpring1D, Spring1D

from helpers.fit_app import run_fit_app

#: a short chain: every dynamic feature, seconds to fit
SMALL_CHAIN = {"dynamic": True, "n": 12, "duration": 2.0, "frames": 20, "dt": 0.02}
#: a small sheet with the IPAM letters barely resolved: derivatives and outputs only
SMALL_SHEET = {"dynamic": True, "nx": 12, "ny": 3, "duration": 0.4, "frames": 4, "dt": 0.05,
               "motion_times": [0.0, 0.2], "motion_dx": [0.0, 0.1], "motion_dy": [0.0, 0.05],
               "backend": "scipy"}


def test_dynamic_flag_selects_the_dynamic_problem_and_its_contract():
    problem = build_problem("spring1d", SMALL_CHAIN)
    assert isinstance(problem, DynamicSpring1D) and isinstance(problem, Spring1D)
    assert type(build_problem("spring1d", {})) is Spring1D
    assert not problem.scale_free
    n = SMALL_CHAIN["n"]
    assert problem.parameterization.n_params == n + 2
    assert problem.field(problem.theta0).shape == (n,)
    assert problem.simulation_input(problem.theta0).shape == (n + 2,)
    assert problem.x_true.shape == (20, n + 1, 1)
    assert problem.data.numel() == 20 * n
    metrics = problem.metrics(problem.theta0)
    assert metrics["alpha_damping"] == pytest.approx(0.5)          # alpha0
    assert metrics["alpha_damping_err_rel"] == pytest.approx(0.5)  # truth 1.0
    assert metrics["beta_damping_err_rel"] == pytest.approx(1.0)   # 2e-3 against 1e-3
    truth = problem.true_theta()
    assert problem.metrics(truth)["k_err_rel"] == pytest.approx(0.0, abs=1e-14)
    assert problem.metrics(truth)["misfit"] == pytest.approx(0.0, abs=1e-10)
    described = problem.describe()
    assert described["integrator"] == "implicit" and described["steps"] == 100


def test_each_class_refuses_the_other_value_of_the_dynamic_flag():
    with pytest.raises(ProblemConfigError, match="problem.dynamic=True: Spring1D is the static"):
        Spring1D(dynamic=True)
    with pytest.raises(ProblemConfigError, match="DynamicSpring1D is the dynamic problem"):
        DynamicSpring1D(n=4)
    assert type(build_problem("membrane2d", {**SMALL_SHEET, "dynamic": False})) is Membrane2D


def test_one_dataclass_holds_the_dynamic_settings_of_both_problems():
    shared = {f.name for f in dataclasses.fields(DynamicSettings)}
    assert {"dynamic", "integrator", "scheme", "dt", "output_times", "checkpoint_every"} <= shared
    for config in (Spring1DConfig, Membrane2DConfig):
        assert issubclass(config, DynamicSettings)
        assert shared <= set(OmegaConf.structured(config))      # problem.dt, problem.scheme, ...
    assert Spring1DConfig().dt == DynamicSettings().dt == 0.01
    assert Membrane2DConfig().dt == 0.02                        # the sheet's own default


def test_the_chain_falls_oscillates_and_settles():
    problem = build_problem("spring1d", {**SMALL_CHAIN, "duration": 8.0, "frames": 80,
                                         "dt": 0.04})
    end = problem.x_true[:, -1, 0]
    velocity = (end[1:] - end[:-1]).abs()
    assert float(end.max()) > float(end[-1]) * 1.05             # overshoot, then back
    assert float(velocity[-10:].max()) < 0.05 * float(velocity.max())   # settled


@pytest.mark.parametrize("integrator", ["implicit",
                                        pytest.param("torchdiffeq", marks=pytest.mark.slow)])
def test_spring1d_dynamic_recovers_stiffness_and_damping(integrator):
    # torchdiffeq's dense Jacobian is 14 forward-sensitivity columns through rk4 (slow)
    settings = {**SMALL_CHAIN, "integrator": integrator}
    if integrator == "torchdiffeq":
        settings.update(n=6, duration=1.0, frames=10, ode_method="rk4", dt=0.01)
    problem = build_problem("spring1d", settings)
    result = torchfit.fit(problem, {"name": "gauss_newton", "max_iter": 15},
                          options=torchfit.FitOptions(progress=False))
    metrics = result.metrics
    assert metrics["k_err_rel"] < 1e-6, metrics           # raw: the scale is observable
    assert metrics["alpha_damping_err_rel"] < 1e-6, metrics
    assert metrics["beta_damping_err_rel"] < 1e-5, metrics


@pytest.mark.slow
def test_spring1d_dynamic_canonical_dense_noise_free_acceptance():
    """The issue's figure: n = 64, 6 s, 60 output times, BDF2 dt = 0.01; raw k_err_rel and
    both damping coefficients to 1e-4 (measured: 3e-14, 2e-14, 3e-12 in 9 GN iterations)."""
    problem = build_problem("spring1d", {"dynamic": True})
    result = torchfit.fit(problem, "gauss_newton", options=torchfit.FitOptions(progress=False))
    assert result.metrics["k_err_rel"] < 1e-4
    assert result.metrics["alpha_damping_err_rel"] < 1e-4
    assert result.metrics["beta_damping_err_rel"] < 1e-4


@pytest.mark.parametrize("integrator", ["implicit",
                                        pytest.param("torchdiffeq", marks=pytest.mark.slow)])
def test_membrane2d_dynamic_derivatives(integrator):
    # torchdiffeq: rk4 (the Taylor test of its exact discrete derivative; the continuous
    # adjoint meets J v to the discretisation error, 1e-10 is tests/physics' dopri5 check)
    problem = build_problem("membrane2d", {**SMALL_SHEET, "integrator": integrator,
                                           "ode_method": "rk4", "dt": 0.004
                                           if integrator == "torchdiffeq" else 0.05})
    assert isinstance(problem, DynamicMembrane2D) and not problem.scale_free
    dot_tol = 1e-10 if integrator == "implicit" else 1e-5
    report = torchfit.verify(problem, at="truth", perturbation=0.1, dot_tol=dot_tol)
    assert abs(report.taylor.rate - 2.0) <= 0.05, report.format()
    assert report.dot.rel_error <= dot_tol, report.format()


def test_dynamic_run_directory_pictures_and_tensorboard(tmp_path):
    problem = build_problem("membrane2d", {**SMALL_SHEET, "noise": 1e-4})
    result = torchfit.fit(problem, {"name": "levenberg_marquardt", "max_iter": 2},
                          run_dir=tmp_path / "run",
                          options=torchfit.FitOptions(progress=False, snapshot_iterations=(1,)))
    names = {f.name for f in result.files}
    assert {"time_errors.png", "frames_strip.png", "field.png", "error_curves.png",
            "frames.npz", "snapshots.png"} <= names
    saved = json.loads((tmp_path / "run" / "result.json").read_text())
    for key in ("alpha_damping", "beta_damping", "alpha_damping_err_rel", "beta_damping_err_rel",
                "k_err_rel"):
        assert key in saved and key in saved["history"][-1]
    assert saved["problem"]["dynamic"] is True
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    events = EventAccumulator(str(tmp_path / "run" / "tb"), size_guidance={"tensors": 0,
                                                                           "images": 0})
    events.Reload()
    tags = events.Tags()
    assert {"metrics/alpha_damping", "metrics/beta_damping_err_rel", "time/u_err_inf",
            "time/u_err_inf_initial"} <= set(tags["tensors"])
    assert len(events.Tensors("time/u_err_inf")) == problem.n_frames   # step = output time
    assert {"motion/time_errors", "motion/frames_strip"} <= set(tags["images"])


def test_dynamic_settings_are_checked_one_line_each():
    bad = {
        "density": (0.0, "problem.density=0.0"),
        "alpha": (-0.1, "negative damping coefficient"),
        "output_times": ([0.1, 0.3, 0.2], "must increase strictly"),
        "dt": (0.0, "problem.dt=0.0"),
        "ode_trial_factor": (-1.0, "problem.ode_trial_factor=-1.0"),
    }
    for key, (value, needle) in bad.items():
        overrides = {**SMALL_CHAIN, key: value}
        if key == "alpha":
            overrides["transform"] = "identity"
        with pytest.raises(ProblemConfigError) as info:
            build_problem("spring1d", overrides)
        assert needle in str(info.value) and "\n" not in str(info.value), str(info.value)
    with pytest.raises(ProblemConfigError, match="must be > 0 with problem.transform=exp"):
        build_problem("spring1d", {**SMALL_CHAIN, "beta": 0.0})
    with pytest.raises(ProblemConfigError, match="integrator choice"):
        build_problem("spring1d", {**SMALL_CHAIN, "integrator": "verlet"})


def test_a_true_material_or_start_the_integrator_cannot_step_is_refused_naming_it(tmp_path):
    """A synthetic target whose true material the step cannot take (one Newton iteration per
    step; alpha = 1e12 no longer serves: its steps converge to their round-off floor) is a
    ProblemConfigError naming the true-material settings; a
    start with unphysical damping (alpha0 = 1e12, far past critical damping at the sheet's
    lowest mode) is refused by the fit app in one line naming the setting, the bound and
    the damping ratio it gives, exit 2, nothing written."""
    sheet = {"dynamic": True, "nx": 16, "ny": 4, "duration": 0.2}
    with pytest.raises(ProblemConfigError) as info:
        build_problem("membrane2d", {**sheet, "newton_max_iter": 1})
    text = str(info.value)
    assert text.startswith("problem.E_background, problem.E_ink, problem.alpha, problem.beta: "
                           "the synthetic target cannot be simulated") and "\n" not in text
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=membrane2d", *(f"problem.{k}={v}" for k, v in sheet.items()),
                       "problem.alpha0=1e12", "solver.max_iter=1", timeout=600)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
    assert lines[0].startswith("error: problem.alpha0=1000000000000.0: gives the damping "
                               "ratio zeta = alpha / (2 w1) = ") and \
        "alpha must be at most 2 ZETA_MAX w1 = " in lines[0], lines[0]
    assert not run.exists()


def test_damping_band_bounds_and_refusal_of_absurd_starts():
    """The chain's band: w1 of the held chain at k0 (shift-invert against the dense
    generalised eigenproblem), w_frames = pi / (output interval); the bounds alpha_max = 2
    w1, beta_max = 2 / max(w1, w_frames) give zeta = 1 by each term alone at the band's
    ends; a start past either is refused in one line; the ratios are metrics."""
    import math

    import numpy as np
    import scipy.linalg

    from torchfit.problems.damping import ZETA_MAX, DampingBand, damping_ratio

    problem = build_problem("spring1d", SMALL_CHAIN)
    band = problem.time.band
    system = problem.system
    free = system.free_dofs.numpy()
    k0 = torch.full((system.n_field,), float(problem.cfg.k0), dtype=torch.float64)
    stiffness = system.elastic.tangent_pattern.to_scipy(
        system.elastic.tangent_pattern.assemble(system.rest_stiffness_contributions(k0)))
    dense = stiffness.toarray()[np.ix_(free, free)]
    lowest = scipy.linalg.eigh(dense, np.diag(system.mass.numpy()[free]), eigvals_only=True)[0]
    assert band.w1 == pytest.approx(math.sqrt(lowest), rel=1e-9)
    assert band.w_frames == pytest.approx(math.pi / 0.1, rel=1e-12)     # 20 frames in 2 s
    assert ZETA_MAX == 1.0
    assert band.alpha_max == pytest.approx(2 * band.w1, rel=1e-12)
    assert band.beta_max == pytest.approx(2 / max(band.w1, band.w_frames), rel=1e-12)
    assert damping_ratio(band.alpha_max, 0.0, band.w1) == pytest.approx(1.0)
    assert damping_ratio(0.0, band.beta_max, band.w_high) == pytest.approx(1.0)
    metrics = problem.metrics(problem.theta0)
    assert metrics["damping_ratio_w1"] == pytest.approx(
        0.5 / (2 * band.w1) + 2e-3 * band.w1 / 2, rel=1e-12)
    # a body stiffer than the frames show: beta bounded at w1, not at the frame rate
    assert DampingBand(100.0, 10.0).beta_max == pytest.approx(0.02)
    assert DampingBand(None, 10.0).alpha_max == math.inf
    for key, value, needle in (("beta0", 1e12, "beta must be at most 2 ZETA_MAX / w"),
                               ("alpha0", 1e3, "alpha must be at most 2 ZETA_MAX w1")):
        with pytest.raises(ProblemConfigError) as info:
            build_problem("spring1d", {**SMALL_CHAIN, key: value})
        text = str(info.value)
        assert text.startswith(f"problem.{key}={value}: gives the damping ratio zeta = ") \
            and needle in text and "\n" not in text, text


def test_identity_transform_negative_damping_at_a_trial_point_is_a_simulation_error():
    problem = build_problem("spring1d", {**SMALL_CHAIN, "transform": "identity"})
    theta = problem.theta0.clone()
    theta[-1] = -1e-3
    with pytest.raises(torchfit.errors.SimulationError, match="beta = -0.001 s is negative"):
        problem.residual().value(theta)


def test_verify_app_on_the_dynamic_presets(tmp_path):
    """experiments/verify.py on spring1d_dynamic (small): exit 0 and verify.json's figures."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    done = subprocess.run([sys.executable, "experiments/verify.py", "problem=spring1d_dynamic",
                           "problem.n=6", "problem.duration=0.6", "problem.frames=6",
                           "problem.dt=0.02", f"hydra.run.dir={tmp_path}"], cwd=repo, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads((tmp_path / "verify.json").read_text())
    assert abs(report["taylor"]["rate"] - 2.0) <= 0.05
    assert report["dot_product"]["rel_error"] <= 1e-10


#: a soft three-spring chain for torchdiffeq checks (dopri5 takes few steps)
TINY_ODE_CHAIN = {"dynamic": True, "integrator": "torchdiffeq", "n": 3, "duration": 0.5,
                  "frames": 5, "k_background": 10.0, "k0": 10.0, "load_times": [0.1, 0.3]}


def test_dot_bound_follows_the_ode_tolerance_and_stays_exact_for_implicit():
    from torchfit.verification import DOT_TOL_EXACT, default_dot_tol

    implicit = build_problem("spring1d", SMALL_CHAIN).residual()
    assert implicit.product_consistency is None          # BDF2: the exact discrete adjoint
    assert default_dot_tol(implicit)[0] == DOT_TOL_EXACT == 1e-10
    ode = build_problem("spring1d", {**TINY_ODE_CHAIN, "ode_rtol": 1e-9}).residual()
    assert ode.product_consistency == 1e-9
    tol, why = default_dot_tol(ode)
    assert tol == pytest.approx(1e-6) and "ODE tolerance" in why


def test_the_ode_dot_bound_catches_a_scaled_or_permuted_adjoint():
    """The bound from the tolerance (1e-5 at rtol 1e-8) still fails an adjoint 0.1 % off
    or with its entries permuted, while the true continuous adjoint passes it."""
    from torchfit.verification import default_dot_tol, dot_product_test, random_direction

    problem = build_problem("spring1d", TINY_ODE_CHAIN)
    residual = problem.residual()
    tol, _ = default_dot_tol(residual)
    lin = residual.linearize(problem.theta0 + 0.05)
    generator = torch.Generator().manual_seed(0)
    v = random_direction(lin.theta.numel(), generator, lin.theta)
    w = random_direction(lin.r.numel(), generator, lin.r)
    jv, jtw = lin.jvp(v), lin.vjp(w)

    class Wrong:
        r = lin.r

        def __init__(self, vjp):
            self.vjp = vjp

        def jvp(self, u):
            return jv

    assert dot_product_test(Wrong(lambda u: jtw), v, w).rel_error <= tol
    for wrong in (lambda u: 1.001 * jtw, lambda u: jtw.flip(0)):
        assert dot_product_test(Wrong(wrong), v, w).rel_error > tol


@pytest.mark.slow
def test_verify_app_on_spring1d_torchdiffeq_passes_with_the_tolerance_bound(tmp_path):
    """experiments/verify.py problem=spring1d problem.dynamic=true problem.integrator=
    torchdiffeq: exit 0; the dot test's bound is 1000 ode_rtol and verify.json says why
    (it failed against the fixed 1e-10: the continuous adjoint and the forward
    sensitivities agree to a multiple of rtol, measured 9e-8 here)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    done = subprocess.run([sys.executable, "experiments/verify.py", "problem=spring1d",
                           "problem.dynamic=true", "problem.integrator=torchdiffeq",
                           "problem.n=3", "problem.duration=0.5", "problem.frames=5",
                           "problem.k_background=10", "problem.k0=10",
                           "problem.load_times=[0.1,0.3]", "threads=1",
                           f"hydra.run.dir={tmp_path}"], cwd=repo, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    report = json.loads((tmp_path / "verify.json").read_text())
    assert report["passed"] and abs(report["taylor"]["rate"] - 2.0) <= 0.05
    assert report["tolerances"]["dot_tol"] == pytest.approx(1e-5)
    assert "ODE tolerance" in report["tolerances"]["dot_tol_basis"]
    assert report["dot_product"]["rel_error"] <= 1e-5
    assert report["fd_passed"]
