"""The posterior spread of a fit (torchfit.run.uncertainty): the covariance against the
closed form of linear least squares (full rank, a nullspace, a gauge, a bound), and the
coverage of the truth by the two-sigma band on a noisy spring chain."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from torchfit import build_problem, fit
from torchfit.run import FitOptions
from torchfit.run.uncertainty import SIGMAS, Uncertainty, covariance_factor, held_parameters

QUIET = FitOptions(progress=False, threads=1)


def random_jacobian(m: int = 40, n: int = 5, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(m, n, generator=generator, dtype=torch.float64)


def test_the_covariance_of_linear_least_squares_is_sigma2_inverse_jtj():
    J = random_jacobian()
    L, null, sigma, rank = covariance_factor(J, sigma=0.3)
    closed = 0.09 * torch.linalg.inv(J.T @ J)
    assert torch.allclose(L @ L.T, closed, rtol=1e-10, atol=0)
    assert rank == 5 and sigma == 0.3 and float(null.max()) < 1e-12


def test_sigma_from_the_residual_is_its_norm_over_the_degrees_of_freedom():
    J = random_jacobian(m=30, n=4)
    residual = torch.linspace(-1.0, 1.0, 30, dtype=torch.float64)
    L, _, sigma, _ = covariance_factor(J, residual=residual)
    assert sigma == pytest.approx(float(residual.norm()) / math.sqrt(30 - 4), rel=1e-12)
    assert torch.allclose(L @ L.T, sigma ** 2 * torch.linalg.inv(J.T @ J), rtol=1e-10)


def test_a_parameter_the_data_never_see_is_undetermined_and_the_rest_exact():
    J = random_jacobian()
    J[:, 2] = 0.0                                   # parameter 2: no effect on the data
    L, null, _, rank = covariance_factor(J, sigma=1.0)
    assert rank == 4
    assert float(null[2]) == pytest.approx(1.0) and float(null[[0, 1, 3, 4]].max()) < 1e-12
    keep = [0, 1, 3, 4]
    closed = torch.linalg.inv(J[:, keep].T @ J[:, keep])
    assert torch.allclose((L @ L.T)[keep][:, keep], closed, rtol=1e-10)
    # two parameters with one column between them: the difference is never seen, so both
    J2 = random_jacobian()
    J2[:, 1] = J2[:, 0]
    _, null2, _, _ = covariance_factor(J2, sigma=1.0)
    assert float(null2[0]) == pytest.approx(0.5) and float(null2[1]) == pytest.approx(0.5)


def test_a_gauge_is_projected_out_the_covariance_is_the_pseudo_inverse():
    n = 5
    A = random_jacobian(n=n)
    ones = torch.ones(n, dtype=torch.float64) / math.sqrt(n)
    J = A - (A @ ones)[:, None] * ones[None, :]      # the data never fix the mean (the scale)
    L, null, _, rank = covariance_factor(J, sigma=0.5, gauge=ones)
    assert rank == n - 1 and float(null.max()) < 1e-12     # the gauge is not a nullspace
    closed = 0.25 * torch.linalg.pinv(J.T @ J, hermitian=True)
    assert torch.allclose(L @ L.T, closed, rtol=1e-8, atol=1e-12)
    assert float((L.T @ ones).abs().max()) < 1e-12
    # held by an anchor instead (a weighted mean of theta): Cov = P C P^T, P = I - g a^T / a^T g
    anchor = torch.tensor([1.0, 2.0, 0.0, 0.5, 3.0], dtype=torch.float64)
    La, _, _, _ = covariance_factor(J, sigma=0.5, gauge=ones, anchor=anchor)
    P = torch.eye(n, dtype=torch.float64) - ones[:, None] * anchor[None, :] / float(anchor @ ones)
    assert torch.allclose(La @ La.T, P @ closed @ P.T, rtol=1e-8, atol=1e-12)
    assert float((anchor @ La).abs().max()) < 1e-12


def test_a_parameter_on_a_bound_is_held_there():
    J = random_jacobian()
    free = torch.tensor([True, True, False, True, True])
    L, null, _, _ = covariance_factor(J, sigma=1.0, free=free)
    keep = [0, 1, 3, 4]
    assert torch.allclose((L @ L.T)[keep][:, keep],
                          torch.linalg.inv(J[:, keep].T @ J[:, keep]), rtol=1e-10)
    assert float(L[2].abs().max()) == 0.0 and float(null[2]) == 1.0


def test_an_undetermined_parameter_the_data_see_is_marginalised_an_invisible_one_held():
    # parameter 3: a column 1e-3 of the others' and nearly parallel to parameter 0's (the
    # identifiability report's "not determined", but seen); parameter 4: 1e-9 (invisible)
    J = random_jacobian(m=60, n=5, seed=3)
    J[:, 3] = 1e-3 * (J[:, 0] + 0.1 * random_jacobian(m=60, n=1, seed=4)[:, 0])
    J[:, 4] = 1e-9 * J[:, 4]
    free = torch.ones(5, dtype=torch.bool)
    not_determined = torch.tensor([False, False, False, True, True])
    held = held_parameters(J, free, not_determined)
    assert held.tolist() == [False, False, False, False, True]
    L, _, _, rank = covariance_factor(J, sigma=1.0, free=free & ~held)
    assert rank == 4 and float(L[4].abs().max()) == 0.0
    seen = [0, 1, 2, 3]
    marginal = torch.linalg.inv(J[:, seen].T @ J[:, seen])
    assert torch.allclose((L @ L.T)[:4, :4], marginal, rtol=1e-8)
    # held instead (conditional on parameter 3), parameter 0's variance would be 100x too
    # small: with parameter 3 fitted too, the estimate of 0 scatters by the marginal one
    conditional = torch.linalg.inv(J[:, :3].T @ J[:, :3])
    assert float(marginal[0, 0]) > 50 * float(conditional[0, 0])
    generator = torch.Generator().manual_seed(5)
    noise = torch.randn(3000, 60, generator=generator, dtype=torch.float64)
    estimates = torch.linalg.lstsq(J[:, seen], noise.T).solution.T     # (draws, 4)
    assert float(estimates[:, 0].std()) == pytest.approx(float(marginal[0, 0].sqrt()), rel=0.05)
    # nothing determined, nothing free: nothing held
    assert not held_parameters(J, torch.zeros(5, dtype=torch.bool), not_determined).any()


def test_monte_carlo_spread_of_linear_least_squares_matches_the_band():
    # the estimate's spread over many noise draws is the covariance (the definition)
    J = random_jacobian(m=60, n=3, seed=1)
    L, _, _, _ = covariance_factor(J, sigma=0.2)
    generator = torch.Generator().manual_seed(2)
    noise = 0.2 * torch.randn(4000, 60, generator=generator, dtype=torch.float64)
    estimates = torch.linalg.lstsq(J, noise.T).solution.T          # (draws, 3)
    empirical = estimates.T @ estimates / len(estimates)
    assert torch.allclose(empirical, L @ L.T, rtol=0.1, atol=0.1 * float((L @ L.T).abs().max()))


def spring_fit(seed: int, known_noise: bool):
    problem = build_problem("spring1d", {"noise": 1e-3, "seed": seed})
    if not known_noise:
        problem.noise_level = None               # sigma from the residual instead
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 50}, options=QUIET)
    return problem, result


@pytest.mark.parametrize("seed,known_noise", [(0, True), (1, False)])
def test_the_two_sigma_band_covers_the_true_stiffness_of_a_noisy_chain(seed, known_noise):
    problem, result = spring_fit(seed, known_noise)
    report = result.uncertainty
    assert report.computed and report.rank == problem.parameterization.n_params == 64
    assert report.sigma_source == ("noise level" if known_noise else "residual")
    assert report.sigma == pytest.approx(1e-3, rel=0.2)
    determined = result.identifiability.parameter_determined
    coverage, count = report.coverage(result.theta, problem.true_theta(), determined)
    assert count == 64 and coverage >= 0.9
    # a sigma ten times too small would not cover the truth
    narrow = dataclasses.replace(report, sd=report.sd / 10)
    assert narrow.coverage(result.theta, problem.true_theta(), determined)[0] < 0.5
    # the band in the parameters' meaning: exp(2 sd) for a log-stiffness
    assert report.factor(report.sd) == pytest.approx(np.exp(SIGMAS * report.sd))


def test_the_run_reports_the_uncertainty_in_result_json_and_its_summary(tmp_path):
    problem = build_problem("spring1d", {"noise": 1e-3, "n": 16})
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 20}, options=QUIET,
                 run_dir=tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "result.json").read_text())["uncertainty"]
    assert saved["computed"] and saved["parameters_with_sd"] == 16
    assert saved["sd_median"] == pytest.approx(float(np.median(result.uncertainty.sd)))
    per_parameter = json.loads((tmp_path / "run" / "uncertainty.json").read_text())
    assert per_parameter["parameters"]["sd"] == pytest.approx(result.uncertainty.sd.tolist())
    assert "2-sigma band x" in result.summary()


def test_a_matrix_free_fit_of_many_parameters_says_not_computed():
    report = Uncertainty(False, reason="3969 parameters, matrix-free")
    assert report.summary() == {"computed": False, "reason": "3969 parameters, matrix-free"}
    assert report.text() == "uncertainty not computed (3969 parameters, matrix-free)"


def test_a_fit_stopped_short_of_its_minimum_says_the_band_does_not_hold():
    problem = build_problem("spring1d", {"noise": 1e-3})
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 1}, options=QUIET)
    report = result.uncertainty
    assert report.short_of_minimum > 10
    # the step that remains is the linearised minimum's: one Gauss-Newton step closer
    moved = np.abs(report.step) > report.sd
    assert int(moved.sum()) == report.short_of_minimum
    assert "stopped short of its minimum" in result.summary()
