"""Seams, not patches: no code outside a problem's class writes the problem's attributes or
replaces its methods, and no module keeps a process-global registry that other code fills.

A collaborator reaches an object through an interface the object declares (a distributed run
plugs its pose simulation in with ``FramePoses.plug``, the seam of the body's ``poses``; a
run's mesh is an argument of ``build_problem``); scans of the source keep it that way. Tests are not scanned: a test double
may stand in for a method.
"""
from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("torchfit", "experiments", "scripts")
#: container constructors whose module-level result, mutated in a function, is a registry
MUTABLE = {"dict", "list", "set", "defaultdict", "OrderedDict", "deque"}
MUTATORS = {"append", "add", "update", "setdefault", "pop", "remove", "clear", "extend",
            "insert", "popitem", "discard", "appendleft"}


#: process state that is not a registry: what the process itself holds of the file system
PROCESS_STATE = {
    # the run-directory locks this process holds (a re-entrant count, and the directories
    # made for them): the state of lock files, released at exit
    "torchfit/run/lock.py:_held", "torchfit/run/lock.py:_created",
    # the torchfit child processes this Blender session started, one per scene: a process
    # handle cannot be a Blender property, and unregister stops every one of them
    "scripts/blender/torchfit_blender/ui.py:_RUNNING",
}


def python_files() -> list[Path]:
    return sorted(p for d in SOURCES for p in (REPO / d).rglob("*.py"))


def _names_a_problem(node: ast.expr) -> bool:
    """``problem``, ``sub_problem``, ``self.problem``, ``split.problem``, ..."""
    name = node.id if isinstance(node, ast.Name) else \
        node.attr if isinstance(node, ast.Attribute) else ""
    return name == "problem" or name.endswith("_problem")


def problem_attribute_writes(source: str, where: str = "") -> list[str]:
    """``where:line`` of every assignment to an attribute of a problem (``problem.x = ...``,
    ``setattr(problem, ...)``) in ``source``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                node.func.id == "setattr" and node.args and _names_a_problem(node.args[0]):
            found.append(f"{where}:{node.lineno}")
        for target in targets:
            for part in ast.walk(target):
                if isinstance(part, ast.Attribute) and isinstance(part.ctx, ast.Store) and \
                        _names_a_problem(part.value):
                    found.append(f"{where}:{node.lineno}")
    return sorted(set(found), key=lambda hit: int(hit.rsplit(":", 1)[1]))


def registries(source: str, where: str = "") -> list[str]:
    """Module-level containers (``NAME = {}``, ``[]``, ``dict()``, ...) that a function of
    the module mutates: process-global registries."""
    tree = ast.parse(source)
    containers = set()
    for node in tree.body:
        value = node.value if isinstance(node, (ast.Assign, ast.AnnAssign)) else None
        targets = node.targets if isinstance(node, ast.Assign) else \
            [node.target] if isinstance(node, ast.AnnAssign) else []
        mutable = isinstance(value, (ast.Dict, ast.List, ast.Set)) or (
            isinstance(value, ast.Call) and isinstance(value.func, ast.Name)
            and value.func.id in MUTABLE)
        if mutable:
            containers |= {t.id for t in targets if isinstance(t, ast.Name)}
    found = set()
    for function in ast.walk(tree):
        if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(function):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                    node.func.attr in MUTATORS and isinstance(node.func.value, ast.Name) and \
                    node.func.value.id in containers:
                found.add(f"{where}:{node.func.value.id}")
            if isinstance(node, (ast.Assign, ast.AugAssign, ast.Delete)):
                for target in (node.targets if isinstance(node, (ast.Assign, ast.Delete))
                               else [node.target]):
                    if isinstance(target, ast.Subscript) and isinstance(target.value, ast.Name) \
                            and target.value.id in containers:
                        found.add(f"{where}:{target.value.id}")
    return sorted(found)


def test_no_code_writes_a_problems_attributes_outside_its_class():
    found = [hit for path in python_files()
             for hit in problem_attribute_writes(path.read_text(), str(path.relative_to(REPO)))]
    assert not found, f"a problem's attributes written from outside it: {found}"


def test_no_module_keeps_a_process_global_registry():
    found = [hit for path in python_files()
             for hit in registries(path.read_text(), str(path.relative_to(REPO)))
             if hit not in PROCESS_STATE]
    assert not found, f"module-level containers filled by functions: {found}"


def test_the_scans_can_fail():
    patched = ("def split(problem, other):\n    problem.quasistatic = other\n"
               "    setattr(problem, 'forward_jacobian', other)\n"
               "    self.problem.data += 1\n    validation_problem.x, y = 1, 2\n")
    assert problem_attribute_writes(patched, "m") == ["m:2", "m:3", "m:4", "m:5"]
    assert problem_attribute_writes("problem.plug(split)\nx = problem.data\n") == []
    registry = ("_REGISTERED: dict = {}\n_SEEN = []\nTABLE = {'a': 1}\n"
                "def register(k, v):\n    _REGISTERED[k] = v\n"
                "def see(x):\n    _SEEN.append(x)\n    return TABLE['a']\n")
    assert registries(registry, "m") == ["m:_REGISTERED", "m:_SEEN"]
