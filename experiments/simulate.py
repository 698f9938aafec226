"""Use a fitted material: the Hydra adapter over :func:`torchfit.run.simulating.simulate`.

    python experiments/simulate.py run=<fitted run>                     # the fit's animation
    python experiments/simulate.py run=<arm run> problem.max_flexion=90 problem.n_frames=12 \\
        problem.frames=null                                              # another animation
    python experiments/simulate.py run=<run> problem.path=<folder>      # a new animation of it

``run`` is a fitted run's directory (or its ``params.pt``); the problem group and every
setting come from it (``.hydra/``), and ``problem.*`` overrides make the animation to
simulate: the same body (rest surface), any frames. One progress line per frame (frame i/F,
Newton iterations, seconds), then a summary line. The run directory (default
``outputs/simulate/<problem>/<time>``) gets ``frames/frame_NNN.obj``, ``body.vtu``,
``frames.npz``, ``simulation.png``, ``result.json`` (per-frame errors) and Hydra's
``.hydra/`` and ``simulate.log``; a ``hydra.run.dir`` that is the fitted run, or holds a fit
or a simulation (``result.json``, ``params.pt``), is refused before Hydra writes there.
Exit statuses (:mod:`app`): 0 done, 1 the simulation failed, 2 bad input (one ``error:``
line, nothing written: e.g. a run of another problem, a changed parameterisation, an
animation of another body), 130 interrupted, 143 terminated.
"""
from __future__ import annotations

import sys
import traceback
import logging
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:       # this checkout's experiments/ (and torchfit), installed or not
    sys.path.insert(0, str(REPO))

from experiments.cli import SIMULATE_HELP, command_line  # noqa: E402

if __name__ == "__main__":      # help, unreadable overrides, paths: before the heavy imports
    sys.argv[1:] = command_line(sys.argv[1:], SIMULATE_HELP)

from experiments.app import (BAD_INPUT, RunDirGuard, Terminated, checked_config, one_line,
                             refuse, results_line, run_hydra_app)

import hydra  # noqa: E402
import matplotlib  # noqa: E402
import yaml  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

matplotlib.use("Agg")   # pictures are files; never a window
from torchfit.config import SimulateConfig, register_configs  # noqa: E402
from torchfit.errors import ConfigurationError  # noqa: E402
from torchfit.run import check_run_dir, read_fitted_run, simulate  # noqa: E402

register_configs()
log = logging.getLogger("simulate")
GUARD = RunDirGuard(sys.argv[1:])
_started = False


def problem_overrides(cfg: DictConfig) -> dict:
    """The ``problem.<key>`` settings given on the command line, with their composed
    (schema-checked) values."""
    composed = OmegaConf.to_container(cfg.problem, resolve=True, throw_on_missing=False,
                                      enum_to_str=True)
    assert isinstance(composed, dict)
    keys = []
    for override in HydraConfig.get().overrides.task:
        name = override.split("=", 1)[0].lstrip("+~")
        if name.startswith("problem."):
            keys.append(name.split(".", 2)[1])
    return {key: composed.get(key) for key in dict.fromkeys(keys)}


@hydra.main(config_path="../conf", config_name="simulate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    global _started
    _started = True
    run_dir = Path(HydraConfig.get().runtime.output_dir).resolve()
    try:
        config = checked_config(cfg, SimulateConfig, throw_on_missing=False)
        result = simulate(str(cfg.run), problem_overrides(cfg), run_dir,
                          threads=int(config["threads"]), progress_lines=bool(config["progress"]))
    except KeyboardInterrupt as interrupt:     # Ctrl-C, or SIGTERM (app.Terminated)
        terminated = isinstance(interrupt, Terminated)
        print("terminated (SIGTERM)" if terminated else "interrupted", file=sys.stderr,
              flush=True)
        sys.exit(143 if terminated else 130)
    except BAD_INPUT as error:
        refuse(error, run_dir, GUARD)
    except Exception as error:  # noqa: BLE001  (one line; the log has the traceback)
        log.error("the simulation failed:\n%s", traceback.format_exc())
        print(f"error: the simulation failed: {one_line(error)} (traceback in "
              f"{run_dir / 'simulate.log'})", file=sys.stderr, flush=True)
        sys.exit(1)
    print(result.summary())
    print(results_line(run_dir, result.files), flush=True)


def fitted_problem_group(argv: list[str]) -> list[str]:
    """``argv`` with ``problem=<the fit's problem group>`` added (unless given), read from
    the run named by ``run=``; exits 2 with one line where there is none or it is no fit."""
    given = next((a.split("=", 1)[1] for a in argv if a.startswith("run=")), None)
    if given is None:
        print("error: run=<the directory of a fitted run> is required (e.g. scripts/simulate.sh "
              "run=outputs/arm3d/levenberg_marquardt/<time>)", file=sys.stderr)
        sys.exit(2)
    if any(a.startswith("problem=") for a in argv):
        return argv
    try:
        fitted = read_fitted_run(given)
    except ConfigurationError as error:
        print("error: " + one_line(error), file=sys.stderr)
        sys.exit(2)
    choice = str(fitted.settings["name"])
    hydra_yaml = fitted.directory / ".hydra" / "hydra.yaml"
    try:
        choices = yaml.safe_load(hydra_yaml.read_text())["hydra"]["runtime"]["choices"]
        choice = str(choices.get("problem") or choice)
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        pass        # a run without Hydra's record: the problem's own group
    return [*argv, f"problem={choice}"]


def refuse_a_taken_run_dir(argv: list[str]) -> None:
    """Exit 2 with one line, before Hydra writes ``.hydra/`` and ``simulate.log``, where
    ``hydra.run.dir`` is the fitted run or holds a fit or a simulation
    (:func:`~torchfit.run.simulating.check_run_dir`)."""
    given = next((a.split("=", 1)[1] for a in argv if a.startswith("hydra.run.dir=")), None)
    run = next((a.split("=", 1)[1] for a in argv if a.startswith("run=")), None)
    if given is None or "${" in given or any(a in ("-m", "--multirun") for a in argv):
        return
    fitted = None
    if run is not None:
        path = Path(run).expanduser()
        fitted = path if path.is_dir() or path.suffix != ".pt" else path.parent
    try:
        check_run_dir(given, fitted, "hydra.run.dir")
    except ConfigurationError as error:
        print("error: " + one_line(error), file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    refuse_a_taken_run_dir(sys.argv[1:])
    sys.argv[1:] = fitted_problem_group(sys.argv[1:])
    run_hydra_app(main, lambda: _started, guard=GUARD)
