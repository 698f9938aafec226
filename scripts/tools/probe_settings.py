"""Probe every setting of the fit app with bad values and classify how each is refused.

    .venv/bin/python scripts/tools/probe_settings.py --out probe.json           # everything
    .venv/bin/python scripts/tools/probe_settings.py --only spring1d --limit 10  # a quick look
    .venv/bin/python scripts/tools/probe_settings.py --list                      # the sections

The settings come from the composed config (Hydra's compose over ``conf/``, so the schema
dataclasses of ``torchfit/config.py`` and their YAML overrides): one section per problem of
``conf/problem/`` (its ``problem.*`` keys), one per solver of ``conf/solver/`` (its
``solver.*`` keys, on spring1d) and ``top`` (the top level of ``experiments/fit.py``: threads,
resume, init, ...). Each setting gets a few bad values chosen from its type
(:func:`bad_values`): numbers a negative, zero, nan, inf, 1e12 and a string; lists a wrong
length and non-numbers; booleans a string; strings a misspelt choice, or a missing file for
a path-like key. Each case runs the real app in a subprocess::

    python experiments/fit.py problem=<p> [solver=<s>] <small sizes> <key>=<value>
        hydra.run.dir=<tmp>/<case>

with ``solver.max_iter=1`` and the problem's small sizes (:data:`SMALL`), a per-case
timeout (``--timeout``, 20 s) and ``--workers`` (2) at a time, and classifies the outcome
(:func:`classify`):

- ``PASS``: exit 2, exactly one stderr line, starting ``error:`` and naming the setting (its
  last key component), and the run directory absent or empty (the promise of bad input);
- ``ACCEPTED``: exit 0, the value was legal after all (listed apart; a fault only if absurd);
- ``FAIL``: anything else (a traceback, exit 1, several lines, the setting not named, files
  left behind); ``reason`` says which;
- ``TIMEOUT``: still running at the timeout (a value that is not size-checked).

Prints the totals per section and every FAIL and TIMEOUT with its first stderr line, and
writes every case to ``--out`` (JSON). A maintenance tool: it reports, it fixes nothing.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Optional

REPO = Path(__file__).resolve().parents[2]
OUTCOMES = ("PASS", "ACCEPTED", "FAIL", "TIMEOUT")

#: base overrides that keep each problem's run short (a case on one of these keys drops it)
SMALL: dict[str, list[str]] = {
    "spring1d": [],
    "spring1d_dynamic": ["problem.n=8", "problem.duration=0.5", "problem.frames=5"],
    "poisson2d": ["problem.N=12"],
    "membrane2d": ["problem.nx=16", "problem.ny=4"],
    "membrane2d_dynamic": ["problem.nx=16", "problem.ny=4", "problem.duration=0.2"],
    "arm3d": ["problem.tet_edge_length=0.1", "problem.frames=[0,11]"],
    "arm3d_short": ["problem.tet_edge_length=0.1", "problem.frames=[0,11]"],
    "animation": ["problem.tet_edge_length=0.1", "problem.frames=[0,1]"],
}
#: sections of a problem with a switch on (``name@switch``: the problem's settings probed with
#: it, where settings unused without it come into play): the rigged bodies in time
SWITCHED: dict[str, list[str]] = {
    "arm3d@dynamic": ["problem.dynamic=true", "problem.substeps=1"],
    "animation@dynamic": ["problem.dynamic=true", "problem.substeps=1"],
}
#: key components that name a file or folder: their bad value is a missing path
PATH_WORDS = ("path", "dir", "file", "init", "data", "weights", "mesh", "cache")
MISSING_PATH = "/nonexistent/torchfit_probe/missing"


@dataclass
class Case:
    """One bad value of one setting: ``section`` (a problem, ``solver:<name>`` or ``top``),
    ``key`` (dotted), ``value`` (the override's right-hand side), ``kind`` (the type it was
    chosen from) and the command's ``overrides`` before ``hydra.run.dir``."""
    section: str
    key: str
    value: str
    kind: str
    overrides: list[str]
    outcome: str = ""
    reason: str = ""
    returncode: Optional[int] = None
    first_line: str = ""
    stderr_lines: int = 0
    left: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def name(self) -> str:
        safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in f"{self.key}={self.value}")
        return f"{self.section.replace(':', '_').replace('@', '_')}__{safe}"[:120]


# ---------------------------------------------------------------------------- settings

def _compose(overrides: list[str]):
    """The composed fit config for ``overrides`` (no ``hydra`` node)."""
    sys.path.insert(0, str(REPO))
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from torchfit.config import register_configs
    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        return compose(config_name="fit", overrides=overrides)


def _kind(node: Any, value: Any) -> str:
    """``int``, ``float``, ``bool``, ``str``, ``list``, ``dict`` or ``any`` for a config node."""
    from omegaconf import DictConfig, ListConfig
    from omegaconf.nodes import BooleanNode, EnumNode, FloatNode, IntegerNode, StringNode
    if isinstance(node, ListConfig):
        return "list"
    if isinstance(node, DictConfig):
        return "dict"
    for cls, name in ((BooleanNode, "bool"), (IntegerNode, "int"), (FloatNode, "float"),
                      (StringNode, "str"), (EnumNode, "str")):
        if isinstance(node, cls):
            return name
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "float"
    if isinstance(value, str):
        return "str"
    return "any"


def leaves(cfg: Any, prefix: str) -> Iterable[tuple[str, str, Any]]:
    """``(dotted key, kind, value)`` of every leaf setting under ``cfg`` (lists are leaves)."""
    from omegaconf import DictConfig, OmegaConf
    for key in cfg.keys():
        node = cfg._get_node(key)
        dotted = f"{prefix}{key}"
        try:
            value = OmegaConf.to_container(node) if not _is_value(node) else node._value()
        except Exception:           # a ??? or an interpolation: its type is all we need
            value = None
        if isinstance(node, DictConfig) and node._is_none() is False and len(node) > 0:
            yield from leaves(node, dotted + ".")
        else:
            yield dotted, _kind(node, value), value


def _is_value(node: Any) -> bool:
    from omegaconf import ValueNode
    return isinstance(node, ValueNode)


def _numbers(kind: str) -> list[str]:
    if kind == "int":
        return ["-1", "0", "1000000000000", "abc"]
    return ["-1", "0", "nan", "inf", "1e12", "abc"]


def bad_values(key: str, kind: str, value: Any) -> list[tuple[str, str]]:
    """``(override value, kind)`` bad values for a setting of type ``kind`` now ``value``."""
    last = key.rsplit(".", 1)[-1].lower()
    if kind in ("int", "float"):
        return [(v, kind) for v in _numbers(kind)]
    if kind == "bool":
        return [("maybe", kind)]
    if kind == "list":
        n = len(value) if isinstance(value, list) else 0
        wrong = "[1.0]" if n != 1 else "[1.0,2.0]"
        return [(wrong, "list"), ("[a,b]", "list"), ("abc", "list")]
    if kind == "dict":
        return [("abc", kind)]
    if any(w in last for w in PATH_WORDS):
        return [(MISSING_PATH, "path")]
    if kind == "str":
        return [((value + "x") if isinstance(value, str) and value else "nosuchchoice", "choice")]
    # any (null default or untyped): a string and a negative number
    return [("abc", kind), ("-1", kind)]


def _without(base: list[str], key: str) -> list[str]:
    return [o for o in base if o.split("=", 1)[0] != key]


def cases_for(section: str, arm_path: str | None) -> list[Case]:
    """Every case of ``section`` (a problem name, ``solver:<name>`` or ``top``)."""
    if section.startswith("solver:"):
        solver = section.split(":", 1)[1]
        choose, prefix, small = ["problem=spring1d", f"solver={solver}"], "solver", []
    elif section == "top":
        choose, prefix, small = ["problem=spring1d"], "", []
    else:
        problem = section.split("@", 1)[0]
        choose, prefix = [f"problem={problem}"], "problem"
        small = [*SMALL.get(problem, []), *SWITCHED.get(section, [])]
        if problem == "animation":
            small.append(f"problem.path={arm_path or MISSING_PATH}")
    base = [*choose, "solver.max_iter=1", *small]
    cfg = _compose(base)
    if prefix:
        items = leaves(cfg[prefix], prefix + ".")
    else:
        items = ((k, kind, v) for k, kind, v in leaves(cfg, "")
                 if k.split(".")[0] not in ("problem", "solver"))
    out = []
    for key, kind, value in items:
        if key in ("problem.name", "solver.name"):
            continue
        for bad, why in bad_values(key, kind, value):
            out.append(Case(section, key, bad, why, [*_without(base, key), f"{key}={bad}"]))
    return out


def sections() -> list[str]:
    problems = sorted(p.stem for p in (REPO / "conf" / "problem").glob("*.yaml"))
    solvers = sorted(p.stem for p in (REPO / "conf" / "solver").glob("*.yaml"))
    return [*problems, *SWITCHED, *(f"solver:{s}" for s in solvers), "top"]


# ---------------------------------------------------------------------------- outcomes

def classify(case: Case, returncode: Optional[int], stderr: str, run_dir: Path) -> Case:
    """Set ``case``'s outcome from the app's exit status (None: timed out), stderr and what
    is left in ``run_dir``."""
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    case.returncode = returncode
    case.stderr_lines = len(lines)
    case.first_line = next((ln for ln in lines if ln.startswith("error:")),
                           next((ln for ln in lines if "Error" in ln), lines[0] if lines else ""))
    case.first_line = case.first_line[:400]
    case.left = sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*")) \
        if run_dir.is_dir() else []
    setting = case.key.rsplit(".", 1)[-1]
    if returncode is None:
        case.outcome, case.reason = "TIMEOUT", "still running at the timeout"
    elif returncode == 0:
        case.outcome, case.reason = "ACCEPTED", "exit 0"
    elif returncode != 2:
        case.outcome, case.reason = "FAIL", f"exit {returncode}"
    elif any(ln.startswith("Traceback") for ln in lines):
        case.outcome, case.reason = "FAIL", "a traceback"
    elif len(lines) != 1:
        case.outcome, case.reason = "FAIL", f"{len(lines)} stderr lines"
    elif not lines[0].startswith("error:"):
        case.outcome, case.reason = "FAIL", "the line does not start with error:"
    elif setting not in lines[0]:
        case.outcome, case.reason = "FAIL", f"the line does not name {setting}"
    elif case.left:
        case.outcome, case.reason = "FAIL", f"{len(case.left)} files left"
    else:
        case.outcome, case.reason = "PASS", ""
    if returncode is not None and returncode != 0 and lines and any(
            ln.startswith("Traceback") for ln in lines) and case.outcome == "FAIL":
        case.reason = case.reason if "traceback" in case.reason else case.reason + ", a traceback"
    return case


def run_case(case: Case, root: Path, timeout: float) -> Case:
    """Run ``case`` through ``experiments/fit.py`` and classify it; its directory is removed."""
    run_dir = root / case.name
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env.setdefault("TORCHFIT_CACHE_DIR", str(root / "_cache"))
    cmd = [sys.executable, "experiments/fit.py", *case.overrides, f"hydra.run.dir={run_dir}"]
    start = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: os.nice(10))
    try:
        _, stderr = proc.communicate(timeout=timeout)
        code: Optional[int] = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, stderr = proc.communicate()
        code = None
    case.wall_s = round(time.monotonic() - start, 2)
    classify(case, code, stderr or "", run_dir)
    shutil.rmtree(run_dir, ignore_errors=True)
    return case


def totals(cases: list[Case]) -> dict[str, dict[str, int]]:
    """Counts of each outcome per section, and ``all``."""
    out: dict[str, dict[str, int]] = {}
    for c in cases:
        for s in (c.section, "all"):
            row = out.setdefault(s, {o: 0 for o in OUTCOMES})
            row[c.outcome] += 1
    if "all" in out:
        out["all"] = out.pop("all")
    return out


def report(cases: list[Case]) -> str:
    lines = [f"{'section':34s} " + " ".join(f"{o:>8s}" for o in OUTCOMES) + "    total"]
    for s, row in totals(cases).items():
        lines.append(f"{s:34s} " + " ".join(f"{row[o]:8d}" for o in OUTCOMES)
                     + f" {sum(row.values()):8d}")
    for outcome in ("FAIL", "TIMEOUT", "ACCEPTED"):
        chosen = [c for c in cases if c.outcome == outcome]
        if chosen:
            lines.append(f"\n{outcome} ({len(chosen)}):")
            lines += [f"  [{c.section}] {c.key}={c.value}: {c.reason}"
                      + (f" | {c.first_line}" if c.first_line and outcome != "ACCEPTED" else "")
                      for c in chosen]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", action="append", help="a section (problem name, solver:<name>, "
                    "top); repeatable; default: all")
    ap.add_argument("--limit", type=int, help="at most N cases per section")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds per case")
    ap.add_argument("--arm-path", help="an animation folder for problem=animation "
                    "(scripts/write_arm.py <folder> --n-frames 16: frames 0 and 1 are 0 and "
                    "40 degrees, one implicit step apart in the section in time; with "
                    "--n-frames 2 the elbow bends 120 degrees in that step, which Newton "
                    "cannot take on some meshes)")
    ap.add_argument("--out", type=Path, help="JSON of every case")
    ap.add_argument("--list", action="store_true", help="print the sections and case counts")
    args = ap.parse_args(argv)
    known = sections()
    chosen = args.only or known
    for s in chosen:
        if s not in known:
            print(f"error: --only {s}: not a section; the sections are {', '.join(known)}",
                  file=sys.stderr)
            return 2
    if args.out and not args.out.parent.is_dir():
        print(f"error: --out {args.out}: the folder {args.out.parent} does not exist",
              file=sys.stderr)
        return 2
    cases = []
    for s in chosen:
        found = cases_for(s, args.arm_path)
        cases += found[:args.limit] if args.limit else found
        if args.list:
            print(f"{s}: {len(found)} cases")
    if args.list:
        return 0
    with tempfile.TemporaryDirectory(prefix="probe_settings_") as tmp:
        with ThreadPoolExecutor(max_workers=max(1, args.workers)) as pool:
            done = list(pool.map(lambda c: run_case(c, Path(tmp), args.timeout), cases))
    print(report(done))
    if args.out:
        args.out.write_text(json.dumps({"totals": totals(done),
                                        "cases": [asdict(c) for c in done]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
