"""What the Hydra apps share: exit statuses, one-line errors, and leaving nothing behind.

Exit statuses of ``experiments/fit.py``, ``experiments/verify.py`` and
``experiments/simulate.py``:

* 0: done (verify: every check passed);
* 1: the work ran and failed (a derivative check failed; the simulation failed during a
  fit: the traceback is in the job's log);
* 2: bad input, nothing run: an invalid setting or an override Hydra cannot compose (a
  misspelt key: the line names the nearest one, :mod:`experiments.cli`), or a run
  directory that cannot be written (``error: <one line>`` on standard error, Hydra's own
  block not shown). The run
  directory is left as it was: removed when the run created it, and a refused resume puts
  the earlier run's ``.hydra/`` back. In a sweep, a value Hydra cannot compose stops the
  whole sweep before any job runs (Hydra composes every job first); settings that compose
  but are invalid fail only their own job (``result.json`` says ``failed``); a sweep whose
  job directory name would exceed 255 bytes is refused naming the override that makes it
  long; a refused sweep leaves no ``multirun.yaml`` behind;
* 3 (the fit app under torchrun): another rank stopped answering (killed, or its machine
  went away): one line from rank 0 naming it and the command that resumes the run;
* 130: interrupted (Ctrl-C); 143: terminated (SIGTERM, what a scheduler sends): both with
  the hint to resume.

A single run with ``hydra.run.dir=<dir>`` holds that directory (:mod:`torchfit.run.lock`)
from before Hydra writes ``.hydra/`` into it to the end of the process: a second run into
it is refused at once (exit 2, one line naming the pid and host holding it) and writes
nothing.
"""
from __future__ import annotations

import contextlib
import dataclasses
import difflib
import errno
import logging
import os
import re
import shutil
import signal
import sys
import threading
from pathlib import Path
from typing import Any, Callable, NoReturn

from omegaconf.errors import OmegaConfBaseException

from experiments.cli import check_sections, schema_named, unknown_setting
from torchfit.errors import (WRITE_ERRNOS, ConfigurationError, write_failure,
                             write_remedy)

#: Exceptions that mean "the input is wrong" (exit 2, one line, nothing left behind).
BAD_INPUT = (ConfigurationError, OmegaConfBaseException, OSError)
#: exit status of a torchrun job whose other rank stopped answering (the run resumable)
RANK_LOST = 3


def one_line(error: BaseException | str) -> str:
    return " ".join(str(error).split())


#: errno values of a write that failed for a reason the user can act on: a full file
#: system or quota, a file-size limit (``ulimit -f``), a read-only or forbidden place
_NO_SPACE = tuple(sorted(WRITE_ERRNOS))


def no_space(error: BaseException) -> bool:
    """Whether ``error`` (or what it was raised from) is a write that failed for a reason the
    user can act on (:func:`torchfit.errors.write_failure`: a full disk, a file-size limit,
    a read-only place; USD's errors of those included)."""
    return write_failure(error) is not None


def _no_space_error(error: BaseException) -> OSError:
    """The failed write in ``error``'s chain, the one that names a file if any."""
    chain = []
    while error is not None:
        found = write_failure(error)
        if found is not None:
            chain.append(found)
        error = error.__cause__ or error.__context__
    return next((e for e in chain if e.filename), chain[0])


def _full(error: OSError, run_dir: Path) -> str:
    """What happened to a write into ``run_dir``, as the start of the line."""
    if error.errno == errno.EFBIG:
        return f"a file of {run_dir} reached the file-size limit"
    what = {errno.EDQUOT: "the disk quota is exhausted", errno.ENOSPC:
            "no space left on the device"}.get(error.errno, (error.strerror or "").lower() or
                                                "a write failed")
    return f"{what} of {run_dir}"


def no_space_line(error: BaseException, run_dir: Path, resume_command: str) -> str:
    """The one line for a run stopped by a failed write (a full disk, a file-size limit): the
    file being written, what to do and how to continue (the checkpoint and every file were
    written atomically: nothing is half)."""
    error = _no_space_error(error)
    where = f" while writing {error.filename}" if error.filename else ""
    return (f"{_full(error, run_dir)}{where}; {write_remedy(error)}, then continue with: "
            f"{resume_command}")


def no_space_at_start_line(error: BaseException, run_dir: Path) -> str:
    """The one line for a failed write before the task ran (the lock, Hydra's ``.hydra/``):
    nothing of the run was written, the same command runs once the cause is gone."""
    error = _no_space_error(error)
    where = f" while writing {error.filename}" if error.filename else ""
    return (f"{_full(error, run_dir)}{where}, before the run started (nothing of it "
            f"was written); {write_remedy(error)}, then run the same command again")


def _name_hydras_files() -> None:
    """Hydra writes ``.hydra/*.yaml`` with ``open(...)`` and ``write``; a full disk raises
    there without a file name: give it the file's (Hydra reports the error as text)."""
    import hydra.core.utils as hydra_utils

    save = hydra_utils._save_config
    if getattr(save, "_names_its_file", False):
        return

    def _save_config(cfg: Any, filename: str, output_dir: Path) -> None:
        try:
            save(cfg, filename, output_dir)
        except OSError as error:
            if error.errno is None or error.filename:
                raise
            raise OSError(error.errno, error.strerror or str(error),
                          str(Path(output_dir) / filename)) from None

    _save_config._names_its_file = True  # type: ignore[attr-defined]
    hydra_utils._save_config = _save_config


#: Hydra's report of an OSError of a full disk: ``OSError: [Errno 28] ...: '<file>'``
_HYDRA_NO_SPACE = re.compile(r"(?:OSError|\w+Error): \[Errno (%s)\] ([^\n]*?)(?:: '([^'\n]+)')?$"
                             % "|".join(str(n) for n in _NO_SPACE), re.MULTILINE)


def _quiet_thread_errors(args: threading.ExceptHookArgs) -> None:
    """A writer thread (TensorBoard's) that hits a full disk: its error reaches the main
    thread at the next write, which reports it in one line; no traceback on the console."""
    if issubclass(args.exc_type, OSError) and getattr(args.exc_value, "errno", None) in _NO_SPACE:
        logging.getLogger("torchfit.run").debug("thread %s: %s", args.thread, args.exc_value)
        return
    threading.__excepthook__(args)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the process is (like Ctrl-C's KeyboardInterrupt): the run ends
    through its ``finally`` blocks, its lock released; the app exits 143."""


def _terminate(signum: int, frame: Any) -> None:
    raise Terminated()


class RunDirGuard:
    """Remembers what a run directory held before Hydra wrote into it, to restore it when the
    job is refused or did nothing (Hydra writes ``.hydra/`` and opens ``<job>.log`` before
    the task runs)."""

    def __init__(self, argv: list[str]) -> None:
        self.run_dir = next((Path(a.split("=", 1)[1]) for a in argv
                             if a.startswith("hydra.run.dir=")), None)
        #: the job makes the directory (absent or empty before it): a refusal removes it
        #: whole, whatever the job wrote before it was refused (a start that cannot be
        #: simulated is found after the outputs opened)
        self.fresh = self.run_dir is not None and (
            not self.run_dir.exists() or (self.run_dir.is_dir() and not any(self.run_dir.iterdir())))
        self.snapshot()

    def snapshot(self) -> None:
        """Read ``.hydra/`` and the sizes of the ``*.log`` files (again: once the run holds
        its directory, before Hydra writes)."""
        self.saved: dict[Path, bytes] = {}
        self.logs: dict[Path, int] = {}
        if self.run_dir is not None and (self.run_dir / ".hydra").is_dir():
            self.saved = {p: p.read_bytes() for p in (self.run_dir / ".hydra").iterdir()
                          if p.is_file()}
        if self.run_dir is not None and self.run_dir.is_dir():
            self.logs = {p: p.stat().st_size for p in self.run_dir.glob("*.log") if p.is_file()}

    def undo(self, run_dir: Path) -> None:
        """Leave ``run_dir`` as it was before this job."""
        if self.saved and all(p.parent.parent.resolve() == run_dir.resolve() for p in self.saved):
            self.restore(run_dir)
            return
        if self.fresh and self.run_dir is not None and run_dir.resolve() == self.run_dir.resolve():
            remove_job_directory(run_dir)
            return
        remove_if_only_hydra(run_dir)

    def restore(self, run_dir: Path) -> None:
        """Put back ``.hydra/`` and cut the logs back to their sizes (a job that changed
        nothing, e.g. the resume of a finished run, leaves the directory byte-identical)."""
        if not self.saved or any(p.parent.parent.resolve() != run_dir.resolve()
                                 for p in self.saved):
            return
        for handler in logging.getLogger().handlers:
            handler.flush()
        for path, content in self.saved.items():
            if not path.is_file() or path.read_bytes() != content:
                path.write_bytes(content)
        for path, size in self.logs.items():
            if path.is_file() and path.stat().st_size > size:
                os.truncate(path, size)


def remove_if_only_hydra(run_dir: Path) -> None:
    """Delete ``run_dir`` if it holds nothing but Hydra's ``.hydra/`` and ``*.log`` files."""
    if not run_dir.is_dir() or any(not ((e.name == ".hydra" and e.is_dir()) or
                                        (e.suffix == ".log" and e.is_file()))
                                   for e in run_dir.iterdir()):
        return
    remove_job_directory(run_dir)


def remove_job_directory(run_dir: Path) -> None:
    """Delete ``run_dir``, a directory this job made, closing Hydra's handler of its log."""
    for handler in list(logging.getLogger().handlers):    # Hydra's handler of <job>.log
        filename = getattr(handler, "baseFilename", None)
        if filename and Path(filename).resolve().parent == run_dir.resolve():
            logging.getLogger().removeHandler(handler)
            handler.close()
    shutil.rmtree(run_dir, ignore_errors=True)


def check_top_level(config: dict, schema: type) -> None:
    """Refuse a key the app's schema (a dataclass) does not have, at the top level or in
    ``problem`` / ``solver`` (their config classes): Hydra accepts ``+foo=1`` and
    ``+problem.foo=1``, and its hint for a misspelt key (``contination=true``) is to add
    one. The line names the nearest key and where the settings are documented."""
    known = [f.name for f in dataclasses.fields(schema)]
    unknown = [key for key in config if key not in known]
    if unknown:
        raise ConfigurationError(unknown_setting(f"{unknown[0]}={config[unknown[0]]}",
                                                 unknown[0], 0, schema, "top-level")
                                 .replace("unknown setting", "unknown top-level setting", 1))
    line = check_sections(config, [s for s in ("problem", "solver") if s in known])
    if line is not None:
        raise ConfigurationError(line)


def checked_config(cfg: Any, schema: type, throw_on_missing: bool = True) -> dict:
    """The composed settings ``cfg`` (a ``DictConfig``) as plain containers (interpolations
    resolved, enums as their names), refused by :func:`check_top_level` against ``schema``."""
    from omegaconf import OmegaConf

    config = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=throw_on_missing,
                                    enum_to_str=True)
    assert isinstance(config, dict)
    check_top_level(config, schema)
    return config


def refuse(message: BaseException | str, run_dir: Path, guard: RunDirGuard) -> NoReturn:
    from torchfit.run import release_all

    print("error: " + one_line(message), file=sys.stderr, flush=True)
    release_all()       # the lock goes before the directory is left as it was
    guard.undo(run_dir)
    sys.exit(2)


def output_root(argv: list[str], default: str) -> Path:
    """The directory Hydra will create: ``hydra.run.dir`` / ``hydra.sweep.dir`` when given
    (without interpolations), else the default root of the config (``outputs``,
    ``multirun``) in the current directory."""
    key = "hydra.sweep.dir=" if any(a in ("-m", "--multirun") for a in argv) else "hydra.run.dir="
    given = next((a.split("=", 1)[1] for a in argv if a.startswith(key)), None)
    if given is None or "${" in given:
        return Path(default if key == "hydra.run.dir=" else "multirun")
    return Path(given)


def run_hydra_app(main: Callable[[], Any], started: Callable[[], bool],
                  default_root: str = "outputs", guard: RunDirGuard | None = None) -> None:
    """Call a ``@hydra.main`` function. A run directory that cannot be written is one
    ``error:`` line (Hydra would report it as a traceback); a config Hydra cannot compose
    (unknown option, misspelt or mistyped override: Hydra exits 1 before the task) exits 2
    like every other bad input. With a ``guard`` (the fit app), a single run into a given
    ``hydra.run.dir`` holds it first (module docstring), and the guard reads it then."""
    from torchfit.run import acquire, check_writable, release_all

    argv = sys.argv[1:]
    root = output_root(argv, default_root).resolve()
    try:
        check_writable(root)
        if guard is not None and guard.run_dir is not None and "${" not in str(guard.run_dir) \
                and not any(a in ("-m", "--multirun") for a in argv):
            acquire(root)
            guard.snapshot()
    except OSError as error:        # RunDirectoryError, RunLockedError, a failed mkdir
        line = no_space_at_start_line(error, root) if no_space(error) else one_line(error)
        print("error: " + line, file=sys.stderr, flush=True)
        sys.exit(2)
    _name_hydras_files()
    signal.signal(signal.SIGTERM, _terminate)
    threading.excepthook = _quiet_thread_errors
    # a log file on a full disk: no "--- Logging error ---" traceback per line on the console
    logging.raiseExceptions = False
    multirun = any(a in ("-m", "--multirun") for a in argv)
    before = _entries(root, multirun)
    stderr = _Tail(sys.stderr, started)
    sys.stderr = stderr                 # keeps Hydra's composition message to name the key
    try:
        main()
    except Terminated:      # before or after the task (the task reports its own)
        print("terminated (SIGTERM)", file=stderr.stream, flush=True)
        sys.exit(143)
    except SystemExit as exit_:
        if exit_.code == 1 and not started() and "File name too long" in stderr.tail:
            _remove_new(output_root(argv, default_root).resolve(), before, multirun)
            stderr.held = ""                # Hydra's traceback: the line below says it all
            print("error: " + long_name_reason(stderr.tail, argv), file=stderr.stream)
            sys.exit(2)
        found = sorted(_HYDRA_NO_SPACE.finditer(stderr.tail), key=lambda m: not m.group(3))
        full = found[0] if found else None
        if exit_.code == 1 and not started() and full:     # a full disk as Hydra wrote .hydra/
            stderr.held = ""                # Hydra's chained tracebacks: the line says it all
            release_all()
            if guard is not None and guard.run_dir is not None and "${" not in str(guard.run_dir):
                with contextlib.suppress(OSError):
                    guard.undo(root)
            error = OSError(int(full.group(1)), full.group(2), full.group(3))
            print("error: " + no_space_at_start_line(error, root), file=stderr.stream,
                  flush=True)
            sys.exit(2)
        if exit_.code != 1 or started() or "Traceback (most recent call last)" in stderr.tail:
            raise           # not a configuration Hydra refused: a crash (its traceback is above)
        reason = hydra_reason(stderr.tail)
        if reason.endswith(_SEE_ABOVE):
            stderr.release()            # Hydra's message, then the line that sums it up
        else:
            stderr.held = ""            # the line below says it all
        if multirun:
            _remove_new(output_root(argv, default_root).resolve(), before, multirun)
            # Hydra's basic sweeper composes every job before it launches the first: one
            # value it cannot compose stops the whole sweep, and no job has run.
            print(f"error: invalid sweep, no job was run: {reason} (Hydra composes every job "
                  "of a sweep before launching any)", file=stderr.stream)
        else:
            prefix = "" if reason.startswith("unknown setting") else "invalid configuration: "
            print(f"error: {prefix}{reason}", file=stderr.stream)
        sys.exit(2)
    finally:
        stderr.release()
        sys.stderr = stderr.stream
        release_all()


def long_name_reason(message: str, argv: list[str]) -> str:
    """One line for a job directory whose name exceeds the 255 bytes of a file name (Hydra
    names a sweep job ``<num>_<override_dirname>``): the override that makes it long."""
    match = re.search(r"File name too long: '(.*)'", message)
    parts = Path(match.group(1)).parts if match else ()
    longest = max(parts, key=lambda p: len(p.encode()), default="")
    culprit = max((a for a in argv if "=" in a and not a.startswith("hydra.")),
                  key=lambda a: sum(len(p) for p in a.split("/") if p and p in longest),
                  default="")
    key = culprit.split("=", 1)[0].lstrip("+~")
    shown = culprit if len(culprit) <= 60 else culprit[:57] + "..."
    return (f"a job directory name would have {len(longest.encode())} bytes, more than the 255 "
            f"a file name may have: the override {shown} makes it long; shorten its value, or "
            f"leave it out of the name with hydra.job.config.override_dirname.exclude_keys=[{key}] "
            "(nothing was run)")


def _entries(root: Path, multirun: bool) -> set[str] | None:
    """What the sweep root holds now (``None``: it does not exist); not for a single run."""
    if not multirun:
        return set()
    return {e.name for e in root.iterdir()} if root.is_dir() else None


def _remove_new(root: Path, before: set[str] | None, multirun: bool) -> None:
    """Remove what a refused sweep left under ``root`` that was not there before: its
    ``multirun.yaml`` and empty directories, nothing that holds any other file."""
    if not multirun or not root.is_dir():
        return
    new = [root] if before is None else [root / n for n in os.listdir(root) if n not in before]
    for path in new:
        files = [f for f in path.rglob("*") if not f.is_dir()] if path.is_dir() else [path]
        if all(f.name == "multirun.yaml" for f in files):
            shutil.rmtree(path) if path.is_dir() else path.unlink()


class _Tail:
    """A text stream that keeps the last few thousand characters, and holds what is written
    before the task starts (Hydra's messages) until :meth:`release` or the task's start."""

    def __init__(self, stream: Any, started: Callable[[], bool]) -> None:
        self.stream = stream
        self.started = started
        self.tail = ""
        self.held = ""

    def write(self, text: str) -> int:
        self.tail = (self.tail + text)[-4000:]
        if not self.started():
            self.held += text
            return len(text)
        self.release()
        return self.stream.write(text)

    def release(self) -> None:
        if self.held:
            self.stream.write(self.held)
            self.held = ""

    def flush(self) -> None:
        if self.started():
            self.release()
        self.stream.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stream, name)


_SEE_ABOVE = "see Hydra's message above"


def hydra_reason(message: str) -> str:
    """One line from Hydra's composition error: an unknown key with the nearest known one
    (:func:`~experiments.cli.unknown_setting`), an unknown option of a group with the
    nearest option and the others, else the override (or the setting, ``full_key``) and why."""
    lines = [line.strip() for line in message.splitlines() if line.strip()]
    override = next((m.group(1) for m in map(re.compile(r"Could not override '(.+)'\.").search,
                                              lines) if m), None)
    missing = next((m for m in map(re.compile(r"Key '(.+)' not in '(\w+)'").search, lines)
                    if m), None)
    full_key = next((line.split(":", 1)[1].strip() for line in lines
                     if line.startswith("full_key:")), None)
    if override and missing and full_key is not None and schema_named(missing.group(2)):
        cls, what = schema_named(missing.group(2))
        shown = next((m.group(1) for m in map(re.compile(r"use \+(\S+=.*)$").search, lines)
                      if m), override)
        return unknown_setting(shown, override, full_key.count("."), cls, what)
    group = next((m for m in map(re.compile(r"Could not find '([\w/]+)/([^'/]+)'").search,
                                 lines) if m), None)
    if group:
        start = next((i for i, line in enumerate(lines) if line.startswith("Available options")),
                     None)
        options: list[str] = []
        for line in lines[start + 1:] if start is not None else []:
            if line.endswith(":") or line.startswith(("provider=", "Set the environment")):
                break
            options.append(line)
        close = difflib.get_close_matches(group.group(2), options, n=1, cutoff=0.5)
        hint = f" (did you mean {group.group(1)}={close[0]}?)" if close else ""
        return (f"{group.group(1)}={group.group(2)} is not an option{hint}; the options: "
                f"{', '.join(options) or 'none'} (conf/{group.group(1)}/)")
    why = next((line for line in lines if not line.startswith(("full_key:", "object_type=",
                                                                 "Set the environment",
                                                                 "Error merging", "error:"))),
               _SEE_ABOVE)
    merging = next((line.split("override", 1)[1].strip() for line in lines
                    if line.startswith("Error merging override")), None)
    if merging and why != _SEE_ABOVE:
        return f"{merging}: {why}"          # the override as typed: problem.noise=abc
    return f"{full_key}: {why}" if full_key else why


def results_line(run_dir: Path, files: list[Path], also: tuple[str, ...] = ()) -> str:
    """``results: <run>/result.json (beside it: frames/, body.vtu, usd/, ...)``: every file a
    run wrote, a folder's files shown once as the folder, then ``also``."""
    names = list(dict.fromkeys(
        p.relative_to(run_dir).parts[0] + ("/" if len(p.relative_to(run_dir).parts) > 1 else "")
        for p in files if p.is_relative_to(run_dir) and p.name != "result.json"))
    return f"results: {run_dir / 'result.json'} (beside it: {', '.join([*names, *also])})"
