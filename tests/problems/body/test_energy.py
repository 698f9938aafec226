"""The body's energy: the elastic model alone without contact (the term absent, not zero),
the sum with the self-contact barrier with it, and the contact settings' refusals."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from helpers.contact_blocks import DHAT, blocks
from torchfit.physics.contact import ElasticityWithContact
from torchfit.physics.elasticity import SimplicialElasticity
from torchfit.problems import ProblemConfigError
from torchfit.problems.body.energy import body_energy, check_contact_settings

CPU = torch.device("cpu")


def test_without_contact_the_term_is_absent():
    points, tets, _, _ = blocks()
    model = body_energy(points, tets, "corotated", 0.45, torch.float64, CPU)
    assert type(model) is SimplicialElasticity


def test_with_contact_the_energy_is_the_sum():
    points, tets, _, _ = blocks()
    model = body_energy(points, tets, "corotated", 0.45, torch.float64, CPU, contact_dhat=DHAT,
                        modulus=2.0)
    assert isinstance(model, ElasticityWithContact)
    assert model.contact.dhat == pytest.approx(DHAT * model.contact.diagonal)
    # IPC's initial stiffness from the elastic scale: proportional to the modulus
    kappa = model.contact.stiffness
    again = body_energy(points, tets, "corotated", 0.45, torch.float64, CPU, contact_dhat=DHAT,
                        modulus=4.0)
    assert again.contact.stiffness == pytest.approx(2 * kappa, rel=1e-9)
    x = torch.from_numpy(points.reshape(1, -1))
    E = torch.full((model.n_cells,), 2.0, dtype=torch.float64)
    # at rest the blocks are 1 mm apart, within dhat: only the barrier has energy and force
    assert float(model.energy(x, E)) == pytest.approx(float(model.contact.energy(x)))
    assert float(model.contact.energy(x)) > 0
    torch.testing.assert_close(model.residual(x, E), model.contact.gradient(x))


def test_a_rest_shape_through_itself_is_one_line():
    points, tets, _, _ = blocks(gap=-0.02)
    with pytest.raises(ProblemConfigError, match=r"surface passes through itself near vertex "
                                                 r"\d+ at .*: fix the mesh") as info:
        body_energy(points, tets, "corotated", 0.45, torch.float64, CPU, contact_dhat=DHAT)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("settings, match", [
    (dict(contact=True, contact_dhat=0.0), r"^problem.contact_dhat=0.0: must be in \(0, 0.1\]"),
    (dict(contact=True, contact_dhat=0.2), r"^problem.contact_dhat=0.2: must be in \(0, 0.1\]"),
    (dict(contact=True, contact_dhat=1e-3, dynamic=True),
     r"^problem.contact=True: is not yet available with problem.dynamic=true"),
])
def test_contact_settings_out_of_range_are_one_line(settings, match):
    with pytest.raises(ProblemConfigError, match=match):
        check_contact_settings(SimpleNamespace(**settings))
    check_contact_settings(SimpleNamespace(contact=False, contact_dhat=1e-3, dynamic=True))
