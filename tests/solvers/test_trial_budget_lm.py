"""Levenberg-Marquardt with a trial budget on the equilibrium: a trial whose Newton runs over
budget is a rejected step (damping raised, theta unchanged), cheaper than the long walk."""
import dataclasses

import torch

from torchfit.linalg import counting
from torchfit.physics.equilibrium.newton import NewtonOptions, TrialBudgetExceeded
from torchfit.solvers import ResidualFunction
from torchfit.solvers.levenberg_marquardt import LevenbergMarquardt, LevenbergMarquardtConfig

from helpers.equilibrium_models import make_hardening


def fit(options: NewtonOptions):
    """LM on the log-stiffness of a hardening chain from a start 30x too stiff: ``(result,
    budget failures, factorisations)``."""
    model, eq, fixed = make_hardening()
    eq.newton = options
    k_true = torch.linspace(1.0, 2.0, 12, dtype=torch.float64)
    with torch.no_grad(), eq.independent():
        data = eq(k_true, fixed).reshape(-1).clone()
    eq.clear_cache()
    failures = []

    def forward(theta):
        try:
            return eq(torch.exp(theta), fixed).reshape(-1)
        except TrialBudgetExceeded as err:
            failures.append(err.budget)
            raise

    residual = ResidualFunction(forward, data)
    config = LevenbergMarquardtConfig(max_iter=8, damping_init=1e-4, dense_jacobian_max_params=0)
    with counting() as count:
        result = LevenbergMarquardt(config).solve(residual, torch.log(k_true) + 3.4)
    return result, failures, count.factorizations


def test_trial_over_budget_is_rejected_and_damping_rises():
    base = NewtonOptions(rtol=1e-13, atol=1e-14, warm_max_iter=50)
    result, failures, _ = fit(dataclasses.replace(base, trial_factor=1.0, trial_min_iter=2))
    assert failures, "no trial ran over its budget"
    records = result.history
    rejected = [i for i, rec in enumerate(records) if not rec.accepted]
    assert len(rejected) >= len(failures)
    for i in rejected:
        assert torch.equal(records[i].theta, records[i - 1].theta)      # theta unchanged
        # a failed trial costs at most its budget of factorisations
        assert records[i].factorizations - records[i - 1].factorizations <= max(failures)
        if i + 1 < len(records):
            assert records[i + 1].damping > records[i].damping            # damping raised
    # without a budget the same rejected trial walks further before it is rejected
    free, no_failures, _ = fit(base)
    first = rejected[0]
    assert not no_failures and not free.history[first].accepted
    assert free.history[first].factorizations - free.history[first - 1].factorizations \
        > records[first].factorizations - records[first - 1].factorizations
