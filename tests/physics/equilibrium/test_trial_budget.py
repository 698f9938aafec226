"""The trial budget of a solve warm-started from the anchor: Newton stopped after the
counted iterations, the failure a SimulationError (a rejected trial), and the first-order
predictor start."""
import dataclasses

import pytest
import torch

from torchfit.errors import SimulationError
from torchfit.linalg import counting
from torchfit.physics.equilibrium.newton import NewtonOptions, TrialBudgetExceeded

from helpers.equilibrium_models import make_hardening


def anchored(options: NewtonOptions):
    """``(model, eq, fixed, k)``: a hardening chain solved at ``k`` and at ``1.01 k`` (a
    warm start), the latter the anchor (few Newton iterations)."""
    model, eq, fixed = make_hardening()
    eq.newton = options
    k = torch.linspace(1.0, 2.0, 12, dtype=torch.float64)
    eq.solution(k, fixed, None)
    near = eq.solution(1.01 * k, fixed, None)
    eq.cache.anchor(near)
    return model, eq, fixed, near


def test_budget_is_factor_times_the_anchors_largest_count_with_a_floor():
    options = NewtonOptions(trial_factor=2.5, trial_min_iter=3)
    assert options.trial_budget([1, 4, 2]) == 18         # ceil(2.5 * 7)
    assert options.trial_budget([0, 1, 1]) == 9          # 3 per frame
    assert NewtonOptions(trial_factor=0).trial_budget([5]) is None       # 0: no budget


def test_trial_over_budget_stops_newton_after_the_counted_iterations():
    base = NewtonOptions(rtol=1e-13, atol=1e-14, warm_max_iter=50)
    _, eq, fixed, near = anchored(dataclasses.replace(base, trial_factor=1.0, trial_min_iter=2))
    budget = eq.newton.trial_budget(near.newton_iterations)
    assert budget == max(2 * 3, sum(near.newton_iterations))
    far = 0.02 * near.params                  # a much softer chain: a long Newton walk
    with counting() as count, pytest.raises(TrialBudgetExceeded) as failed:
        eq.solution(far, fixed, None)
    assert isinstance(failed.value, SimulationError) and failed.value.budget == budget
    # at most `budget` frame-iterations (one factorisation each), no cold start
    assert budget - fixed.shape[0] < count.factorizations <= budget
    # without a budget the same point converges, warm, in more iterations than that
    _, eq_free, fixed, _ = anchored(base)
    sol = eq_free.solution(far, fixed, None)
    assert sol.warm_started and sum(sol.newton_iterations) > budget


def test_trial_within_budget_is_the_same_solve_as_without():
    base = NewtonOptions(rtol=1e-13, atol=1e-14)
    _, eq, fixed, near = anchored(dataclasses.replace(base, trial_factor=3.0))
    _, eq_ref, _, _ = anchored(base)
    step = 1.02 * near.params
    a, b = eq.solution(step, fixed, None), eq_ref.solution(step, fixed, None)
    assert torch.equal(a.x, b.x) and a.newton_iterations == b.newton_iterations


def test_no_budget_without_an_anchor():
    model, eq, fixed = make_hardening()
    eq.newton = NewtonOptions(rtol=1e-13, atol=1e-14, trial_factor=1.0, trial_min_iter=1)
    k = torch.linspace(1.0, 2.0, 12, dtype=torch.float64)
    sol = eq.solution(k, fixed, None)                 # cold: no anchor, no budget
    assert max(sol.newton_iterations) > 1


def twisted_box(predictor: bool):
    """``(eq, fixed_values, E)``: a corotated box, its top turned by 1.2 rad about z, solved
    at a random modulus field that is then the anchor."""
    from helpers.tetbox import clamped_box
    model, qs, bottom, top = clamped_box((2, 2, 3), (0.5, 0.5, 1.0), "corotated")
    X = model.rest.points
    c, s = torch.cos(torch.tensor(1.2, dtype=X.dtype)), torch.sin(torch.tensor(1.2, dtype=X.dtype))
    R = torch.stack([torch.stack([c, -s, 0 * c]), torch.stack([s, c, 0 * c]),
                     torch.tensor([0.0, 0.0, 1.0], dtype=X.dtype)])
    centre = torch.tensor([0.25, 0.25, 0.0], dtype=X.dtype)
    moved = (X[top] - centre) @ R.T + centre
    fixed = qs.dirichlet_values(torch.cat([X[bottom], moved])[None])
    eq = qs.equilibrium
    eq.newton = dataclasses.replace(eq.newton, trial_predictor=predictor)
    E = torch.exp(0.3 * torch.randn(model.n_cells, dtype=X.dtype,
                                    generator=torch.Generator().manual_seed(3)))
    eq.cache.anchor(eq.solution(E, fixed, None))
    return eq, fixed, E


def test_predictor_start_is_closer_and_ends_at_the_same_solution():
    plain_eq, fixed, E = twisted_box(False)
    trial = E * torch.exp(0.25 * torch.sin(torch.arange(E.numel(), dtype=E.dtype)))
    plain = plain_eq.solution(trial, fixed, None)
    predicted_eq, _, _ = twisted_box(True)
    with counting() as count:
        predicted = predicted_eq.solution(trial, fixed, None)
    assert predicted.warm_started and plain.warm_started
    assert sum(predicted.newton_iterations) <= sum(plain.newton_iterations)
    # the first-order predictor leaves a second-order residual at the trial parameters
    anchor = plain_eq.cache.lookup(E, fixed)
    start = predicted_eq.predicted_start(predicted_eq.cache.lookup(E, fixed), trial)
    norm = lambda x: float(torch.linalg.vector_norm(plain_eq.reduction.free_residual(x, trial)))
    assert norm(start) < 0.2 * norm(anchor.x)          # 0.11 measured
    # Newton's solves and the predictor's one; Newton's factorisations and the one at x*
    newton = sum(predicted.newton_iterations)
    assert (count.solves, count.factorizations) == (newton + 1, newton + 1)
    assert torch.allclose(predicted.x, plain.x, rtol=0, atol=1e-9)
