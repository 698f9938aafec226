"""Both integrators behind make_integrator: the same Jacobian columns as their jvps, the
observed orders (1 and 2) towards torchdiffeq's trajectory as the step shrinks, a state
that is not finite named with its time and vertex."""
from __future__ import annotations

import math

import pytest
import torch

from torchfit.physics.dynamics import NonFiniteStateError, make_integrator

from helpers.dynamics_systems import DT, chain_system, one_line


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
