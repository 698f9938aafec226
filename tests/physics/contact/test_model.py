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
    return build()


def build():
    """``(model, quasistatic, Dirichlet positions of the PUSHES frames, E)``."""
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


@pytest.mark.slow   # 38 s on 2 busy cores: 8 substeps of Newton with contact (notes/contact.md)
def test_a_start_through_itself_is_reached_in_substeps():
    """The animated pose moves the whole upper block 2 mm down, through the lower one (the
    gap is 1 mm): its start is replaced by the equilibrium reached by moving the Dirichlet
    dofs in substeps, each checked by CCD and solved with contact."""
    model, qs, positions, E = build()
    rest = model.elastic.rest.points.reshape(1, -1).clone()
    target = rest.clone().reshape(-1, 3)
    target[target[:, 2] > 0.1 + 1e-9, 2] -= 0.002
    target = target.reshape(1, -1)
    assert model.contact.intersecting_frames(target) == [0]
    dirichlet = qs.dirichlet_vertices
    fixed = (dirichlet[:, None] * 3 + torch.arange(3)).reshape(-1)
    starts, stuck = model.collision_free_start(target, fixed)
    assert model.contact.intersecting_frames(starts) == [] and stuck == []

    # a solver of its own without warm starts: each substep starts where it is told
    fresh = QuasistaticElasticity(model, dirichlet, backend="scipy", start="rest",
                                  newton=NewtonOptions(rtol=1e-9, atol=1e-9))

    def solve(x):
        return fresh(E, x.reshape(1, -1, 3)[:, dirichlet],
                     x_init=x.reshape(1, -1, 3)).reshape(1, -1)

    x = model.stepped_start(solve, solve(rest), rest, target, fixed)
    assert model.contact.intersecting_frames(x) == []
    torch.testing.assert_close(x[:, fixed], target[:, fixed], rtol=0, atol=1e-12)
    assert 0 < model.contact.minimum_distance(x) < model.contact.dhat
    assert model.start_substeps == 8
