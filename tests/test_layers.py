"""The import graph of torchfit/ (lazy imports included): no cycle, and every arrow points down
docs/architecture.md's table of layers. One test for the whole package."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchfit"

NEUTRAL = {"errors", "memory", "records", "residual", "settings", "steps"}   # the contract every layer may use
#: layer -> the layers it may import (docs/architecture.md's table): solvers know nothing of
#: meshes or physics, problems nothing of solvers, reporting meets solvers only through the records.
ALLOWED = {
    "errors": set(), "memory": {"errors"}, "records": set(), "residual": {"errors"}, "settings": {"errors"},
    "steps": set(),
    "linalg": NEUTRAL, "mesh": NEUTRAL | {"linalg"}, "params": NEUTRAL | {"linalg"},
    "physics": NEUTRAL | {"linalg", "mesh"}, "verification": NEUTRAL,
    "problems": NEUTRAL | {"linalg", "mesh", "physics", "params"},
    "solvers": NEUTRAL | {"linalg"},
    "reporting": NEUTRAL | {"linalg", "mesh", "physics", "params", "problems"},
    # one run (fit, the continuation, verify): on top of everything but the Hydra schemas
    "run": NEUTRAL | {"linalg", "problems", "solvers", "reporting", "verification"},
    "config": NEUTRAL | {"problems", "solvers", "run"},
}


def modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__" and len(parts) > 1:
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [module] + [f"{module}.{a.name}" for a in node.names]
        for target in targets:
            while target and target not in known:
                target = target.rsplit(".", 1)[0] if "." in target else ""
            if target and target != name and not name.startswith(target + "."):
                found.add(target)
    return found


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {name: imports_of(name, path, set(mods)) for name, path in mods.items()}


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_no_import_cycle():
    edges = graph()
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(edges[node]):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def forbidden(edges: dict[str, set[str]]) -> list[str]:
    return sorted(f"{m} -> {d}" for m, deps in edges.items() for d in deps
                  if layer(m) != "__init__" and layer(d) != layer(m)
                  and layer(d) not in ALLOWED[layer(m)])


def test_every_import_follows_the_layers():
    edges = graph()
    assert set(map(layer, edges)) - {"__init__"} <= set(ALLOWED), "a new layer needs its row"
    bad = forbidden(edges)
    assert not bad, "imports against docs/architecture.md's layers: " + ", ".join(bad)


def test_no_private_name_crosses_a_module():
    crossing = []
    for name, path in modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith(
                    "torchfit")):
                crossing += [f"{name} imports {a.name} from {node.module}" for a in node.names
                             if a.name.startswith("_") and not a.name.startswith("__")]
    assert not crossing, crossing


def test_the_checks_can_fail():
    # what a solver importing the physics, or reporting importing a solver, would look like
    assert forbidden({"torchfit.solvers.x": {"torchfit.physics.equilibrium"},
                      "torchfit.reporting.x": {"torchfit.solvers.base"},
                      "torchfit.problems.x": {"torchfit.solvers"}}) == [
        "torchfit.problems.x -> torchfit.solvers", "torchfit.reporting.x -> torchfit.solvers.base",
        "torchfit.solvers.x -> torchfit.physics.equilibrium"]
    assert "torchfit.solvers" in imports_of("torchfit.run.x", PACKAGE / "run" / "solver.py",
                                            set(modules()))
