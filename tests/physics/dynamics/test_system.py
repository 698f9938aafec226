"""The semi-discrete system: keyed motions, and its bad input as one-line errors (negative
damping, output times, density)."""
from __future__ import annotations

import pytest
import torch

from torchfit.errors import ConfigurationError, SimulationError
from torchfit.physics import ScalarSpringNetwork
from torchfit.physics.dynamics import (DynamicsInputError, DynamicSystem, KeyedMotion,
                                       NegativeDampingError, check_output_times, make_integrator)
from torchfit.physics.dynamics.system import smootherstep

from helpers.dynamics_systems import chain_system, one_line, sheet_system


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


def test_density_must_be_positive():
    nodes = torch.arange(3)
    springs = ScalarSpringNetwork(torch.stack([nodes[:-1], nodes[1:]], 1), torch.full((2,), 0.5),
                            torch.zeros(1, 3))
    with pytest.raises(DynamicsInputError) as info:
        DynamicSystem(springs, 2, torch.tensor([0.5, 0.0, 0.5]), torch.tensor([0]),
                      KeyedMotion(torch.zeros(1), torch.zeros(1, 1)), None, torch.zeros(3),
                      torch.arange(3.0) / 2)
    assert "density must be > 0" in one_line(info.value)


@pytest.mark.parametrize("make", [chain_system, sheet_system])
def test_sparse_operators_are_the_element_sums(make):
    """``K0(k) U`` and the element-column matrix ``B`` of the tangents' right-hand side, as
    sparse products, equal the element loops they replace (scatter of einsum products)."""
    system, params = make()
    field = system.split(params)[0]
    g = torch.Generator().manual_seed(3)
    U = torch.randn(system.n_dofs, 5, dtype=params.dtype, generator=g)
    columns = torch.stack([system.stiffness_matvec(field, U[:, j]) for j in range(5)], dim=1)
    assert torch.allclose(system.stiffness_matmul(field, U), columns, rtol=1e-12, atol=1e-12)
    # the kept K0 follows the field: a changed field is not served the old matrix
    doubled = system.stiffness_matmul(2.0 * field, U)
    assert torch.allclose(doubled, 2.0 * columns, rtol=1e-12, atol=1e-12)
    forces = system.unit_element_forces(U[:, 0])                     # (n_field, d_el)
    V = torch.randn(system.n_field, 4, dtype=params.dtype, generator=g)
    loop = system.scatter_elements(forces[:, :, None] * V[:, None, :])
    product = torch.sparse.mm(system.element_matrix(forces), V)
    assert torch.allclose(product, loop, rtol=1e-12, atol=1e-12)


def test_lowest_frequency_of_a_spring_chain_is_its_closed_form():
    """A chain of n springs of stiffness k held at both ends, mass m at each of its n - 1
    inner nodes: w_j = 2 sqrt(k / m) sin(j pi / (2 n)), the lowest j = 1 (shift-invert
    Lanczos against the closed form); w1 scales as sqrt(k); a chain held nowhere has a rigid
    mode (None)."""
    import math

    n, k, m = 40, 250.0, 0.02
    nodes = torch.arange(n + 1)
    springs = ScalarSpringNetwork(torch.stack([nodes[:-1], nodes[1:]], 1),
                                  torch.full((n,), 1.0 / n, dtype=torch.float64),
                                  torch.zeros(1, n + 1, dtype=torch.float64))
    rest = nodes.to(torch.float64) / n

    def chain(fixed):
        return DynamicSystem(springs, n, torch.full((n + 1,), m, dtype=torch.float64),
                             torch.tensor(fixed), KeyedMotion(torch.zeros(1, dtype=torch.float64),
                                                              rest[fixed][None]),
                             None, torch.zeros(n + 1, dtype=torch.float64), rest)

    system = chain([0, n])
    field = torch.full((n,), k, dtype=torch.float64)
    w1 = system.lowest_frequency(field)
    assert w1 == pytest.approx(2 * math.sqrt(k / m) * math.sin(math.pi / (2 * n)), rel=1e-10)
    assert system.lowest_frequency(4 * field) == pytest.approx(2 * w1, rel=1e-10)
    # below the highest mode, which the power iteration finds: 2 sqrt(k / m) sin((n-1) pi / 2n)
    assert system.max_frequency(field, iterations=2000) == pytest.approx(
        2 * math.sqrt(k / m) * math.sin((n - 1) * math.pi / (2 * n)), rel=1e-3)
    free = DynamicSystem(springs, n, torch.full((n + 1,), m, dtype=torch.float64),
                         torch.zeros(0, dtype=torch.long),
                         KeyedMotion(torch.zeros(1, dtype=torch.float64),
                                     torch.zeros(1, 0, dtype=torch.float64)),
                         None, torch.zeros(n + 1, dtype=torch.float64), rest)
    assert free.lowest_frequency(field) is None
