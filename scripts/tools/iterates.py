"""Record and compare the iterates of a fixed set of fits: the bit-for-bit check of a refactor.

    .venv/bin/python scripts/tools/iterates.py record before.json     # on the old tree
    .venv/bin/python scripts/tools/iterates.py record after.json      # on the new tree
    .venv/bin/python scripts/tools/iterates.py compare before.json after.json

Each run goes through the command line (``experiments/fit.py``), so the record does not
depend on the package's internal layout. A record holds, per run, the fitted parameters as
the hex of their float64 bits, every history row (misfit, objective, step norm, counters;
wall times dropped) and the result's metrics, counters, iterations and stop reason.
``compare`` exits 1 and names the first difference when anything is not bit-identical.
The arm's tetrahedral mesh comes from the cache (``$TORCHFIT_CACHE_DIR``): run both records
with the same cache, or pytetwild makes another mesh.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]

# name -> overrides; chosen before the refactor of 2026-11-26 (issue 26) and kept fixed.
RUNS: dict[str, list[str]] = {
    "spring1d_gn": ["problem=spring1d", "solver=gauss_newton", "problem.noise=1e-4"],
    "spring1d_lm": ["problem=spring1d", "solver=levenberg_marquardt", "problem.noise=1e-4"],
    "spring1d_sb": ["problem=spring1d", "solver=split_bregman", "problem.noise=1e-4"],
    "poisson2d_gn": ["problem=poisson2d", "solver=gauss_newton", "problem.N=24",
                     "problem.noise=1e-3"],
    "poisson2d_sb": ["problem=poisson2d", "solver=split_bregman", "problem.N=24",
                     "problem.noise=1e-3"],
    "membrane2d_lm": ["problem=membrane2d", "problem.nx=32", "problem.ny=8",
                      "solver.max_iter=8"],
    "spring1d_dynamic": ["problem=spring1d_dynamic", "problem.n=16", "problem.duration=2.0",
                         "problem.frames=20", "solver.max_iter=6"],
    # one thread: MKL PARDISO's multithreaded factorisation is not bit-reproducible run to run
    # (the initial damping differed in the last digit between two runs of one tree)
    "arm3d_short": ["threads=1"],
    # the arm's synthetic target: unbounded by default (problem.bounds), its iterates unchanged
    "arm3d_short_synthetic": ["problem.target=synthetic", "threads=1"],
    # added with the body's recomposition (issue 46): the body in time and the sheet in time
    "arm3d_short_dynamic": ["problem=arm3d_short_dynamic", "solver.max_iter=3"],
    "membrane2d_dynamic": ["problem=membrane2d_dynamic", "problem.nx=16", "problem.ny=4",
                           "solver.max_iter=3"],
}
_WALL_KEYS = {"wall_time", "wall_s", "solver_wall_s", "setup_s"}


def _clean(value):
    """Drop wall-clock entries (they differ run to run) from nested JSON."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()
                if k not in _WALL_KEYS and not k.endswith("wall_s") and "time" not in k}
    if isinstance(value, list):
        return [_clean(v) for v in value]
    return value


def record_one(overrides: list[str], run_dir: Path) -> dict:
    cmd = [sys.executable, str(REPO / "experiments" / "fit.py"), *overrides,
           f"hydra.run.dir={run_dir}", "progress=false"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(overrides)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    result = json.loads((run_dir / "result.json").read_text())
    theta = torch.load(run_dir / "params.pt", weights_only=True)
    if isinstance(theta, dict):
        theta = theta.get("theta", next(iter(theta.values())))
    bits = theta.detach().to(torch.float64).contiguous().numpy().tobytes().hex()
    keep = {k: result[k] for k in ("metrics", "iterations", "stop_reason", "converged",
                                   "factorizations", "solves", "history") if k in result}
    return {"theta_bits": bits, **_clean(keep)}


def record(out: Path, names: list[str]) -> None:
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            print(f"[iterates] {name}", flush=True)
            runs[name] = record_one(RUNS[name], Path(tmp) / name)
    out.write_text(json.dumps(runs, indent=1, sort_keys=True))


def _first_difference(a, b, path: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                return f"{path}/{key}: only in {'after' if key in b else 'before'}"
            found = _first_difference(a[key], b[key], f"{path}/{key}")
            if found:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: length {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            found = _first_difference(x, y, f"{path}[{i}]")
            if found:
                return found
        return None
    return None if a == b else f"{path}: {a!r} != {b!r}"


def compare(before: Path, after: Path) -> int:
    a, b = json.loads(before.read_text()), json.loads(after.read_text())
    failed = 0
    for name in sorted(set(a) | set(b)):
        if name not in a or name not in b:
            print(f"{name}: recorded only {'after' if name in b else 'before'} (not compared)")
            continue
        diff = _first_difference(a[name], b[name], name)
        print(f"{name}: {'identical' if diff is None else 'DIFFERS ' + diff}")
        failed += diff is not None
    return 1 if failed else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="verb", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("out", type=Path)
    rec.add_argument("--only", nargs="*", choices=sorted(RUNS), default=sorted(RUNS))
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("before", type=Path)
    cmp_.add_argument("after", type=Path)
    args = parser.parse_args()
    if args.verb == "record":
        record(args.out, args.only)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    raise SystemExit(main())
