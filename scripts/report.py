"""Aggregate the ``result.json`` files of a Hydra sweep or of run directories into one table.

Usage::

    python scripts/report.py multirun/seed_table/<date-time>                 # markdown on stdout
    python scripts/report.py multirun/seed_table/<date-time> --out report.md --csv report.csv
    python scripts/report.py outputs/<date>/<time> outputs/<date>/<time2>    # single runs

Each argument is a sweep directory (``multirun/<date-time>``: the job directories below
it) or one run directory (the one that holds ``.hydra/``; a single run's job has no number,
and its row is named by its directory). One row per job of the sweep, in job order: the
job's overrides (those that differ between jobs; the ones shared by every job are listed
above the table), ``u_err_inf``, ``u_err_2``, ``k_err_inf``, ``k_err_2``, ``k_err_rel_aligned`` (``k_err_rel`` as well when a problem is
not scale-free), iterations, solver wall seconds, factorisations and the stop reason. Jobs
with frames held out of the fit (``problem.validation_frames`` / ``validation_every``) add
the validation error at the chosen iteration (``validation_surface_err_mean``), its
reduction and that iteration, and the job of lowest validation error is named below the
table: how validation chooses a regularisation weight (``-m solver.mu=...``).

A job that did not produce a usable result is a row marked ``failed: <reason>``, never a
missing row:

* a ``result.json`` that says ``"status": "failed"``: the job's settings were invalid or
  its fit raised; its ``error`` line is the reason (``experiments/fit.py`` writes it);
* no ``result.json`` in its directory (the job was killed, or is still running; the last
  error line of its log is the reason when there is one);
* a ``result.json`` that cannot be read, is not JSON or is JSON but not an object;
* a ``result.json`` whose misfit is not finite (written as ``null``);
* no directory at all, for a sweeper that says how many trials it runs (Optuna's
  ``n_trials`` in ``multirun.yaml``): not run yet.

The report reads files only (``result.json``, ``.hydra/*.yaml``, ``multirun.yaml``); it
imports nothing of Hydra.

With Hydra's Optuna sweeper the best trial of ``optimization_results.yaml`` is named
below the table. ``--out`` and ``--csv`` create the folders they name. Exit status 2 with one
``error:`` line, and nothing written, when a directory does not exist or holds no jobs, or
an output file cannot be written (a folder, a path below a file, no permission).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import sys
from pathlib import Path
from typing import Any, Callable, Iterable, Optional, Sequence

import yaml

RESULT_FILE = "result.json"
#: Columns from result.json, in table order: (key, header).
METRIC_COLUMNS = (("u_err_inf", "u_err_inf"), ("u_err_2", "u_err_2"),
                  ("k_err_inf", "k_err_inf"), ("k_err_2", "k_err_2"),
                  ("k_err_rel", "k_err_rel"), ("k_err_rel_aligned", "k_err_rel_aligned"),
                  ("iterations", "iterations"), ("wall_s", "wall [s]"),
                  ("factorizations", "factorizations"),
                  ("validation_surface_err_mean", "validation err"),
                  ("validation_surface_err_reduction", "validation reduction"),
                  ("validation_iteration", "chosen iteration"))
#: Columns shown only when some job has them (runs with validation frames).
OPTIONAL_COLUMNS = ("validation_surface_err_mean", "validation_surface_err_reduction",
                    "validation_iteration")
#: Overrides that name the preset, not a setting of the job.
IGNORED_OVERRIDES = ("experiment",)


class ReportError(Exception):
    """A sweep directory that cannot be reported (one-line message)."""


@dataclasses.dataclass
class JobRow:
    """One job of the sweep: its overrides and its result, or why it has none."""

    num: int
    overrides: dict[str, str]
    directory: Optional[Path]
    result: Optional[dict[str, Any]] = None
    failure: Optional[str] = None
    #: the table's job cell: the job number, or a single run's directory name
    label: str = ""

    def __post_init__(self) -> None:
        if not self.label:
            self.label = str(self.num) if self.num >= 0 else (
                self.directory.name if self.directory is not None else "?")

    @property
    def failed(self) -> bool:
        return self.failure is not None


def parse_overrides(lines: Iterable[str]) -> dict[str, str]:
    """``["solver=gauss_newton", "+x=1"]`` -> ``{"solver": "gauss_newton", "x": "1"}``
    (``+``/``++``/``~`` prefixes dropped; the preset choice ``experiment=`` left out)."""
    out: dict[str, str] = {}
    for line in lines:
        key, _, value = str(line).partition("=")
        key = key.lstrip("+~")
        if key not in IGNORED_OVERRIDES:
            out[key] = value
    return out


def _load_yaml(path: Path) -> Any:
    with open(path, encoding="utf-8") as f:
        return yaml.safe_load(f)


def _try_yaml(path: Path) -> Any:
    """The YAML in ``path``; ``None`` where it is missing, unreadable or not YAML."""
    try:
        return _load_yaml(path) if path.is_file() else None
    except (OSError, ValueError, yaml.YAMLError):
        return None


def job_number(hydra_cfg: Any) -> int:
    """``hydra.job.num`` of a job's ``hydra.yaml``; -1 for a single run (Hydra writes
    ``???`` there) or a file that does not say."""
    job = ((hydra_cfg if isinstance(hydra_cfg, dict) else {}).get("hydra") or {}).get("job")
    num = (job or {}).get("num") if isinstance(job, dict) else None
    return num if isinstance(num, int) and not isinstance(num, bool) and num >= 0 else -1


def _last_error_line(job_dir: Path) -> Optional[str]:
    """The last line of the job's Hydra logs that reports an error, if any."""
    for log_file in sorted(job_dir.glob("*.log")):
        lines = [line.strip() for line in log_file.read_text(errors="replace").splitlines()
                 if "ERROR" in line or line.startswith("error:")]
        if lines:
            return lines[-1].split(" - ", 1)[-1]
    return None


def read_job(job_dir: Path) -> JobRow:
    """The row of one job directory (one that holds ``.hydra/``)."""
    num = job_number(_try_yaml(job_dir / ".hydra" / "hydra.yaml"))
    lines = _try_yaml(job_dir / ".hydra" / "overrides.yaml")
    overrides = parse_overrides(lines) if isinstance(lines, list) else {}
    row = JobRow(num, overrides, job_dir)
    result_path = job_dir / RESULT_FILE
    if not result_path.is_file():
        reason = "no result.json"
        if (job_dir / "checkpoint.pt").is_file():
            reason += " (still running, or stopped during the fit: checkpoint.pt left)"
        error = _last_error_line(job_dir)
        row.failure = f"{reason}: {error}" if error else reason
        return row
    try:
        row.result = json.loads(result_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        row.failure = f"unreadable result.json ({e})"
        return row
    if not isinstance(row.result, dict):
        row.failure = (f"unreadable result.json (a JSON {type(row.result).__name__}, not an "
                       "object)")
        row.result = None
        return row
    if row.result.get("status") == "failed":
        row.failure = str(row.result.get("error") or "failed")
    elif not _finite(row.result.get("misfit")):
        row.failure = "non-finite misfit in result.json"
    return row


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def expected_trials(sweep_dir: Path) -> int:
    """The number of trials a sweeper was asked for (``n_trials`` of Optuna and sweepers
    alike, read from ``multirun.yaml``); 0 when it does not say."""
    multirun = sweep_dir / "multirun.yaml"
    config = _try_yaml(multirun)
    hydra_cfg = (config.get("hydra") if isinstance(config, dict) else None) or {}
    sweeper = (hydra_cfg.get("sweeper") if isinstance(hydra_cfg, dict) else None) or {}
    n_trials = sweeper.get("n_trials") if isinstance(sweeper, dict) else None
    return n_trials if isinstance(n_trials, int) and n_trials > 0 else 0


def collect_all(directories: Sequence[Path]) -> list[JobRow]:
    """The rows of every directory given, in the order given: a run directory's one row,
    a sweep's rows in job order (:func:`collect`)."""
    rows: list[JobRow] = []
    for directory in directories:
        rows += collect(directory)
    return rows


def collect(sweep_dir: Path) -> list[JobRow]:
    """Every job of the sweep, in job order, with its result or failure; a run directory
    (one that holds ``.hydra/hydra.yaml``) is its one job."""
    if not sweep_dir.is_dir():
        what = "is not a directory" if sweep_dir.exists() else "does not exist"
        raise ReportError(f"{sweep_dir} {what}; pass the multirun directory of a sweep "
                          f"(e.g. multirun/seed_table/<date-time>) or a run directory (the "
                          f"one that holds .hydra/)")
    if (sweep_dir / ".hydra" / "hydra.yaml").is_file():
        return [read_job(sweep_dir)]
    job_dirs = sorted({p.parent.parent for p in sweep_dir.rglob(".hydra/hydra.yaml")
                       if ".submitit" not in p.parts})
    found = [read_job(d) for d in job_dirs]
    by_num = {job.num: job for job in found if job.num >= 0}
    expected = expected_trials(sweep_dir)
    if not found and not expected:
        raise ReportError(f"{sweep_dir} holds no jobs (no .hydra/hydra.yaml in it or below "
                          f"it, no multirun.yaml); pass the directory of a multirun (-m) sweep "
                          f"or a run directory")
    rows = list(found)
    for num in range(expected):
        if num not in by_num:
            rows.append(JobRow(num, {}, None, failure="no job directory (not run yet)"))
    return sorted(rows, key=lambda job: (job.num, str(job.directory)))


def override_columns(rows: Sequence[JobRow]) -> tuple[list[str], dict[str, str]]:
    """Override keys that differ between jobs (table columns, in order of first
    appearance) and those every job shares (key -> value)."""
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row.overrides if k not in keys]
    known = [row for row in rows if row.overrides]
    common = {k: known[0].overrides[k] for k in keys
              if len(known) > 1 and k in known[0].overrides
              and all(r.overrides.get(k) == known[0].overrides[k] for r in known)}
    return [k for k in keys if k not in common], common


def short_headers(keys: Sequence[str]) -> list[str]:
    """``problem.noise`` -> ``noise`` where the last component is unambiguous."""
    last = [k.rsplit(".", 1)[-1] for k in keys]
    return [name if last.count(name) == 1 else key for key, name in zip(keys, last)]


def metric_columns(rows: Sequence[JobRow]) -> list[tuple[str, str]]:
    """The metric columns to show: ``k_err_rel`` only when some job has no aligned error
    (a problem that fixes the scale), ``k_err_rel_aligned`` only when some job has one."""
    results = [row.result for row in rows if row.result is not None and not row.failed]
    has_aligned = [("k_err_rel_aligned" in r) for r in results]
    columns = []
    for key, header in METRIC_COLUMNS:
        if key == "k_err_rel" and results and all(has_aligned):
            continue
        if key == "k_err_rel_aligned" and results and not any(has_aligned):
            continue
        if key in OPTIONAL_COLUMNS and not any(key in r for r in results):
            continue
        columns.append((key, header))
    return columns


def _format_override(value: str) -> str:
    """Long floats (Optuna's samples) to 4 significant digits; everything else as given."""
    try:
        number = float(value)
    except ValueError:
        return value
    return f"{number:.4g}" if len(value) > 8 and "." in value else value


def _format_metric(key: str, value: Any) -> str:
    if value is None:
        return "nan"
    if key in ("iterations", "factorizations", "validation_iteration"):
        return str(int(value))
    if key == "wall_s":
        return f"{float(value):.1f}"
    return f"{float(value):.2e}"


def stop_cell(row: JobRow) -> str:
    if row.failed:
        return f"failed: {row.failure}"
    assert row.result is not None
    reason = str(row.result.get("stop_reason", "?"))
    return reason if row.result.get("converged", True) else f"{reason} (not converged)"


def markdown_table(rows: Sequence[JobRow], sweep_dirs: Sequence[Path]) -> str:
    """The report as markdown: shared overrides, the table, the Optuna best trial."""
    keys, common = override_columns(rows)
    metrics = metric_columns(rows)
    header = ["job", *short_headers(keys), *(h for _, h in metrics), "stop reason"]
    lines = []
    if common:
        lines += ["Common overrides: " + ", ".join(f"`{k}={v}`" for k, v in common.items()), ""]
    lines += ["| " + " | ".join(header) + " |",
              "|" + "|".join(" --- " if i <= len(keys) or i == len(header) - 1 else " ---: "
                             for i in range(len(header))) + "|"]
    for row in rows:
        cells = [row.label.replace("|", "\\|"), *(_format_override(row.overrides.get(k, "?")) for k in keys)]
        if row.failed:
            cells += ["–"] * len(metrics)
        else:
            assert row.result is not None
            cells += [_format_metric(key, row.result.get(key)) for key, _ in metrics]
        cells.append(stop_cell(row).replace("|", "\\|"))
        lines.append("| " + " | ".join(cells) + " |")
    n_failed = sum(row.failed for row in rows)
    lines += ["", f"{len(rows)} job{'' if len(rows) == 1 else 's'}, {n_failed} failed or "
                  "unfinished."]
    lines += [line for line in (best_validation(rows, keys),
                                *(optuna_best(d) for d in sweep_dirs)) if line]
    return "\n".join(lines) + "\n"


def best_validation(rows: Sequence[JobRow], keys: Sequence[str]) -> Optional[str]:
    """One line on the job of lowest validation error (``None`` without validation)."""
    scored = [(float(row.result["validation_surface_err_mean"]), row) for row in rows
              if not row.failed and row.result is not None
              and _finite(row.result.get("validation_surface_err_mean"))]
    if not scored:
        return None
    error, row = min(scored, key=lambda item: item[0])
    job = f"job {row.num}" if row.num >= 0 else f"run {row.label}"
    settings = ", ".join(f"`{k}={_format_override(row.overrides.get(k, '?'))}`" for k in keys)
    return (f"Lowest validation error {error:.3e}: {job}"
            + (f" ({settings})" if settings else "")
            + f", at its iteration {row.result.get('validation_iteration')}.")


def optuna_best(sweep_dir: Path) -> Optional[str]:
    """One line on Optuna's best trial, from ``optimization_results.yaml`` if present."""
    path = sweep_dir / "optimization_results.yaml"
    if not path.is_file():
        return None
    data = _try_yaml(path)
    if not isinstance(data, dict) or not _finite(data.get("best_value")):
        return None
    params = ", ".join(f"`{k}={_format_override(str(v))}`"
                       for k, v in (data.get("best_params") or {}).items())
    return f"Optuna best value {float(data['best_value']):.4g} at {params}."


def write_csv(rows: Sequence[JobRow], path: Path) -> None:
    """Full-precision CSV: job, every override key, every metric column, status."""
    keys = []
    for row in rows:
        keys += [k for k in row.overrides if k not in keys]
    metrics = [key for key, _ in metric_columns(rows)]
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["job", *keys, *metrics, "converged", "stop_reason", "status", "directory"])
        for row in rows:
            result = row.result if (row.result is not None and not row.failed) else {}
            writer.writerow([row.label, *(row.overrides.get(k, "") for k in keys),
                             *("" if result.get(m) is None else result[m] for m in metrics),
                             result.get("converged", ""), result.get("stop_reason", ""),
                             f"failed: {row.failure}" if row.failed else "ok",
                             "" if row.directory is None else str(row.directory)])


def check_output(option: str, path: Path) -> None:
    """Refuse an output file that cannot be written (:class:`ReportError`): a folder, a path
    below a file, a folder without write permission. Missing folders are fine (created)."""
    if path.is_dir():
        raise ReportError(f"{option} {path} is a folder; name a file in it, e.g. "
                          f"{option} {path / ('report.csv' if option == '--csv' else 'report.md')}")
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ReportError(f"{option} {path}: {ancestor} is a file, not a folder; choose "
                          f"another path")
    if not os.access(ancestor, os.W_OK | os.X_OK) or (
            path.exists() and not os.access(path, os.W_OK)):
        raise ReportError(f"{option} {path}: no permission to write "
                          f"{path if path.exists() else ancestor}; choose another path")


def write_outputs(outputs: Sequence[tuple[str, Path, Callable[[Path], None]]]) -> None:
    """Write each ``(option, path, writer)``, creating missing folders; on a failure remove
    what was written and created, and raise :class:`ReportError` naming the option."""
    written: list[Path] = []
    made: list[Path] = []
    for option, path, writer in outputs:
        try:
            missing = [d for d in [path.parent, *path.parent.parents] if not d.exists()]
            for directory in reversed(missing):
                directory.mkdir()
                made.append(directory)
            existed = path.exists()
            writer(path)
            if not existed:
                written.append(path)
        except OSError as e:
            for done in written:
                done.unlink(missing_ok=True)
            for directory in reversed(made):
                try:
                    directory.rmdir()
                except OSError:
                    pass
            raise ReportError(f"{option} {path}: cannot be written ({e.strerror or e}); "
                              f"choose another path") from None


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n", 1)[1] + "\nWrites only --out and "
                                     "--csv. Documented in docs/guide/sweeps.md (One table of a sweep).",
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("directories", type=Path, nargs="+", metavar="DIR",
                        help="the multirun directory of a sweep, or a run directory (several: "
                             "their rows in the order given)")
    parser.add_argument("--out", type=Path,
                        help="also write the markdown table to this file (its folders created)")
    parser.add_argument("--csv", type=Path,
                        help="write the table as CSV to this file (its folders created)")
    args = parser.parse_args(argv)
    try:
        outputs = [(option, path, writer) for option, path, writer in (
            ("--out", args.out, None), ("--csv", args.csv, None)) if path is not None]
        for option, path, _ in outputs:
            check_output(option, path)
        rows = collect_all(args.directories)
        table = markdown_table(rows, args.directories)
        write_outputs([(option, path, (lambda p: p.write_text(table, encoding="utf-8"))
                        if option == "--out" else (lambda p: write_csv(rows, p)))
                       for option, path, _ in outputs])
    except ReportError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sys.stdout.write(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
