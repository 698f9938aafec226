"""The Hydra schemas of the apps (torchfit.config): every top-level default written once.

``FitConfig`` and ``FitOptions``, ``VerifyConfig`` and ``VerifyOptions`` (``verify``'s
settings), and the keyword arguments of ``fit``, ``fit_continued``, ``verify`` and
``verification_point`` must not declare one setting with a default of their own twice: a
setting is declared with a literal default in one place and reused (by reference) elsewhere
(``fit_continued`` takes ``fit``'s arguments as they are).
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import torchfit.config as config
from torchfit.run import FitOptions, VerifyOptions, fit, fit_continued, verify
from torchfit.run.verifying import verification_point

PACKAGE = Path(config.__file__).resolve().parent
#: keyword arguments that are a schema's setting under another name
ALIASES = {"min_volume": "continuation_min_volume",
           "first_max_iter": "continuation_first_max_iter"}


def _literal(node: ast.AST | None) -> bool:
    """A default written out: a constant, a container of constants, ``lambda: [...]``, or
    ``dataclasses.field(default=...)`` / ``default_factory=...`` of one."""
    if node is None:
        return False
    if isinstance(node, ast.Constant):
        return True
    if isinstance(node, (ast.List, ast.Tuple, ast.Set)):
        return all(_literal(e) for e in node.elts)
    if isinstance(node, ast.UnaryOp):
        return _literal(node.operand)
    if isinstance(node, ast.Lambda):
        return _literal(node.body)
    if isinstance(node, ast.Call):
        return any(k.arg in ("default", "default_factory") and _literal(k.value)
                   for k in node.keywords)
    return False


def declarations(path: Path, classes: set[str], functions: set[str],
                 skip: frozenset[str] = frozenset()) -> list[tuple[str, str]]:
    """``(setting, where)`` of every literal default in ``path``: fields of the dataclasses
    ``classes``, keyword defaults of ``functions`` (but the arguments ``skip``), and
    ``_field("name", type, default=...)`` calls (the schemas built by ``make_dataclass``)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ClassDef) and node.name in classes:
            for item in node.body:
                if isinstance(item, ast.AnnAssign) and _literal(item.value):
                    found.append((item.target.id, f"{path.name}:{node.name}"))
        elif isinstance(node, ast.FunctionDef) and node.name in functions:
            args = node.args
            positional = args.posonlyargs + args.args
            pairs = list(zip(positional[len(positional) - len(args.defaults):], args.defaults))
            pairs += [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]
            for arg, default in pairs:
                if arg.arg in skip:
                    continue
                if _literal(default) and not (isinstance(default, ast.Constant)
                                              and default.value is None and arg.arg in
                                              ("run_dir", "options", "config")):
                    found.append((ALIASES.get(arg.arg, arg.arg), f"{path.name}:{node.name}()"))
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "_field" and \
                node.args and isinstance(node.args[0], ast.Constant) and _literal(node):
            found.append((node.args[0].value, f"{path.name}:_field"))
    return found


def all_declarations() -> dict[str, list[str]]:
    # fit_continued takes fit's arguments as they are: only its own are its settings
    of_fit = frozenset(inspect.signature(fit).parameters)
    sources = [
        (PACKAGE / "config.py", set(), set(), frozenset()),
        (PACKAGE / "run" / "options.py", {"ProcessOptions", "FitOptions", "VerifyOptions"},
         set(), frozenset()),
        (PACKAGE / "run" / "fitting.py", set(), {"fit"}, frozenset()),
        (PACKAGE / "run" / "continuation.py", set(), {"fit_continued"}, of_fit),
        (PACKAGE / "run" / "verifying.py", set(), {"verify", "verification_point"}, frozenset()),
    ]
    out: dict[str, list[str]] = {}
    for path, classes, functions, skip in sources:
        for name, where in declarations(path, classes, functions, skip):
            out.setdefault(name, []).append(where)
    return out


def test_every_top_level_default_is_written_once():
    twice = {name: where for name, where in all_declarations().items() if len(where) > 1}
    assert not twice, f"settings declared with a default of their own more than once: {twice}"


def test_the_check_finds_a_restated_default(tmp_path):
    restated = tmp_path / "config.py"
    restated.write_text('@dataclasses.dataclass\nclass FitConfig:\n    log_every: int = 1\n'
                        '    threads: int = dataclasses.field(default=0)\n'
                        'X = make([_field("progress", bool, default=True)])\n'
                        'def fit(problem, *, run_dir=None, resume=False, min_volume=0.25): ...\n')
    assert sorted(declarations(restated, {"FitConfig"}, {"fit"})) == [
        ("continuation_min_volume", "config.py:fit()"), ("log_every", "config.py:FitConfig"),
        ("progress", "config.py:_field"), ("resume", "config.py:fit()"),
        ("threads", "config.py:FitConfig")]


@pytest.mark.parametrize("schema,options,left_out", [
    (config.FitConfig, FitOptions, {"fold_hint"}),
    (config.VerifyConfig, VerifyOptions, set()),
])
def test_the_schemas_are_the_options(schema, options, left_out):
    schema_fields = {f.name: f for f in dataclasses.fields(schema)}
    defaults = OmegaConf.to_container(OmegaConf.structured(schema))
    for f in dataclasses.fields(options):
        if f.name in left_out:
            assert f.name not in schema_fields
            continue
        assert f.name in schema_fields, f.name
        assert defaults[f.name] == getattr(options(), f.name), f.name


def test_the_run_arguments_in_the_fit_schema_keep_their_defaults():
    defaults = OmegaConf.to_container(OmegaConf.structured(config.FitConfig))
    fit_args = inspect.signature(fit).parameters
    assert defaults["resume"] is fit_args["resume"].default is False
    assert defaults["init"] is fit_args["init"].default is None
    assert defaults["continuation_min_volume"] == \
        inspect.signature(fit_continued).parameters["min_volume"].default
    assert defaults["continuation_first_max_iter"] is \
        inspect.signature(fit_continued).parameters["first_max_iter"].default is None
    for name in ("at", "perturbation", "seed"):
        assert inspect.signature(verification_point).parameters[name].default == \
            getattr(VerifyOptions(), name)
    assert not {f.name for f in dataclasses.fields(VerifyOptions)} & set(
        inspect.signature(verify).parameters)
