#!/usr/bin/env python
"""Time to accuracy of the default solvers on the seed's 2-D cases and on spring1d.

For every case (``--cases``; default: the four poisson2d cases of the issue and spring1d
dense with noise 1e-4) this runs :func:`torchfit.fit` exactly as ``experiments/fit.py``
would with the named solver's defaults (plus the listed overrides), records the wall time
and ``k_err_rel_aligned`` of every iteration, and reports

* ``reached``: for each accuracy of ``--accuracies`` (default 1e-1 ... 1e-7) the wall time
  and iteration at which the run first reached it (``null``: never);
* ``final``: the final accuracy, iterations, stop reason, total wall time, and the counted
  factorisations and solves;
* ``target``: where a case has a reference figure (the accuracy a plain scipy
  implementation reaches and the time it takes, quoted in the issue and measured on an
  earlier machine), the time at which torchfit reached it and the ratio to the reference
  time (the acceptance asks for at most 0.5);
* ``in_run_reference`` / ``in_run_target``: the same comparison against
  ``scripts/bench/scipy_reference.py`` (an independent numpy/scipy Gauss-Newton and split
  Bregman with explicit adjoints and SuperLU) timed in this run on this machine: its final
  accuracy, the time it first reached it, and when torchfit reached that accuracy;
  ``in_run_at_issue_accuracy``: both timed in this run to the issue's accuracy
  (``--no-reference`` skips the reference).

Wall time includes everything :func:`torchfit.fit` does after the problem is built
(solver set-up, scale estimates, every simulation), with the metric callback's own cost
subtracted (it is not part of the solve). Prints JSON and writes a PNG of accuracy against
time (``--png``). Example::

    .venv/bin/python scripts/bench/time_to_accuracy.py --out t2a.json --png t2a.png
    .venv/bin/python scripts/bench/time_to_accuracy.py --cases gn_dense sb_dense_noisy
"""
from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchtools import emit_report, loadavg, machine_info  # noqa: E402
from torchfit import fit  # noqa: E402
from torchfit.linalg import counting, set_threads  # noqa: E402
from torchfit.problems import build_problem  # noqa: E402

# the accuracy: the aligned relative field error where the problem has a gauge (poisson2d:
# k is determined up to a constant factor), else the raw one (spring1d)
ACCURACY_METRIC, FALLBACK_METRIC = "k_err_rel_aligned", "k_err_rel"
ACCURACIES = [1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7]

# name -> the case of scripts/bench/scipy_reference.py timed in the same run (and its settings):
# the plain numpy/scipy Gauss-Newton with a CGLS cap of 1000 (with the cap of 200 it stops
# at 3.3e-6 after 50 iterations; 1000 reaches the 6.1e-7), split Bregman as is
IN_RUN_REFERENCE: dict[str, tuple[str, dict[str, Any]]] = {
    "gn_dense": ("gn_dense", {"cg_max_iter": 1000}),
    "gn_dense_difference": ("gn_dense", {"cg_max_iter": 1000}),
    "sb_dense_noisy": ("sb_dense_noisy", {}),
    "sb_sparse": ("sb_sparse", {}),
}

# name -> (problem settings, solver name, solver overrides, reference (accuracy, seconds))
# The references: an independent numpy/scipy implementation of the same Gauss-Newton (CG
# on the normal equations, discrepancy stop) and split Bregman (SuperLU, explicit
# adjoints), measured on this 2-core machine (issue "The seed's 2-D fits ... in half its
# time").
CASES: dict[str, tuple[dict[str, Any], str, dict[str, Any], tuple[float, float] | None]] = {
    "gn_dense": ({"name": "poisson2d", "N": 64, "data": "dense", "noise": 0.0},
                 "gauss_newton", {}, (6.1e-7, 5.2)),
    "gn_dense_difference": ({"name": "poisson2d", "N": 64, "data": "dense", "noise": 0.0},
                            "gauss_newton", {"preconditioner": "difference"}, (6.1e-7, 5.2)),
    "sb_dense_noisy": ({"name": "poisson2d", "N": 64, "data": "dense", "noise": 1e-3},
                       "split_bregman", {}, (3.6e-2, 1.6)),
    "sb_sparse": ({"name": "poisson2d", "N": 64, "data": "sparse", "noise": 0.0},
                  "split_bregman", {}, (1.4e-2, 4.5)),
    "spring1d_gn": ({"name": "spring1d", "data": "dense", "noise": 1e-4},
                    "gauss_newton", {}, None),
    "spring1d_sb": ({"name": "spring1d", "data": "dense", "noise": 1e-4},
                    "split_bregman", {}, None),
}
DEFAULT_CASES = ["gn_dense", "gn_dense_difference", "sb_dense_noisy", "sb_sparse",
                 "spring1d_gn", "spring1d_sb"]


def run_reference(name: str, cache: dict[str, Any]) -> dict[str, Any] | None:
    """The scipy reference of case ``name`` (run once per reference case and process):
    its final accuracy, the wall time at which it first reached it, and its trace
    (``[seconds, iteration, accuracy]`` per iteration)."""
    if name not in IN_RUN_REFERENCE:
        return None
    import scipy_reference

    ref_name, settings = IN_RUN_REFERENCE[name]
    key = f"{ref_name}{sorted(settings.items())}"
    if key not in cache:
        gc.collect()
        summary = scipy_reference.run_case(ref_name, with_trace=True, **settings)
        cache[key] = {"case": ref_name, "settings": settings,
                      "trace": [[round(t, 4), it, err] for t, it, err in summary["trace"]],
                      "accuracy": summary["final_accuracy"],
                      "seconds": round(summary["time_to_final_accuracy"], 3),
                      "iterations": summary["final_iteration"], "stop": summary["stop"],
                      "counts": {"factorizations": summary["factorizations"],
                                 "solves": summary["solves"]}}
    return cache[key]


def compare(trace: list[tuple[float, int, float]], accuracy: float, ref_seconds: float
            ) -> dict[str, Any]:
    """When ``trace`` first reached ``accuracy`` and the ratio of that time to ``ref_seconds``."""
    hit = next(((t, it) for t, it, err in trace if err <= accuracy), None)
    return {"accuracy": accuracy, "reference_seconds": ref_seconds,
            "seconds": None if hit is None else round(hit[0], 3),
            "iteration": None if hit is None else hit[1],
            "ratio": None if hit is None else round(hit[0] / ref_seconds, 3),
            "ok_at_most_half": hit is not None and hit[0] <= 0.5 * ref_seconds}


def run_case(name: str, accuracies: list[float], references: dict[str, Any] | None = None
             ) -> dict[str, Any]:
    settings, solver, overrides, reference = CASES[name]
    settings = dict(settings)
    in_run = None if references is None else run_reference(name, references)
    problem = build_problem(settings.pop("name"), settings)
    trace: list[tuple[float, int, float]] = []
    metric_seconds = [0.0]

    def record(rec) -> None:
        # fit's own metric callback has filled rec.extra; read it, time our own reading.
        start = time.perf_counter()
        value = rec.extra.get(ACCURACY_METRIC, rec.extra.get(FALLBACK_METRIC))
        if value is None:
            metrics = problem.metrics(rec.theta)
            value = metrics.get(ACCURACY_METRIC, metrics.get(FALLBACK_METRIC))
        trace.append((rec.wall_time, rec.iteration, float(value)))
        metric_seconds[0] += time.perf_counter() - start

    gc.collect()
    with counting() as delta:
        start = time.perf_counter()
        result = fit(problem, {"name": solver, **overrides}, callbacks=[record])
        seconds = time.perf_counter() - start
        counts = delta.as_dict()
    reached: dict[str, Any] = {}
    for accuracy in accuracies:
        hit = next(((t, it) for t, it, err in trace if err <= accuracy), None)
        reached[f"{accuracy:g}"] = None if hit is None else {"seconds": round(hit[0], 3),
                                                             "iteration": hit[1]}
    out: dict[str, Any] = {
        "problem": CASES[name][0], "solver": solver, "overrides": overrides,
        "final": {"accuracy": trace[-1][2], "iterations": result.iterations,
                  "stop_reason": result.stop_reason, "seconds": round(seconds, 3),
                  "solver_seconds": round(result.wall_s, 3), "counts": counts},
        "reached": reached,
        "trace": [[round(t, 4), it, err] for t, it, err in trace],
    }
    if reference is not None:
        out["target"] = compare(trace, *reference)
    if in_run is not None:
        out["in_run_reference"] = in_run
        out["in_run_target"] = compare(trace, in_run["accuracy"], in_run["seconds"])
        if reference is not None:
            # the accuracy, both implementations timed in this run
            hit = next((t for t, _, err in in_run["trace"] if err <= reference[0]), None)
            out["in_run_at_issue_accuracy"] = None if hit is None else \
                compare(trace, reference[0], hit)
    return out


def plot(report: dict[str, Any], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, case in report["results"].items():
        times = [max(t, 1e-3) for t, _, _ in case["trace"]]
        ax.loglog(times, [err for _, _, err in case["trace"]], marker=".", label=name)
        target = case.get("target")
        if target:
            ax.plot([target["reference_seconds"]], [target["accuracy"]], "kx")
        in_run = case.get("in_run_target")
        if in_run:
            ax.plot([in_run["reference_seconds"]], [in_run["accuracy"]], "r+", markersize=10)
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("k_err_rel_aligned (spring1d: k_err_rel)")
    ax.set_title("time to accuracy (x: the issue's reference, +: scipy_reference.py in this run)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=DEFAULT_CASES, choices=sorted(CASES))
    parser.add_argument("--accuracies", nargs="+", type=float, default=ACCURACIES)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--png", type=Path, default=None)
    parser.add_argument("--no-reference", action="store_true",
                        help="skip scripts/bench/scipy_reference.py (the in-run reference)")
    args = parser.parse_args(argv)
    set_threads(args.threads)
    report: dict[str, Any] = {"benchmark": "time_to_accuracy", "machine": machine_info(),
                              "loadavg_start": loadavg(),
                              "settings": {"threads": args.threads,
                                           "accuracies": args.accuracies},
                              "results": {}}
    references: dict[str, Any] | None = None if args.no_reference else {}
    for name in args.cases:
        report["results"][name] = run_case(name, args.accuracies, references)
        case = report["results"][name]
        print(f"{name}: final {case['final']['accuracy']:.3g} in "
              f"{case['final']['seconds']:.1f} s ({case['final']['iterations']} its, "
              f"{case['final']['stop_reason']}); issue's target {case.get('target')}; "
              f"in-run target {case.get('in_run_target')}; in-run at the issue's accuracy "
              f"{case.get('in_run_at_issue_accuracy')}", file=sys.stderr, flush=True)
    report["loadavg_end"] = loadavg()
    for key in ("target", "in_run_target", "in_run_at_issue_accuracy"):
        ok = [c[key]["ok_at_most_half"] for c in report["results"].values() if c.get(key)]
        report[f"all_{key}s_met"] = all(ok) if ok else None
    emit_report(report, args.out)
    if args.png is not None:
        plot(report, args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
