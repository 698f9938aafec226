"""The problems layer's interfaces: every collaborator offers all of its protocol's members, and
the problem classes stay composed (at most 30 methods of their own, one torchfit base)."""
from __future__ import annotations

import ast
import inspect
import textwrap
from pathlib import Path

import pytest

import torchfit.problems as problems
from torchfit.problems import (NO_WARM_STARTS, QUASISTATIC, BodySimulation, PoseSimulation,
                               TimeIntegration, TimeModel, WarmStarts, protocols)
from torchfit.problems.body.dynamic import BodyInTime
from torchfit.problems.body.poses import FramePoses

PROBLEMS_DIR = Path(problems.__file__).parent
#: the most methods a class of the problems layer defines itself (issue 46)
MAX_OWN_METHODS = 30


def members(protocol: type) -> set[str]:
    """The attributes and methods a protocol declares (not those of ``Protocol`` itself)."""
    names = set(getattr(protocol, "__annotations__", {}))
    names |= {name for name, value in vars(protocol).items()
              if callable(value) and not name.startswith("_")}
    return names - {"__init__"}


def offered(cls: type) -> set[str]:
    """What instances of ``cls`` offer without being built: methods, properties, class
    attributes and the annotated attributes ``__init__`` sets."""
    names = {name for name in dir(cls) if not name.startswith("_")}
    source = textwrap.dedent(inspect.getsource(cls))
    names |= {node.attr for node in ast.walk(ast.parse(source))
              if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
              and node.value.id == "self" and isinstance(node.ctx, ast.Store)}
    return names


@pytest.mark.parametrize("cls, protocol", [
    (FramePoses, BodySimulation), (BodyInTime, BodySimulation), (FramePoses, WarmStarts),
    (type(NO_WARM_STARTS), WarmStarts), (type(QUASISTATIC), TimeModel),
    (TimeIntegration, TimeModel), (BodyInTime, TimeModel)])
def test_each_collaborator_offers_every_member_of_its_protocol(cls, protocol):
    missing = members(protocol) - offered(cls)
    assert not missing, f"{cls.__name__} lacks {sorted(missing)} of {protocol.__name__}"


def test_the_pose_simulation_of_this_process_is_a_pose_simulation():
    from torchfit.physics.elasticity import QuasistaticElasticity
    missing = members(PoseSimulation) - {"__call__"} - offered(QuasistaticElasticity)
    assert not missing and callable(QuasistaticElasticity.__call__)


def test_the_members_test_can_fail():
    class Partial:
        def independent(self):
            return None

    assert members(WarmStarts) - offered(Partial) == {"warm_start_state",
                                                       "restore_warm_start_state"}


def classes() -> list[tuple[str, ast.ClassDef]]:
    out = []
    for path in sorted(PROBLEMS_DIR.rglob("*.py")):
        tree = ast.parse(path.read_text())
        out += [(f"{path.relative_to(PROBLEMS_DIR)}:{node.name}", node)
                for node in ast.walk(tree) if isinstance(node, ast.ClassDef)]
    return out


def test_no_class_of_the_problems_layer_grows_past_thirty_methods():
    grown = {name: n for name, node in classes()
             if (n := sum(isinstance(b, (ast.FunctionDef, ast.AsyncFunctionDef))
                          for b in node.body)) > MAX_OWN_METHODS}
    assert not grown, f"classes with more than {MAX_OWN_METHODS} methods of their own: {grown}"


def test_a_problem_has_one_torchfit_base():
    # settings dataclasses mix DynamicSettings into a ProblemConfig: settings, not problems
    mixed = {name: [ast.unparse(b) for b in node.bases] for name, node in classes()
             if len(node.bases) > 1 and not node.name.endswith("Config")}
    assert not mixed, f"problem classes with several bases: {mixed}"
    assert not hasattr(protocols, "DynamicMixin") and not hasattr(problems, "DynamicRiggedBody")
