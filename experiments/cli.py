"""The command line of the Hydra apps before Hydra reads it: help, paths, unreadable overrides.

* ``--help`` / ``-h``: what the command does, the settings a TD uses and where the rest is
  documented (exit 0, nothing written); Hydra's own help stays at ``--hydra-help``, and
  ``--cfg job``, ``--info`` and ``-m`` reach Hydra unchanged.
* Paths are where the user typed them: a relative value of :data:`PATH_KEYS` is made
  absolute against the current directory before Hydra composes (the scripts do not change
  directory), so that every error names the absolute path tried and a run's
  ``.hydra/config.yaml`` names files that a later ``simulate`` or ``resume`` from another
  directory finds.
* An override Hydra's lexer cannot read (a value with a space the shell split in two, a
  bracket) is one ``error:`` line saying how to quote it (exit 2, nothing written).
* :func:`unknown_setting`: the one line for a misspelt or unknown key (the nearest valid
  one, and where the settings are documented), shared by the app's checks of the composed
  config and its reading of Hydra's composition error.
"""
from __future__ import annotations

import dataclasses
import difflib
import inspect
import os
import sys
from pathlib import Path
from typing import Iterable, NoReturn

REPO = Path(__file__).resolve().parents[1]

#: Overrides whose value is a path (a file or directory the user names)
PATH_KEYS = ("problem.path", "problem.init_field", "problem.cache_dir", "init", "run",
             "hydra.run.dir", "hydra.sweep.dir")
#: Hydra's options that take a value (the next argument); ``--info``'s is optional
_VALUE_OPTIONS = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name",
                  "-cn", "--config-dir", "-cd", "--experimental-rerun"}
_INFO_CHOICES = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}
#: Where the settings are documented (named by every unknown-setting line)
SETTINGS_DOC = "docs/guide/install-and-run.md"

FIT_HELP = f"""\
usage: scripts/fit.sh [setting=value ...]     (or: python experiments/fit.py ...)

Fit the material (a Young's modulus field) of a body or a test problem so that its
simulation reproduces the animated motion. With no setting: the short arm
(problem=arm3d_short), about half a minute.

  scripts/fit.sh problem=animation problem.path=my_arm      # your rigged animation
  scripts/fit.sh problem=animation problem.path=shot.usda problem.tet_count=3000 \\
      problem.frames=[0,12,24] solver.max_iter=5            # a quick first try
  scripts/fit.sh hydra.run.dir=runs/arm resume=true         # continue a killed run

The settings a TD uses:
  problem=<name>                  animation (yours), arm3d_short (the default), arm3d,
                                  spring1d, poisson2d, membrane2d (conf/problem/)
  problem.path=<folder|file>      the animation: a folder with animation.yaml, a USD stage
                                  or a glTF file (relative paths: from this directory)
  problem.frames=[0,12,24]        the frames fitted (null: all)
  problem.validation_frames=[..]  frames held out of the fit and checked at every
  problem.validation_every=<k>    iteration (or every k-th pose)
  problem.tet_count=<n>           about n tetrahedra (3000: a quick try)
  problem.init_field=<layer.usda> start from a painted or fitted material layer
  solver=<name>                   levenberg_marquardt, gauss_newton, split_bregman, ...
  solver.max_iter=<n>             the iteration budget
  hydra.run.dir=<dir>             where the run writes (default: outputs/<problem>/<solver>/
                                  <date-time> under this directory)
  threads=<n>                     CPU threads (threads=1 on a busy machine)
  resume=true                     continue the killed run of hydra.run.dir
  init=<run>                      start from an earlier run's fitted parameters
  -m a=1,2 b=x,y                  a sweep, one job per combination

Every setting with its value: add --cfg job. Hydra's own options: --hydra-help.
Documented in {SETTINGS_DOC} (the settings, what a run writes),
docs/guide/your-character.md, docs/guide/resume.md (resume, init, exit statuses),
docs/guide/validation.md, docs/guide/sweeps.md.
"""

SIMULATE_HELP = f"""\
usage: scripts/simulate.sh run=<fitted run> [setting=value ...]
       (or: python experiments/simulate.py ...)

Simulate the material a fit found on an animation of the same body (the same rest
surface): the fit's own frames, another shot, other frames. Writes the simulated frames
(OBJ, USD), their error against the animation and result.json.

  scripts/simulate.sh run=outputs/animation/levenberg_marquardt/<date-time>
  scripts/simulate.sh run=<run> problem.path=shot2 problem.frames=null

The settings a TD uses:
  run=<dir>                       the fitted run (its directory or its params.pt); required
  problem.path=<folder|file>      another animation of the fitted body (default: the fit's;
                                  relative paths: from this directory)
  problem.frames=null             every frame of the animation (default: the fit's frames);
                                  [0,10,20]: those
  hydra.run.dir=<dir>             where it writes (default: outputs/simulate/<problem>/
                                  <date-time> under this directory)
  threads=<n>                     CPU threads

Every setting with its value: add --cfg job. Hydra's own options: --hydra-help.
Documented in docs/guide/simulate.md and {SETTINGS_DOC}.
"""

VERIFY_HELP = f"""\
usage: python experiments/verify.py [setting=value ...]

Check a problem's derivatives (Jacobian and adjoint products against finite differences,
Taylor test) at its initial guess; exit 0 when every check passes, 1 when one fails.

  python experiments/verify.py problem=spring1d
  python experiments/verify.py problem=animation problem.path=my_arm problem.tet_count=2000

The settings: problem=<name> and its problem.* settings as for scripts/fit.sh, seed=<n>,
perturbation=<h>, threads=<n>, hydra.run.dir=<dir>.
Every setting with its value: add --cfg job. Documented in docs/guide/derivatives.md and
{SETTINGS_DOC}.
"""


def fail(message: str) -> NoReturn:
    print("error: " + message, file=sys.stderr, flush=True)
    sys.exit(2)


def overrides_of(argv: list[str]) -> list[tuple[int, str]]:
    """The overrides of ``argv`` (index, text): what is neither one of Hydra's options nor
    an option's value."""
    out, skip = [], False
    for i, arg in enumerate(argv):
        if skip:
            skip = False
            continue
        if arg.startswith("-"):
            skip = arg in _VALUE_OPTIONS
            continue
        if i > 0 and argv[i - 1] in ("--info", "-i") and arg in _INFO_CHOICES:
            continue
        out.append((i, arg))
    return out


def command_line(argv: list[str], help_text: str, cwd: str | None = None) -> list[str]:
    """``argv`` as the app hands it to Hydra: exits 0 with ``help_text`` on ``--help`` or
    ``-h``; exits 2 with one line on an override that cannot be read; the paths of
    :data:`PATH_KEYS` made absolute against ``cwd`` (default: the current directory)."""
    if "--help" in argv or "-h" in argv:
        print(help_text, end="", flush=True)
        sys.exit(0)
    check_readable(argv)
    return absolute_paths(argv, cwd)


def check_readable(argv: list[str]) -> None:
    """Exit 2 with one line where an override is not ``key=value`` (the shell split a value
    at a space) or Hydra's lexer cannot read it (it says how to quote it)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    listed = overrides_of(argv)
    for n, (i, arg) in enumerate(listed):
        if "=" not in arg and not arg.startswith("~"):
            previous = listed[n - 1][1] if n > 0 and listed[n - 1][0] == i - 1 else None
            if previous is not None and "=" in previous:
                key, value = previous.split("=", 1)
                fail(f"{arg!r} is not a setting (key=value): the shell split the value of "
                     f"{key} at a space; quote a value with spaces, e.g. "
                     f"'{key}=\"{value} {arg}\"'")
            fail(f"{arg!r} is not a setting (key=value, e.g. solver.max_iter=5); "
                 f"--help lists the settings")
        try:
            parser.parse_override(arg)
        except HydraException as error:
            key, value = arg.split("=", 1) if "=" in arg else (arg, "")
            why = " ".join(str(error).split("\n")[0].split())
            fail(f"cannot read the override {arg!r} ({why}): quote a value holding spaces or "
                 f"any of ()[]{{}},:=, e.g. '{key}=\"{value}\"'")


def _absolute(text: str, cwd: str) -> str:
    if not text or text.startswith("${") or text in ("null", "???"):
        return text
    return os.path.normpath(os.path.join(cwd, os.path.expanduser(text)))


def _as_value(text: str, quoted: bool, parser: object) -> str:
    """``text`` as an override value: quoted where it was, or where Hydra would read the
    bare text otherwise (a space, a bracket)."""
    from hydra.core.override_parser.types import Quote, QuotedString
    from hydra.errors import HydraException

    if not quoted:
        try:
            if parser.parse_override(f"k={text}")._value == text:  # type: ignore[attr-defined]
                return text
        except HydraException:
            pass
    return QuotedString(text, Quote.double).with_quotes()


def absolute_paths(argv: list[str], cwd: str | None = None) -> list[str]:
    """``argv`` with each relative value of :data:`PATH_KEYS` (a plain or quoted string, or
    a sweep's choices ``a,b``) joined to ``cwd``; interpolations, ``null`` and the other
    sweeps (``glob(...)``) as they are."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import ChoiceSweep, QuotedString
    from hydra.errors import HydraException

    cwd = cwd or os.getcwd()
    parser = OverridesParser.create()
    out = list(argv)
    for i, arg in overrides_of(argv):
        key, _, _ = arg.partition("=")
        if key.lstrip("+~") not in PATH_KEYS or "=" not in arg:
            continue
        try:
            override = parser.parse_override(arg)
        except HydraException:
            continue        # Hydra reports it
        value = override._value

        def one(element: object) -> str | None:
            if isinstance(element, QuotedString):
                return _as_value(_absolute(element.text, cwd), True, parser)
            if isinstance(element, str):
                return _as_value(_absolute(element, cwd), False, parser)
            return None

        if isinstance(value, ChoiceSweep) and not value.simple_form:
            continue        # choice(...): as it is
        elements = value.list if isinstance(value, ChoiceSweep) else [value]
        made = [one(e) for e in elements]
        if any(m is None for m in made):
            continue
        out[i] = f"{key}={','.join(m for m in made if m is not None)}"
    return out


def _schemas() -> dict[str, tuple[type, str]]:
    """Config dataclasses by class name: (the class, what it configures)."""
    from torchfit import PROBLEMS, SOLVERS
    from torchfit.config import FitConfig, SimulateConfig, VerifyConfig

    out: dict[str, tuple[type, str]] = {}
    for name, entry in PROBLEMS.items():
        out.setdefault(entry.config_class.__name__, (entry.config_class, f"problem={name}"))
    for name, entry in SOLVERS.items():
        out.setdefault(entry.config_class.__name__, (entry.config_class, f"solver={name}"))
    for schema in (FitConfig, SimulateConfig, VerifyConfig):
        out[schema.__name__] = (schema, "top-level")
    return out


def schema_named(name: str) -> tuple[type, str] | None:
    return _schemas().get(name)


def _source(cls: type) -> str:
    try:
        return str(Path(inspect.getsourcefile(cls) or "").resolve().relative_to(REPO))
    except (TypeError, ValueError):
        return cls.__module__


def unknown_setting(shown: str, key: str, segment: int, cls: type, what: str) -> str:
    """The line for the unknown key ``key`` (shown as ``shown``, e.g. with its value), whose
    ``segment``-th dotted part is not a field of the dataclass ``cls`` (``what`` it
    configures: ``solver=levenberg_marquardt``): the nearest field, where they are listed."""
    known = [f.name for f in dataclasses.fields(cls)]
    parts = key.lstrip("+~").split(".")
    close = difflib.get_close_matches(parts[segment], known, n=1, cutoff=0.6) \
        if segment < len(parts) else []
    hint = f" (did you mean {'.'.join([*parts[:segment], close[0], *parts[segment + 1:]])}?)" \
        if close else ""
    listed = f"; the known ones are {', '.join(known)}" if not close or len(known) <= 20 else ""
    return (f"unknown setting {shown}{hint}{listed}; {what} settings: the fields of "
            f"{cls.__name__} ({_source(cls)}), with their values: add --cfg job; "
            f"{SETTINGS_DOC}")


def check_sections(config: dict, sections: Iterable[str]) -> str | None:
    """The line for the first key of ``config``'s ``sections`` (``problem``, ``solver``:
    chosen by their ``name``) that is no field of its config class (``+problem.foo=1``,
    which Hydra adds); ``None`` where all are known."""
    from torchfit import PROBLEMS, SOLVERS

    registries = {"problem": PROBLEMS, "solver": SOLVERS}
    for section in sections:
        values = config.get(section)
        if not isinstance(values, dict) or values.get("name") not in registries[section]:
            continue
        cls = registries[section][values["name"]].config_class
        names = {f.name for f in dataclasses.fields(cls)}
        for key, value in values.items():
            if key not in names:
                return unknown_setting(f"{section}.{key}={value}", f"{section}.{key}", 1, cls,
                                       f"{section}={values['name']}")
    return None
