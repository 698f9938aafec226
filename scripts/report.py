"""Aggregate the ``result.json`` files of a Hydra multirun directory into one table.

Usage::

    python scripts/report.py multirun/seed_table/<date-time>                 # markdown on stdout
    python scripts/report.py multirun/seed_table/<date-time> --out report.md --csv report.csv

One row per job of the sweep, in job order: the job's overrides (those that differ between
jobs; the ones shared by every job are listed above the table), ``u_err_inf``, ``u_err_2``,
``k_err_inf``, ``k_err_2``, ``k_err_rel_aligned`` (``k_err_rel`` as well when a problem is
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
below the table. Exit status 2 with one ``error:`` line when the directory does not exist
or holds no jobs.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Any, Iterable, Optional, Sequence

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
    hydra_cfg = _load_yaml(job_dir / ".hydra" / "hydra.yaml") or {}
    num = int(hydra_cfg.get("hydra", {}).get("job", {}).get("num", -1))
    overrides_file = job_dir / ".hydra" / "overrides.yaml"
    overrides = parse_overrides(_load_yaml(overrides_file) or []) if overrides_file.is_file() else {}
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
    config = _load_yaml(multirun) if multirun.is_file() else None
    n_trials = ((config or {}).get("hydra", {}).get("sweeper") or {}).get("n_trials")
    return n_trials if isinstance(n_trials, int) and n_trials > 0 else 0


def collect(sweep_dir: Path) -> list[JobRow]:
    """Every job of the sweep, in job order, with its result or failure."""
    if not sweep_dir.is_dir():
        raise ReportError(f"sweep directory {sweep_dir} does not exist; pass the multirun "
                          f"directory of a sweep, e.g. multirun/seed_table/<date-time>")
    job_dirs = sorted({p.parent.parent for p in sweep_dir.rglob(".hydra/hydra.yaml")
                       if ".submitit" not in p.parts})
    found = [read_job(d) for d in job_dirs]
    by_num = {job.num: job for job in found if job.num >= 0}
    expected = expected_trials(sweep_dir)
    if not found and not expected:
        raise ReportError(f"{sweep_dir} holds no jobs (no <job>/.hydra/hydra.yaml, no "
                          f"multirun.yaml); pass the directory of a multirun (-m) sweep")
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
              if len(known) > 1 and all(r.overrides.get(k) == known[0].overrides[k]
                                        for r in known)}
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


def markdown_table(rows: Sequence[JobRow], sweep_dir: Path) -> str:
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
        cells = [str(row.num), *(_format_override(row.overrides.get(k, "?")) for k in keys)]
        if row.failed:
            cells += ["–"] * len(metrics)
        else:
            assert row.result is not None
            cells += [_format_metric(key, row.result.get(key)) for key, _ in metrics]
        cells.append(stop_cell(row).replace("|", "\\|"))
        lines.append("| " + " | ".join(cells) + " |")
    n_failed = sum(row.failed for row in rows)
    lines += ["", f"{len(rows)} jobs, {n_failed} failed or unfinished."]
    lines += [line for line in (best_validation(rows, keys), optuna_best(sweep_dir)) if line]
    return "\n".join(lines) + "\n"


def best_validation(rows: Sequence[JobRow], keys: Sequence[str]) -> Optional[str]:
    """One line on the job of lowest validation error (``None`` without validation)."""
    scored = [(float(row.result["validation_surface_err_mean"]), row) for row in rows
              if not row.failed and row.result is not None
              and _finite(row.result.get("validation_surface_err_mean"))]
    if not scored:
        return None
    error, row = min(scored, key=lambda item: item[0])
    settings = ", ".join(f"`{k}={_format_override(row.overrides.get(k, '?'))}`" for k in keys)
    return (f"Lowest validation error {error:.3e}: job {row.num}"
            + (f" ({settings})" if settings else "")
            + f", at its iteration {row.result.get('validation_iteration')}.")


def optuna_best(sweep_dir: Path) -> Optional[str]:
    """One line on Optuna's best trial, from ``optimization_results.yaml`` if present."""
    path = sweep_dir / "optimization_results.yaml"
    if not path.is_file():
        return None
    data = _load_yaml(path) or {}
    if "best_value" not in data:
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
            writer.writerow([row.num, *(row.overrides.get(k, "") for k in keys),
                             *("" if result.get(m) is None else result[m] for m in metrics),
                             result.get("converged", ""), result.get("stop_reason", ""),
                             f"failed: {row.failure}" if row.failed else "ok",
                             "" if row.directory is None else str(row.directory)])


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="Writes only --out and --csv. Documented in "
                                            "docs/guide/sweeps.md (One table of a sweep).")
    parser.add_argument("sweep_dir", type=Path, help="the multirun directory of one sweep")
    parser.add_argument("--out", type=Path, help="also write the markdown table to this file")
    parser.add_argument("--csv", type=Path, help="write the table as CSV to this file")
    args = parser.parse_args(argv)
    try:
        rows = collect(args.sweep_dir)
    except ReportError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    table = markdown_table(rows, args.sweep_dir)
    sys.stdout.write(table)
    if args.out:
        args.out.write_text(table, encoding="utf-8")
    if args.csv:
        write_csv(rows, args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
