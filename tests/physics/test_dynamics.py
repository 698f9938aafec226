"""Elastodynamics and its two integrators (torchfit.physics.dynamics).

Derivatives (Taylor rate 2 +- 0.05, dot product to 1e-10) for the implicit integrator
(backward Euler and BDF2, every state kept and checkpointed) and for torchdiffeq (dopri5
at a tight tolerance, rk4), on a small hanging chain and a small corotated sheet; the
observed convergence orders as the step shrinks (1 and 2) towards the same trajectory as
torchdiffeq; the counted cost; each bad input as a one-line error.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchfit.errors import ConfigurationError, SimulationError
from torchfit.linalg.counters import counting
from torchfit.mesh import rectangle_triangles
from torchfit.physics import SpringChain1D
from torchfit.physics.dynamics import (DynamicsInputError, DynamicSystem, KeyedMotion,
                                       NegativeDampingError, NonFiniteStateError,
                                       UnstableStepError, check_output_times, make_integrator,
                                       smootherstep)
from torchfit.physics.elasticity import SimplicialElasticity
from torchfit.residual import ResidualFunction
from torchfit.verification import dot_product_test, random_direction, taylor_test

DT = torch.float64


@pytest.fixture(autouse=True)
def one_thread():
    """Step-by-step integrations are many small kernels: one torch thread (as the dynamic
    presets run) avoids the intra-op pool's overhead on a shared machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def chain_system(n: int = 6, stiffness: float = 30.0, loads=None, x0=None) -> tuple[DynamicSystem, torch.Tensor]:
    """A hanging chain of ``n`` springs released at rest length, with an eased end load."""
    nodes = torch.arange(n + 1)
    springs = SpringChain1D(torch.stack([nodes[:-1], nodes[1:]], 1),
                            torch.full((n,), 1.0 / n, dtype=DT), torch.zeros(1, n + 1, dtype=DT))
    end = torch.zeros(2, n + 1, dtype=DT)
    end[1, n] = 1.5
    if loads is None:
        loads = KeyedMotion(torch.tensor([0.1, 0.3], dtype=DT), end)
    rest = nodes.to(DT) / n
    system = DynamicSystem(springs, n, torch.full((n + 1,), 1.0 / n, dtype=DT), torch.tensor([0]),
                           KeyedMotion(torch.zeros(1, dtype=DT), torch.zeros(1, 1, dtype=DT)),
                           loads, torch.full((n + 1,), 9.81, dtype=DT),
                           rest if x0 is None else x0, vertex_dim=1)
    k = stiffness * (1.0 + 0.5 * torch.sin(torch.arange(n, dtype=DT)))
    return system, torch.cat([k, torch.tensor([0.8, 2e-3], dtype=DT)])


def sheet_system(material: str = "corotated") -> tuple[DynamicSystem, torch.Tensor]:
    """A 6 x 2 sheet, left edge held, right edge moved by a keyed translation that stops."""
    mesh = rectangle_triangles(6, 2, 1.0, 0.3)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 material, nu=0.3)
    left, right = mesh.boundary_vertices("left"), mesh.boundary_vertices("right")
    dirichlet = np.sort(np.concatenate([left, right]))
    fixed = torch.as_tensor((dirichlet[:, None] * 2 + np.arange(2)).reshape(-1))
    rest = model.rest.points.to(DT)
    moving = torch.as_tensor(np.isin(dirichlet, right), dtype=DT)[:, None]
    base = rest[torch.as_tensor(dirichlet)]
    shift = torch.tensor([[0.0, 0.0], [0.15, 0.1]], dtype=DT)
    keys = base[None] + shift[:, None, :] * moving[None]
    mass = torch.zeros(model.n_vertices, dtype=DT).index_add(
        0, torch.as_tensor(mesh.cells.reshape(-1)),
        (model.rest.volumes.to(DT) / 3.0).repeat_interleave(3)).repeat_interleave(2)
    system = DynamicSystem(model, model.n_cells, mass, fixed,
                           KeyedMotion(torch.tensor([0.0, 0.2], dtype=DT), keys.reshape(2, -1)),
                           None, torch.zeros(model.n_dofs, dtype=DT), rest.reshape(-1),
                           vertex_dim=2)
    E = 2.0 + torch.rand(model.n_cells, generator=torch.Generator().manual_seed(1), dtype=DT)
    return system, torch.cat([E, torch.tensor([0.5, 3e-3], dtype=DT)])


def residual_of(integrator, params: torch.Tensor) -> tuple[ResidualFunction, torch.Tensor]:
    """``theta = log params`` -> every position at the output times, data offset from it."""
    def forward(theta: torch.Tensor) -> torch.Tensor:
        return integrator(torch.exp(theta)).reshape(-1)

    theta = torch.log(params)
    data = forward(theta).detach() + 0.01
    return ResidualFunction(forward, data), theta


def check_derivatives(integrator, params: torch.Tensor, *, taylor_steps: int = 18):
    residual, theta = residual_of(integrator, params)
    generator = torch.Generator().manual_seed(3)
    point = theta + 0.1 * random_direction(theta.numel(), generator, theta)
    lin = residual.linearize(point)
    v = random_direction(theta.numel(), generator, theta)
    w = random_direction(residual.size, generator, theta)
    dot = dot_product_test(lin, v, w)
    taylor = taylor_test(residual, point, v, lin=lin, n_steps=taylor_steps)
    return taylor, dot


@pytest.mark.parametrize("scheme,checkpoint_every", [("bdf2", 1), ("bdf2", 4),
                                                     ("backward_euler", 1)])
def test_implicit_derivatives_on_the_chain(scheme, checkpoint_every):
    system, params = chain_system()
    integrator = make_integrator("implicit", system, torch.linspace(0.05, 0.3, 6), dt=0.01,
                                 scheme=scheme, checkpoint_every=checkpoint_every)
    taylor, dot = check_derivatives(integrator, params)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    assert dot.rel_error <= 1e-10, dot.rel_error


def test_implicit_derivatives_on_the_corotated_sheet():
    system, params = sheet_system()
    integrator = make_integrator("implicit", system, torch.tensor([0.1, 0.2]), dt=0.04,
                                 checkpoint_every=2)
    taylor, dot = check_derivatives(integrator, params)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    assert dot.rel_error <= 1e-10, dot.rel_error


def test_torchdiffeq_derivatives_dopri5_tight_tolerance():
    system, params = chain_system(n=4, stiffness=10.0)
    integrator = make_integrator("torchdiffeq", system, torch.linspace(0.05, 0.2, 4), dt=0.01,
                                 method="dopri5", rtol=1e-13, atol=1e-14)
    taylor, dot = check_derivatives(integrator, params, taylor_steps=14)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    assert dot.rel_error <= 1e-10, dot.rel_error


def test_torchdiffeq_derivatives_rk4_and_the_sheet():
    system, params = sheet_system("linear")
    integrator = make_integrator("torchdiffeq", system, torch.tensor([0.05, 0.1]), dt=0.002,
                                 method="rk4")
    taylor, dot = check_derivatives(integrator, params, taylor_steps=14)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    # the continuous adjoint against the exact derivative of rk4's discrete map
    assert dot.rel_error <= 1e-6, dot.rel_error


def test_jacobian_columns_equal_jvps_for_both_integrators():
    system, params = chain_system(n=4)
    times = torch.tensor([0.1, 0.2])
    V = torch.randn(params.numel(), 3, dtype=DT)
    for kind, kwargs in (("implicit", {}), ("torchdiffeq", {"rtol": 1e-10, "atol": 1e-12})):
        integrator = make_integrator(kind, system, times, dt=0.01, **kwargs)
        J = integrator.jacobian(params, V)
        import torch.autograd.forward_ad as fwAD
        with fwAD.dual_level():
            out = integrator(fwAD.make_dual(params, V[:, 1]))
            tangent = fwAD.unpack_dual(out).tangent
        assert torch.allclose(J[..., 1], tangent, rtol=1e-9, atol=1e-12), kind


def test_step_shrinking_orders_and_the_same_trajectory_as_torchdiffeq():
    system, params = chain_system(n=6)
    times = torch.linspace(0.1, 0.5, 5)
    reference = make_integrator("torchdiffeq", system, times, dt=0.01, rtol=1e-12,
                                atol=1e-13)(params)
    orders = {}
    for scheme in ("backward_euler", "bdf2"):
        errors = []
        for dt in (0.004, 0.002, 0.001):
            x = make_integrator("implicit", system, times, dt=dt, scheme=scheme)(params)
            errors.append(float((x - reference).abs().max()))
        orders[scheme] = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
        if scheme == "bdf2":
            assert errors[-1] < 1e-3 * float(reference.abs().max())
    assert all(0.9 <= q <= 1.1 for q in orders["backward_euler"]), orders
    assert all(1.85 <= q <= 2.15 for q in orders["bdf2"]), orders


def test_cost_is_counted_and_stored_solutions_make_products_solve_only():
    system, params = chain_system(n=6)
    times = torch.linspace(0.05, 0.3, 6)
    integrator = make_integrator("implicit", system, times, dt=0.01)
    steps = integrator.n_steps
    with counting() as forward:
        integrator(params)
    assert forward.factorizations == steps            # linear springs: one per step
    assert forward.solves == steps
    residual, theta = residual_of(integrator, params)
    lin = residual.linearize(theta)
    with counting() as products:
        lin.vjp(lin.r)
        lin.jvp(theta)
    assert products.factorizations == 0               # every step's factor is kept (c = 1)
    assert products.solves == 2 * steps
    checkpointed = make_integrator("implicit", system, times, dt=0.01, checkpoint_every=5)
    assert checkpointed.stored_states < integrator.stored_states == steps + 1
    lin = residual_of(checkpointed, params)[0].linearize(theta)
    with counting() as products:
        lin.vjp(lin.r)
    # every segment recomputed from its checkpoint (one factorisation per step), then one
    # factorisation per step replayed, except the segment's last two (still cached)
    assert products.factorizations == 2 * steps - 2 * len(checkpointed.segments())


def test_keyed_motion_is_c2_and_stops():
    w, dw = smootherstep(torch.tensor([0.0, 0.5, 1.0, 2.0]))
    assert torch.allclose(w, torch.tensor([0.0, 0.5, 1.0, 1.0]))
    assert torch.allclose(dw, torch.tensor([0.0, 1.875, 0.0, 0.0]))
    motion = KeyedMotion(torch.tensor([0.0, 1.0]), torch.tensor([[0.0], [2.0]]))
    t = torch.tensor([0.25, 0.5, 3.0])
    h = 1e-6
    fd = (motion(t + h) - motion(t - h)) / (2 * h)
    assert torch.allclose(motion.velocity(t), fd, atol=1e-8)
    assert float(motion(t)[-1]) == 2.0 and float(motion.velocity(t)[-1]) == 0.0


# -- bad input: one line each ------------------------------------------------------------------
def one_line(error: BaseException) -> str:
    text = str(error)
    assert "\n" not in text and text
    return text


def test_negative_damping_is_a_one_line_simulation_error():
    system, params = chain_system()
    integrator = make_integrator("implicit", system, [0.1], dt=0.01)
    bad = params.clone()
    bad[-2] = -0.1
    with pytest.raises(NegativeDampingError) as info:
        integrator(bad)
    assert isinstance(info.value, SimulationError)
    assert "alpha = -0.1" in one_line(info.value) and "transform=exp" in str(info.value)


def test_output_times_must_increase():
    with pytest.raises(DynamicsInputError) as info:
        check_output_times([0.1, 0.3, 0.3])
    assert isinstance(info.value, ConfigurationError)
    assert "t[2] = 0.3 is not after t[1] = 0.3" in one_line(info.value)
    system, _ = chain_system()
    with pytest.raises(DynamicsInputError):
        make_integrator("torchdiffeq", system, [0.2, 0.1], dt=0.01)


def test_explicit_blow_up_names_the_implicit_integrator():
    system, params = chain_system(n=6, stiffness=100.0)
    integrator = make_integrator("torchdiffeq", system, torch.linspace(0.1, 2.0, 20), dt=0.1,
                                 method="rk4")
    with pytest.raises(UnstableStepError) as info:
        integrator(params)
    text = one_line(info.value)
    assert "blew up" in text and "problem.integrator=implicit" in text and "omega_max" in text
    # the implicit integrator takes the same step
    x = make_integrator("implicit", system, torch.linspace(0.1, 2.0, 20), dt=0.1)(params)
    assert bool(torch.isfinite(x).all())


def test_nan_in_the_state_names_time_and_vertex():
    x0 = torch.arange(7, dtype=DT) / 6
    x0[3] = math.nan
    with pytest.raises(NonFiniteStateError) as info:
        chain_system(x0=x0)
    assert "t = 0" in one_line(info.value) and "vertex 3" in str(info.value)

    class NaNLoad:
        def __call__(self, t):
            out = torch.zeros(t.numel(), 7, dtype=DT)
            out[t > 0.2, 5] = math.nan
            return out

    system, params = chain_system(loads=NaNLoad())
    with pytest.raises(NonFiniteStateError) as info:
        make_integrator("implicit", system, [0.5], dt=0.05)(params)
    assert "t = 0.25" in one_line(info.value) and "vertex 5" in str(info.value)
    with pytest.raises(NonFiniteStateError) as info:
        make_integrator("torchdiffeq", system, [0.5], dt=0.05, method="rk4")(params)
    assert "vertex 5" in one_line(info.value)


def test_density_must_be_positive():
    nodes = torch.arange(3)
    springs = SpringChain1D(torch.stack([nodes[:-1], nodes[1:]], 1), torch.full((2,), 0.5),
                            torch.zeros(1, 3))
    with pytest.raises(DynamicsInputError) as info:
        DynamicSystem(springs, 2, torch.tensor([0.5, 0.0, 0.5]), torch.tensor([0]),
                      KeyedMotion(torch.zeros(1), torch.zeros(1, 1)), None, torch.zeros(3),
                      torch.arange(3.0) / 2)
    assert "density must be > 0" in one_line(info.value)
