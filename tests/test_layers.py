"""The import graph of torchfit/ (lazy imports included): no cycle, and every arrow points down
DESIGN.md's table of layers. One test for the whole package."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchfit"

#: layer -> rank; a module may import modules of a lower rank only (or of its own package).
#: ``records``/``residual``/``errors`` are the neutral contract every layer may use.
RANK = {"errors": -1, "records": 0, "residual": 0,
        "linalg": 1, "mesh": 2, "physics": 3, "params": 3, "verification": 3,
        "problems": 4, "solvers": 4, "logging": 5, "config": 6, "fit": 6, "__init__": 7}


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


def test_every_import_points_down_the_layers():
    upward = [f"{m} -> {d}" for m, deps in graph().items() for d in deps
              if layer(d) != layer(m) and RANK[layer(d)] >= RANK[layer(m)]]
    assert not upward, "imports against DESIGN.md's layers: " + ", ".join(sorted(upward))


def test_the_check_can_fail():
    # problems and logging meet solvers only through torchfit.records / torchfit.residual
    assert RANK["solvers"] >= RANK["problems"] and RANK["solvers"] > RANK["linalg"]
    assert "torchfit.solvers" in imports_of("torchfit.x", PACKAGE / "fit.py", set(modules()))
