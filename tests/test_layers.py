"""The import graph of torchfit/ (lazy imports included): no cycle, every arrow points down
docs/architecture.md's table of layers, and an import across parts goes through a face. One
test for the whole package.

The faces (issue 46, item 3: "the faces are the door"):

* a *part* is a package of torchfit, each directory with an ``__init__.py``
  (``torchfit``, ``torchfit.linalg``, ``torchfit.linalg.backends``, ``torchfit.mesh``,
  ``torchfit.mesh.formats``, ``torchfit.mesh.formats.usd``, ...); its *face* is its
  ``__init__.py``, and what the face offers is its ``__all__``. Each top-level module
  (``torchfit.errors``, ``torchfit.records``, ..., ``torchfit.verification``,
  ``torchfit.config``) is a face of its own;
* a module belongs to the package of its directory (an ``__init__.py`` to its own package),
  and is *inside* package P when that package is P or a subpackage of P;
* an import *passes a face* when a module not inside package P names a module of P (not P
  itself, nor a subpackage, nor a top-level module). ``from P import name`` names P's face
  where ``name`` is in P's ``__all__``, else P's module ``name`` where there is one;
  ``import P.m`` and ``from P.m import name`` name the module ``P.m``.

So a module imports the modules of its own package and of the packages above it directly
(its siblings; a subpackage its parent's modules: the parent's face re-exports the
subpackage, so a subpackage importing that face would import itself), and everything else
through faces: another layer, a sibling subpackage, and its own package's subpackages (the
face of ``mesh`` imports ``.tetwild``, not ``.tetwild.tetrahedralize``). Every import that
passes a face is in :data:`PAST_A_FACE` with the reason it stays, and the list only shrinks
(an entry that no import needs any more fails the test). The apps (``experiments/*.py``)
import only the faces in :data:`APP_FACES`: the package, the run, the Hydra schemas, the
errors.
"""
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


def imported_module(package: str, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` in ``package`` names (relative levels
    resolved)."""
    if node.level:
        base = package.split(".")[: len(package.split(".")) - node.level + 1]
        return ".".join(base + ([node.module] if node.module else []))
    return node.module or ""


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = imported_module(package, node)
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


# -- the faces --------------------------------------------------------------------------------
REPO = PACKAGE.parent
#: what the apps (experiments/*.py, thin adapters: config in, exit status out) may import
APP_FACES = {"torchfit", "torchfit.run", "torchfit.run.distributed", "torchfit.config",
             "torchfit.errors"}

#: (importer, imported module) -> why this import passes the face of the imported module's
#: package. Only shrinks: an entry no import needs fails the test (84 on 2026-12-07 before
#: issue 46, none after).
PAST_A_FACE: dict[tuple[str, str], str] = {
}

#: (app, imported module) -> why an app imports a module outside :data:`APP_FACES`
APP_PAST_A_FACE: dict[tuple[str, str], str] = {
}


def packages(mods: dict[str, Path]) -> set[str]:
    return {name for name, path in mods.items() if path.name == "__init__.py"}


def package_of(module: str, pkgs: set[str]) -> str:
    return module if module in pkgs else module.rsplit(".", 1)[0]


def exports(mods: dict[str, Path]) -> dict[str, set[str]]:
    """package -> the names in its face's ``__all__``."""
    out = {}
    for name in packages(mods):
        found: set[str] = set()
        for node in ast.parse(mods[name].read_text()).body:
            if isinstance(node, ast.Assign) and any(
                    isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
                found = set(ast.literal_eval(node.value))
        out[name] = found
    return out


def named_modules(name: str, path: Path, mods: dict[str, Path],
                  offered: dict[str, set[str]]) -> set[str]:
    """The modules of torchfit the imports of ``path`` (module ``name``; an app where ``name``
    is not in ``mods``) name, resolved as the docstring says."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]

    def known(target: str) -> str:
        while target and target not in mods:
            target = target.rsplit(".", 1)[0] if "." in target else ""
        return target

    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {known(a.name) for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = imported_module(package, node)
            source = known(module)
            for alias in node.names:
                if source == module and alias.name in offered.get(source, set()):
                    found.add(source)                       # the face's export
                elif f"{module}.{alias.name}" in mods:
                    found.add(f"{module}.{alias.name}")     # a submodule (or subpackage)
                else:
                    found.add(source)
    return {target for target in found if target and target != name}


def past_faces(importers: dict[str, Path], mods: dict[str, Path]) -> set[tuple[str, str]]:
    """(importer, module) for every import of ``importers`` that passes a face."""
    pkgs, offered = packages(mods), exports(mods)
    out = set()
    for name, path in importers.items():
        inside = package_of(name, pkgs) if name in mods else ""
        for target in named_modules(name, path, mods, offered):
            if target in pkgs or target.rsplit(".", 1)[0] == "torchfit":
                continue                                    # a face
            owner = package_of(target, pkgs)
            if inside == owner or inside.startswith(owner + "."):
                continue                                    # inside its own package
            out.add((name, target))
    return out


def apps() -> dict[str, Path]:
    return {f"experiments.{p.stem}": p for p in sorted((REPO / "experiments").glob("*.py"))}


def app_imports(mods: dict[str, Path]) -> set[tuple[str, str]]:
    """(app, module of torchfit) for every import of an app outside :data:`APP_FACES`."""
    offered = exports(mods)
    return {(name, target) for name, path in apps().items()
            for target in named_modules(name, path, mods, offered)
            if target.startswith("torchfit") and target not in APP_FACES}


def test_imports_across_parts_name_the_package():
    found = past_faces(modules(), modules())
    new = sorted(found - set(PAST_A_FACE))
    stale = sorted(set(PAST_A_FACE) - found)
    assert not new, "imports past a package's face (name the package, export the name from " \
        "its __init__.py's __all__): " + ", ".join(f"{m} -> {t}" for m, t in new)
    assert not stale, "PAST_A_FACE entries no import needs any more (drop them): " + \
        ", ".join(f"{m} -> {t}" for m, t in stale)
    assert all(why.strip() for why in PAST_A_FACE.values()), "every entry says why"


def test_the_apps_import_the_run():
    found = app_imports(modules())
    new = sorted(found - set(APP_PAST_A_FACE))
    stale = sorted(set(APP_PAST_A_FACE) - found)
    assert not new, f"apps importing past {sorted(APP_FACES)}: " + \
        ", ".join(f"{m} -> {t}" for m, t in new)
    assert not stale, "APP_PAST_A_FACE entries no import needs any more (drop them): " + \
        ", ".join(f"{m} -> {t}" for m, t in stale)


def test_mesh_does_not_depend_on_its_formats():
    """The formats build a :class:`~torchfit.mesh.Animation` out of mesh's modules; no module
    of mesh outside ``mesh.formats`` imports it (mesh's face re-exports its readers)."""
    edges = graph()
    inward = sorted(f"{m} -> {d}" for m, deps in edges.items() for d in deps
                    if m.startswith("torchfit.mesh.") and not m.startswith("torchfit.mesh.formats")
                    and d.startswith("torchfit.mesh.formats"))
    assert not inward, inward


def test_the_face_rule_can_fail(tmp_path):
    root = tmp_path / "torchfit"
    for package in ("", "a", "a/sub", "b"):
        (root / package).mkdir(exist_ok=True)
    files = {
        "__init__.py": "",
        "errors.py": "",
        "a/__init__.py": "from .inner import Thing\n__all__ = ['Thing']\n",
        "a/inner.py": "from ..errors import Error\nfrom .sub.deep import x\n",
        "a/sub/__init__.py": "from .deep import x\n__all__ = ['x']\n",
        "a/sub/deep.py": "from ..inner import Thing\n",          # its parent's module: inside
        "b/__init__.py": "",
        "b/user.py": ("from ..a import Thing\nfrom ..a.inner import Thing\n"
                      "from ..a import sub\nimport torchfit.a.sub.deep\n"),
    }
    for file, text in files.items():
        (root / file).write_text(text)
    mods = {}
    for path in root.rglob("*.py"):
        parts = list(path.relative_to(tmp_path).with_suffix("").parts)
        if parts[-1] == "__init__" and len(parts) > 1:
            parts = parts[:-1]
        mods[".".join(parts)] = path
    assert past_faces(mods, mods) == {("torchfit.a.inner", "torchfit.a.sub.deep"),
                                      ("torchfit.b.user", "torchfit.a.inner"),
                                      ("torchfit.b.user", "torchfit.a.sub.deep")}


def test_the_checks_can_fail():
    # what a solver importing the physics, or reporting importing a solver, would look like
    assert forbidden({"torchfit.solvers.x": {"torchfit.physics.equilibrium"},
                      "torchfit.reporting.x": {"torchfit.solvers.base"},
                      "torchfit.problems.x": {"torchfit.solvers"}}) == [
        "torchfit.problems.x -> torchfit.solvers", "torchfit.reporting.x -> torchfit.solvers.base",
        "torchfit.solvers.x -> torchfit.physics.equilibrium"]
    assert "torchfit.solvers" in imports_of("torchfit.run.x", PACKAGE / "run" / "solver.py",
                                            set(modules()))
