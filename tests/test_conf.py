"""The Hydra config tree against its schemas: every YAML of ``conf/problem`` and
``conf/solver`` composes (Hydra's compose API, primary config ``fit``), builds a valid problem
or solver config, and holds only real overrides: a value that restates its dataclass
default (or what the YAML it extends already sets) fails, so each default is written once."""
from __future__ import annotations

import dataclasses
import enum
import shutil
from pathlib import Path
from typing import Any

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from torchfit.config import register_configs
from torchfit.problems import PROBLEMS
from torchfit.problems.config import make_config, validate_config
from torchfit.solvers import SOLVERS

CONF = Path(__file__).resolve().parents[1] / "conf"
PROBLEM_FILES = sorted(p.stem for p in (CONF / "problem").glob("*.yaml"))
SOLVER_FILES = sorted(p.stem for p in (CONF / "solver").glob("*.yaml"))
#: settings a composition needs that no YAML sets (a required path)
REQUIRED = {"animation": ["problem.path=/data/my_animation"]}
#: the solver file of ``fit.yaml``'s defaults list
DEFAULT_SOLVER = "gauss_newton"


def composed(conf: Path, group: str, name: str) -> Any:
    """``fit`` composed with ``<group>=<name>``."""
    register_configs()
    with initialize_config_dir(config_dir=str(conf), version_base=None):
        return compose("fit", overrides=[f"{group}={name}", *REQUIRED.get(name, [])])


def load(conf: Path, group: str, name: str) -> tuple[dict, list]:
    """The file's own values (``{section: {key: value}}``, section ``""`` the top level of
    ``fit``) and its defaults list. A file without ``# @package _global_`` sets keys of its
    group's section."""
    path = conf / group / f"{name}.yaml"
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    defaults = node.pop("defaults", [])
    if "@package _global_" not in path.read_text():
        node = {group: node}
    values: dict[str, dict[str, Any]] = {"problem": {}, "solver": {}, "": {}}
    for section, value in node.items():
        if section in ("problem", "solver"):
            values[section].update(value or {})
        elif section != "hydra":
            values[""][section] = value
    return values, defaults


def parents(conf: Path, group: str, defaults: list) -> list[str]:
    """The files of ``group`` that a defaults list extends."""
    found = []
    for entry in defaults:
        if isinstance(entry, str) and entry != "_self_" and not entry.startswith("/schema/"):
            target = entry.split("@", 1)[0].removeprefix(f"/{group}/")
            if (conf / group / f"{target}.yaml").is_file():
                found.append(target)
    return found


def inherited(conf: Path, group: str, name: str) -> tuple[dict, str]:
    """What the files ``name`` extends set (nearest last), and the solver file chosen."""
    values: dict[str, dict[str, Any]] = {"problem": {}, "solver": {}, "": {}}
    own, defaults = load(conf, group, name)
    solver = DEFAULT_SOLVER if group == "problem" else name
    for parent in parents(conf, group, defaults):
        above, solver = inherited(conf, group, parent)
        mine, _ = load(conf, group, parent)
        for section in values:
            values[section].update(above[section])
            values[section].update(mine[section])
    for entry in defaults:
        if isinstance(entry, dict) and "override /solver" in entry:
            solver = entry["override /solver"]
    return values, solver


def plain(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def same(a: Any, b: Any) -> bool:
    """Equal as settings (``1 == 1.0``, but ``1 != True``)."""
    a, b = plain(a), plain(b)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return isinstance(a, bool) == isinstance(b, bool) and a == b


def schema_defaults(cfg: Any) -> dict[str, dict[str, Any]]:
    """Dataclass defaults of the sections of a composed ``fit`` config."""
    problem = PROBLEMS[cfg.problem.name].config_class()
    solver = SOLVERS[cfg.solver.name].config_class()
    top = OmegaConf.to_container(ConfigStore.instance().load("fit_schema.yaml").node,
                                 resolve=False)
    return {"problem": {f.name: getattr(problem, f.name) for f in dataclasses.fields(problem)},
            "solver": {f.name: getattr(solver, f.name) for f in dataclasses.fields(solver)},
            "": {k: v for k, v in top.items() if k not in ("problem", "solver")}}


def restated(group: str, name: str, conf: Path = CONF) -> list[str]:
    """``section.key=value`` of every value the file sets that the key gets anyway: from a
    file it extends, the solver file it chooses, or the dataclass default."""
    defaults = schema_defaults(composed(conf, group, name))
    own, _ = load(conf, group, name)
    above, solver = inherited(conf, group, name)
    if group == "problem":
        solver_values, _ = load(conf, "solver", solver)
        above["solver"] = {**solver_values["solver"], **above["solver"]}
    out = []
    for section, values in own.items():
        for key, value in values.items():
            if key not in defaults[section]:
                continue                 # not a schema setting (composition checks those)
            anyway = above[section].get(key, defaults[section][key])
            if same(value, anyway):
                out.append(f"{section + '.' if section else ''}{key}={value}")
    return out


@pytest.mark.parametrize("name", PROBLEM_FILES)
def test_problem_yaml_holds_only_real_overrides(name):
    assert restated("problem", name) == [], (
        f"conf/problem/{name}.yaml restates what these keys get anyway: remove the lines "
        "(a default is written once, in the dataclass)")


@pytest.mark.parametrize("name", SOLVER_FILES)
def test_solver_yaml_holds_only_real_overrides(name):
    assert restated("solver", name) == [], (
        f"conf/solver/{name}.yaml restates its dataclass defaults: remove the lines")


@pytest.mark.parametrize("name", PROBLEM_FILES)
def test_problem_yaml_builds_valid_problem_and_solver_configs(name):
    cfg = composed(CONF, "problem", name)
    config = make_config(PROBLEMS[cfg.problem.name].config_class, cfg.problem)
    validate_config(config)
    assert config.name == cfg.problem.name
    solver = SOLVERS[cfg.solver.name].config_class(**OmegaConf.to_container(cfg.solver))
    solver.validate()


@pytest.mark.parametrize("name", SOLVER_FILES)
def test_solver_yaml_builds_a_valid_solver_config(name):
    cfg = composed(CONF, "solver", name)
    config = SOLVERS[cfg.solver.name].config_class(**OmegaConf.to_container(cfg.solver))
    config.validate()


def test_the_check_finds_restated_values(tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(CONF, conf)
    with open(conf / "problem" / "spring1d.yaml", "a") as f:
        f.write("\nn: 64\nk0: 50.0\n")                   # the default, and a real override
    assert restated("problem", "spring1d", conf) == ["problem.n=64"]
    with open(conf / "problem" / "spring1d_dynamic.yaml", "a") as f:
        f.write("\nlog_every: 1\n")                       # fit's default
    assert restated("problem", "spring1d_dynamic", conf) == ["log_every=1"]
    (conf / "problem" / "stiff.yaml").write_text(
        "defaults:\n  - /schema/problem/spring1d@_here_\n  - _self_\nk0: 50.0\n")
    (conf / "problem" / "stiffer.yaml").write_text("defaults:\n  - stiff\n  - _self_\nk0: 50.0\n")
    assert restated("problem", "stiffer", conf) == ["problem.k0=50.0"]    # what stiff sets
    (conf / "problem" / "stiffer.yaml").write_text("defaults:\n  - stiff\n  - _self_\nk0: 100.0\n")
    assert restated("problem", "stiffer", conf) == []     # the default, back from stiff's value
