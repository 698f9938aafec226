"""The elastic blocks with self-contact: Newton's equilibrium never passes through the
contact, the union pattern grows only when new pairs touch, and the body's Jacobian with
active contacts matches finite differences and its adjoint (the dot test)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.helpers.contact_blocks import DHAT, blocks
from torchfit.physics import NewtonOptions
from torchfit.physics.contact import ElasticityWithContact, SelfContact
from torchfit.physics.elasticity import QuasistaticElasticity, SimplicialElasticity

PUSHES = (0.0, 0.004, 0.012)   # the upper block's top pressed down (m), gap 1 mm


@pytest.fixture(scope="module")
def pressed():
    points, tets, bottom, top = blocks()
    elastic = SimplicialElasticity(torch.from_numpy(points), torch.from_numpy(tets),
                                   "stable_neo_hookean", nu=0.3)
    contact = SelfContact(points, tets, DHAT)
    E = torch.full((elastic.n_cells,), 1e4, dtype=torch.float64)
    rest = torch.from_numpy(points.reshape(1, -1))
    pattern = elastic.tangent_pattern
    diagonal = pattern.diagonal(pattern.assemble(elastic.tangent_values(rest, E))[0])
    # IPC's initial stiffness from the elastic scale (about 2e6 here; a weak barrier lets the
    # gap close to nothing and the collision-free steps creep)
    contact.initial_stiffness(np.zeros(elastic.n_dofs), rest, float(diagonal.mean()))
    model = ElasticityWithContact(elastic, contact)
    qs = QuasistaticElasticity(model, np.concatenate([bottom, top]), backend="scipy",
                               newton=NewtonOptions(rtol=1e-9, atol=1e-9), start="rest")
    X = torch.from_numpy(points)
    frames = []
    for push in PUSHES:
        moved = X[top].clone()
        moved[:, 2] -= push
        frames.append(torch.cat([X[bottom], moved]))
    E = E * (1 + 0.3 * torch.linspace(-1, 1, elastic.n_cells, dtype=torch.float64))
    return model, qs, torch.stack(frames), E


def test_equilibrium_holds_the_blocks_apart(pressed):
    model, qs, positions, E = pressed
    x = qs(E, positions).reshape(len(PUSHES), -1)
    contact = model.contact
    assert contact.intersecting_frames(x) == []
    gaps = [contact.minimum_distance(x[f:f + 1]) for f in range(len(PUSHES))]
    # pressed harder, the barrier's gap closes but stays open (the blocks never touch)
    assert gaps[0] > gaps[1] > gaps[2] > 0
    assert gaps[2] < 0.5 * contact.dhat
    # the residual of the sum is zero on the free dofs, the barrier's force is not
    free = qs.equilibrium.free_dofs
    assert float(model.residual(x, E)[:, free].abs().max()) < 1e-7
    assert float(contact.gradient(x)[:, free].abs().max()) > 1.0
    # a pattern per new set of touching pairs, not per Newton iteration
    assert 1 <= model.pattern_builds < sum(qs.last_newton_iterations)
    assert model.pairs.shape[0] > 0


def test_jacobian_with_contact_matches_finite_differences_and_adjoint(pressed):
    model, qs, positions, E = pressed
    lin = qs.linearization(E, positions)
    generator = torch.Generator().manual_seed(1)
    v = torch.randn(E.shape, generator=generator, dtype=torch.float64) * E * 1e-2
    w = torch.randn(lin.x.shape, generator=generator, dtype=torch.float64)
    jv = lin.jvp(v)
    # dot test: w . (J v) = (J^T w) . v
    assert float((w * jv).sum()) == pytest.approx(float((lin.vjp(w) * v).sum()), rel=1e-10)
    h = 1e-3
    plus = qs(E + h * v, positions).reshape(len(PUSHES), -1)
    minus = qs(E - h * v, positions).reshape(len(PUSHES), -1)
    fd = (plus - minus) / (2 * h)
    error = float(torch.linalg.vector_norm(fd - jv) / torch.linalg.vector_norm(jv))
    assert error < 1e-5, error
    # the contact matters: the Jacobian of the pressed frame differs from the elastic one's
    assert float(torch.linalg.vector_norm(jv[2])) > 0
