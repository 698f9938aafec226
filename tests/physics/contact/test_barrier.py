"""The IPC self-contact barrier (ipctk) of two blocks whose facing surfaces are within reach:
its gradient and Hessian by Taylor tests (rate 2), the collision-free step, the refusals."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.helpers.contact_blocks import DHAT, GAP, blocks
from torchfit.physics.contact import ContactInputError, SelfContact


def taylor_rates(f, df, x, v, steps=(1e-3, 5e-4, 2.5e-4)):
    """Rates of ``|f(x + h v) - f(x) - h df(x) v|`` as ``h`` halves (2: ``df`` is right)."""
    base, slope = f(x), df(x, v)
    errors = [float(torch.linalg.vector_norm(f(x + h * v) - base - h * slope)) for h in steps]
    return [np.log2(a / b) for a, b in zip(errors, errors[1:])], errors


@pytest.fixture(scope="module")
def pressed():
    """The blocks' contact term (kappa 1) and positions with the upper block moved down to a
    third of the gap (every facing pair active, none at zero distance)."""
    points, tets, _, _ = blocks()
    contact = SelfContact(points, tets, DHAT, stiffness=1.0)
    x = points.copy()
    upper = x[:, 2] > 0.1 + GAP / 2
    x[upper, 2] -= 2 * GAP / 3
    # sheared and shifted off the grid: no edge of one block parallel to an edge of the other
    # within reach (their distance is not smooth there)
    x[upper, 0] += 0.013 + 0.01 * x[upper, 1]
    x[upper, 1] += 0.007 + 0.02 * x[upper, 0]
    return contact, torch.from_numpy(x.reshape(1, -1))


def test_contact_reaches_the_facing_surfaces_only(pressed):
    contact, x = pressed
    assert contact.dhat == pytest.approx(DHAT * np.sqrt(0.2 ** 2 + 0.2 ** 2 + 0.201 ** 2))
    assert contact.minimum_distance(x) == pytest.approx(GAP / 3, rel=1e-6)
    g = contact.gradient(x)[0].reshape(-1, 3)
    z = x[0].reshape(-1, 3)[:, 2]
    upper, lower = g[z > 0.1 + 1e-9].sum(0), g[z < 0.1 + 1e-9].sum(0)
    # the barrier pushes the blocks apart (the energy falls as the upper block rises) with
    # equal and opposite forces; the vertices far from the gap feel nothing
    assert float(upper[2]) < 0 < float(lower[2])
    torch.testing.assert_close(upper, -lower, rtol=0, atol=1e-9 * float(upper.abs().max()))


def test_gradient_and_hessian_taylor_rate_two(pressed):
    contact, x = pressed
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    v *= 1e-3 / float(v.abs().max())
    rates, errors = taylor_rates(contact.energy, lambda x, v: (contact.gradient(x) * v).sum(1),
                                 x, v)
    assert min(rates) > 1.9, (rates, errors)

    def hessian_times(x, v):
        V = contact.surface_positions(x)[0]
        H, _ = contact.hessian_and_pairs(V)
        dofs = contact.surface_dofs
        out = torch.zeros_like(x)
        out[0, dofs] = torch.from_numpy(H.tocsr() @ v[0, dofs].numpy())
        return out

    rates, errors = taylor_rates(contact.gradient, hessian_times, x, v)
    assert min(rates) > 1.9, (rates, errors)


def test_projected_hessian_is_positive_semidefinite(pressed):
    contact, x = pressed
    V = contact.surface_positions(x)[0]
    exact, pairs = contact.hessian_and_pairs(V)
    projected, same = contact.hessian_and_pairs(V, projected=True)
    np.testing.assert_array_equal(pairs, same)
    assert np.linalg.eigvalsh(projected.toarray()).min() > -1e-9 * abs(projected).max()
    assert np.linalg.eigvalsh(exact.toarray()).min() < 0     # the barrier is not convex here


def test_collision_free_step_stops_short_of_contact(pressed):
    contact, x = pressed
    through = x.clone().reshape(-1, 3)
    upper = through[:, 2] > 0.1 + 1e-9
    through[upper, 2] -= 2 * GAP / 3                         # past the lower face
    alpha = float(contact.collision_free_step(x, through.reshape(1, -1))[0])
    assert 0.1 < alpha < 0.5                                # contact at alpha = 0.5
    assert contact.intersecting_frames(through.reshape(1, -1)) == [0]
    assert contact.intersecting_frames(x) == []


def test_refusals():
    points, tets, _, _ = blocks()
    with pytest.raises(ContactInputError, match=r"problem.contact_dhat = 0.5 is out of range"):
        SelfContact(points, tets, 0.5)
    overlapping, tets, _, _ = blocks(gap=-0.02)
    with pytest.raises(ContactInputError, match=r"the rest shape's surface passes through itself "
                                                r"near vertex \d+ at .*: fix the mesh"):
        SelfContact(overlapping, tets, DHAT)
