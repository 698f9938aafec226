"""Verify the derivatives of a problem's residual: the Hydra adapter over :func:`torchfit.verify`.

    python experiments/verify.py problem=spring1d
    python experiments/verify.py problem=spring1d at=truth perturbation=0.05 seed=3

Taylor, dot-product and finite-difference checks at the problem's initial guess
(``at=initial``) or its true parameters (``at=truth``), offset by ``perturbation`` times a
seeded Gaussian vector so that the point is generic. Prints the report and writes
``verify.json`` into the run directory. Exit statuses (:mod:`app`): 0 every check passed,
1 a check failed, 2 bad input (``error: ...`` on standard error, nothing left behind).
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:       # this checkout's experiments/ (and torchfit), installed or not
    sys.path.insert(0, str(REPO))

from experiments.cli import VERIFY_HELP, command_line  # noqa: E402

if __name__ == "__main__":      # help, unreadable overrides, paths: before the heavy imports
    sys.argv[1:] = command_line(sys.argv[1:], VERIFY_HELP)

from experiments.app import BAD_INPUT, RunDirGuard, checked_config, refuse, run_hydra_app

import hydra  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from torchfit import build_problem  # noqa: E402
from torchfit.config import VerifyConfig, register_configs  # noqa: E402
from torchfit.run import VerifyOptions, set_threads, verify  # noqa: E402

register_configs()
GUARD = RunDirGuard(sys.argv[1:])
_started = False


@hydra.main(config_path="../conf", config_name="verify", version_base="1.3")
def main(cfg: DictConfig) -> None:
    global _started
    _started = True
    run_dir = Path(HydraConfig.get().runtime.output_dir).resolve()
    try:
        config = checked_config(cfg, VerifyConfig)
        options = VerifyOptions(**{f.name: config[f.name]
                                   for f in dataclasses.fields(VerifyOptions) if f.name in config})
        options.check()
        if options.threads > 0:
            set_threads(options.threads)  # before the build: a synthetic target is simulated there
        problem = build_problem(str(config["problem"].get("name")), dict(config["problem"]))
        report = verify(problem, run_dir=run_dir, options=options, config=config)
    except BAD_INPUT as error:
        refuse(error, run_dir, GUARD)
    print(f"problem {problem.name} at {config['at']} + {config['perturbation']:g} * random "
          f"offset (seed {config['seed']})")
    print(report.format())
    print(f"wrote {run_dir / 'verify.json'}")
    if not report.passed:
        sys.exit(1)


if __name__ == "__main__":
    run_hydra_app(main, lambda: _started)
