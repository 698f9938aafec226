#!/usr/bin/env python
"""Do thread settings slow small element kernels? A measurement (issue 30, item 4).

Each configuration runs in a fresh process (thread pools are set once per process):

* ``default``: nothing set (torch's own default: one thread per core, MKL dynamic);
* ``threads=1`` / ``threads=2``: :func:`torchfit.linalg.set_threads` as ``threads=`` calls it
  (``torch.set_num_threads``, MKL's dynamic threading switched back on, ``threadpoolctl``
  limits for the BLAS/OpenMP libraries);
* ``torch_only=2``: ``torch.set_num_threads(2)`` alone, MKL dynamic off (what ``threads=2``
  did before 2026-11-26, and what the issue measured).

Kernels, float64, timed as the median of repeated calls: ``sqrt_384`` (``torch.sqrt`` of 384
doubles, the issue's example), ``sqrt_1e6`` (a large one, where threads can help), and the
whole projected stable neo-Hookean tangent of a tet box of about 4,860 tetrahedra
(``SimplicialElasticity.tangent_values``, the evaluation the issue timed).

Each configuration is measured on an idle machine and under load: ``--load`` busy
processes (default: one per core) spinning beside it. Prints JSON (``--out`` writes it).

    python scripts/bench/threads.py --out /tmp/threads.json
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchtools import emit_report, machine_info  # noqa: E402

CONFIGS = ("default", "threads=1", "threads=2", "torch_only=2")


def _spin(stop_at: float) -> None:
    x = 0
    while time.time() < stop_at:
        x += 1


def _median(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(config: str, repeats: int) -> dict[str, Any]:
    """In this process: apply ``config``, time the kernels."""
    import torch

    from torchfit.linalg import set_threads
    from torchfit.mesh import box_tetrahedra
    from torchfit.physics.elasticity import SimplicialElasticity

    if config.startswith("threads="):
        set_threads(int(config.split("=")[1]))
    elif config.startswith("torch_only="):
        torch.set_num_threads(int(config.split("=")[1]))
    dt = torch.float64
    small = torch.rand(384, dtype=dt) + 0.5
    large = torch.rand(1_000_000, dtype=dt) + 0.5
    mesh = box_tetrahedra(9, 9, 10, (1.0, 1.0, 1.0))
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "stable_neo_hookean", nu=0.3)
    g = torch.Generator().manual_seed(0)
    x = (model.rest.points @ (0.6 * torch.eye(3, dtype=dt)).T).reshape(1, -1)
    x = x + 0.03 * torch.randn(x.shape, dtype=dt, generator=g)
    E = torch.ones(model.n_cells, dtype=dt)
    return {"config": config, "torch_threads": torch.get_num_threads(),
            "n_tets": int(model.n_cells),
            "sqrt_384_us": 1e6 * _median(lambda: torch.sqrt(small), 50 * repeats),
            "sqrt_1e6_ms": 1e3 * _median(lambda: torch.sqrt(large), repeats),
            "neo_hookean_tangent_ms": 1e3 * _median(
                lambda: model.tangent_values(x, E, projected=True), max(3, repeats // 4))}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--load", type=int, default=os.cpu_count() or 2,
                        help="busy processes beside the measurement in the loaded runs")
    parser.add_argument("--configs", default=",".join(CONFIGS))
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.child is not None:
        print(json.dumps(measure(args.child, args.repeats)))
        return {}
    rows = []
    for loaded in (False, True):
        for config in args.configs.split(","):
            spinners = []
            if loaded:
                stop_at = time.time() + 600
                spinners = [multiprocessing.Process(target=_spin, args=(stop_at,))
                            for _ in range(args.load)]
                for p in spinners:
                    p.start()
            try:
                out = subprocess.run([sys.executable, __file__, "--child", config,
                                      "--repeats", str(args.repeats)], capture_output=True,
                                     text=True, check=True)
            finally:
                for p in spinners:
                    p.terminate()
                    p.join()
            row = json.loads(out.stdout.strip().splitlines()[-1])
            row.update(loaded=loaded, busy_processes=args.load if loaded else 0,
                       load_average_1min=os.getloadavg()[0])
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    report = {"benchmark": "threads", "machine": machine_info(), "rows": rows}
    emit_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
