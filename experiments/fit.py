"""Fit a problem's material field with a solver: the Hydra adapter over :func:`torchfit.run.fit`.

    python experiments/fit.py                                   # spring1d, Gauss-Newton
    python experiments/fit.py problem.noise=1e-4 solver=levenberg_marquardt
    python experiments/fit.py -m experiment=seed_table          # a sweep preset (conf/experiment/)
    python experiments/fit.py hydra.run.dir=<run> resume=true   # continue a killed run exactly
    python experiments/fit.py problem.frames=null init=<run>    # start from an earlier fit
    python experiments/fit.py problem=arm3d continuation=true   # frames far from a fold first
                                        # (default auto: where a synthetic target folds)

The run directory's files are those of :mod:`torchfit.run` plus Hydra's ``.hydra/`` and
``fit.log`` (which has the progress table). Exit statuses: :mod:`app` (0 done, 1 the fit
failed, 2 bad input or the directory in use by another run, and nothing written, 3 under
torchrun: another rank stopped answering, the run resumable, 130 interrupted, 143
terminated). In a multirun (``-m``) a job that fails writes
``result.json`` with ``"status": "failed"`` and its ``error`` line, and returns ``+inf``
(what a sweeper minimises is ``objective_metric``; Optuna aborts a study on NaN), so that
the other jobs run.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
import shlex
import signal
import sys
import traceback
from pathlib import Path
from typing import Any, NoReturn

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:       # this checkout's experiments/ (and torchfit), installed or not
    sys.path.insert(0, str(REPO))

from experiments.cli import FIT_HELP, command_line  # noqa: E402

if __name__ == "__main__":      # help, unreadable overrides, paths: before the heavy imports
    sys.argv[1:] = command_line(sys.argv[1:], FIT_HELP)

from experiments.app import (  # noqa: E402
    BAD_INPUT, RANK_LOST, RunDirGuard, Terminated, checked_config, no_space, no_space_line,
    one_line, refuse, results_line, run_hydra_app)

import hydra  # noqa: E402
import matplotlib  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

matplotlib.use("Agg")   # pictures are files and TensorBoard images; never a window
from torchfit import build_problem  # noqa: E402
from torchfit.config import FitConfig, register_configs  # noqa: E402
from torchfit.run import (FIRST_STAGE_DIR, FitOptions, check_threads,  # noqa: E402
                          continuation_applies, continuation_setting, distributed, fit,
                          fit_continued, first_stage_iterations, resumed_mesh, set_threads,
                          solver_config, write_json)

register_configs()
log = logging.getLogger("fit")
GUARD = RunDirGuard(sys.argv[1:])
SESSION = distributed.DistributedSession()     # this process's part in a torchrun job
_started = False


def prepare(cfg: DictConfig, run_dir: Path | None = None
            ) -> tuple[Any, Any, FitOptions, dict[str, Any]]:
    """Problem, solver config, options and the plain config; raises on bad input. A resume
    builds a body on the mesh its run keeps (``mesh.npz``): no mesh cache needed."""
    config = checked_config(cfg, FitConfig)
    solver = solver_config(dict(config["solver"]))
    continuation_setting(config["continuation"])        # checked before the (long) build
    first_stage_iterations(solver, config["continuation_first_max_iter"])
    threads = config.get("threads")
    check_threads(threads)
    if threads:
        set_threads(threads)     # before the build: a synthetic target is simulated there
    kept = resumed_mesh(run_dir) if config["resume"] and run_dir is not None else None
    problem = build_problem(str(config["problem"].get("name")), dict(config["problem"]), kept)
    options = FitOptions(**{f.name: config[f.name] for f in dataclasses.fields(FitOptions)
                            if f.name in config})
    return problem, solver, options, config


def resume_command(run_dir: Path) -> str:
    """The command that continues the run in ``run_dir`` (under torchrun: this job's launch
    and overrides, :func:`torchrun_resume_command`)."""
    if distributed.launched():
        return torchrun_resume_command(run_dir, sys.argv[1:])
    return f"python experiments/fit.py {shlex.quote(f'hydra.run.dir={run_dir}')} resume=true " \
           "(and the same overrides)"


def torchrun_resume_command(run_dir: Path, argv: list[str]) -> str:
    """``torchrun ... experiments/fit.py hydra.run.dir=<run_dir> <argv's overrides>
    resume=true``: the launch from torchrun's environment (one node: ``--standalone
    --nproc_per_node=<ranks>``; several: their count and a reminder of the rendezvous
    options, which the ranks do not see), or the one ``experiments/launch.py`` names
    (``TORCHFIT_LAUNCH``); each override shell-quoted."""
    nodes = int(os.environ.get("GROUP_WORLD_SIZE", "1"))
    per_node = int(os.environ.get("LOCAL_WORLD_SIZE", str(distributed.world_size())))
    launch = f"torchrun --standalone --nproc_per_node={per_node} experiments/fit.py" \
        if nodes == 1 else f"torchrun --nnodes={nodes} --nproc_per_node={per_node} <the same " \
                           "rendezvous options> experiments/fit.py"
    launch = os.environ.get("TORCHFIT_LAUNCH") or launch
    kept = [a for a in argv if not a.startswith(("hydra.run.dir=", "resume=", "+resume=",
                                                 "++resume="))]
    words = [f"hydra.run.dir={run_dir}", *kept, "resume=true"]
    return f"{launch} {' '.join(shlex.quote(w) for w in words)}"


def rank_lost(who: str, run_dir: Path) -> NoReturn:
    """Rank 0 once ``who`` (``"rank 1 of 2"``) stopped answering: one line naming it, the
    iteration and the resume command; the traceback to ``fit.log`` only; exit 3. Nothing is
    lost: the checkpoint of the last finished iteration is written atomically. torchrun's
    SIGTERM (it follows a worker's death within its monitor interval) is ignored from here."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    SESSION.abandon()
    _log_to_file(f"{who} stopped answering:\n{traceback.format_exc()}")
    print(f"error: {who} stopped answering (killed, or its machine went away) "
          f"{_when(run_dir)}; nothing of the run is lost: continue with: "
          f"{resume_command(run_dir)}", file=sys.stderr, flush=True)
    sys.exit(RANK_LOST)


def _when(run_dir: Path) -> str:
    """``during iteration N``: the one after the checkpoint's."""
    import torch

    try:
        payload = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=True)
        iteration, finished = int(payload["iteration"]), bool(payload.get("finished"))
    except Exception:  # noqa: BLE001  (none yet)
        return "before the first iteration ended"
    return "after the fit, while writing its outputs" if finished else \
        f"during iteration {iteration + 1}"


def _log_to_file(message: str) -> None:
    """``message`` to the job's log files (Hydra's ``fit.log``), not to the console."""
    record = log.makeRecord(log.name, logging.ERROR, __file__, 0, message, None, None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


@hydra.main(config_path="../conf", config_name="fit", version_base="1.3")
def main(cfg: DictConfig) -> float:
    global _started
    _started = True
    run_dir = Path(HydraConfig.get().runtime.output_dir).resolve()
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    try:
        problem, solver, options, config = prepare(cfg, run_dir)
        if config["resume"]:            # warm starts saved by as many processes as now
            distributed.check_resume(run_dir, distributed.world_size())
        continuation = continuation_setting(config["continuation"])
        continuing = continuation is True or (continuation == "auto"
                                              and continuation_applies(problem))
        if distributed.launched():      # torchrun: rank 0 fits, the others simulate frames
            SESSION.lead(problem, {**config, "continuation": continuing,
                                   "run_dir": str(run_dir)}, multirun)
        if continuing:
            result = fit_continued(problem, solver, run_dir=run_dir,
                                   resume=bool(config["resume"]), options=options,
                                   config=config, init=config["init"],
                                   min_volume=config["continuation_min_volume"],
                                   first_max_iter=config["continuation_first_max_iter"])
        else:
            result = fit(problem, solver, run_dir=run_dir, resume=bool(config["resume"]),
                         options=options, config=config, init=config["init"])
    except KeyboardInterrupt as interrupt:     # Ctrl-C, or SIGTERM (app.Terminated)
        terminated = isinstance(interrupt, Terminated)
        lost = SESSION.stopped_answering(None) if terminated else None
        if lost is not None:        # torchrun stops rank 0 because another rank died
            rank_lost(lost, run_dir)
        print(f"{'terminated (SIGTERM)' if terminated else 'interrupted'}; continue with: "
              f"{resume_command(run_dir)}", file=sys.stderr, flush=True)
        sys.exit(143 if terminated else 130)
    except Exception as error:  # noqa: BLE001  (reported as one line; the log has the rest)
        if distributed.launched() and distributed.communication_failure(error):
            # a collective lost its peer; torchrun's SIGTERM follows within its monitor
            # interval (0.1 s): ignored while rank 0 finds which rank is gone and says so
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            rank_lost(SESSION.stopped_answering(error) or "a rank", run_dir)
        if no_space(error) and not multirun:
            # a fault, not bad input: what the run wrote stays (checkpoint, history) and the
            # same command with resume=true continues it once there is space
            log.error("the fit stopped, the disk is full:\n%s", traceback.format_exc())
            print("error: " + no_space_line(error, run_dir, resume_command(run_dir)),
                  file=sys.stderr, flush=True)
            sys.exit(2)
        bad_input = isinstance(error, BAD_INPUT)
        if not bad_input:
            log.error("the fit failed:\n%s", traceback.format_exc())
        if multirun:        # the other jobs of the sweep go on
            print(f"error: job {run_dir.name}: {one_line(error)}", file=sys.stderr, flush=True)
            write_json(run_dir / "result.json", {"status": "failed", "error": one_line(error),
                                                 "config": OmegaConf.to_container(
                                                     cfg, resolve=False, enum_to_str=True)})
            return math.inf
        if bad_input:
            refuse(error, run_dir, GUARD)
        print(f"error: the fit failed: {one_line(error)} (traceback in {run_dir / 'fit.log'})",
              file=sys.stderr, flush=True)
        sys.exit(1)
    if result.solve is None and result.resumed_from is not None:
        GUARD.restore(run_dir)      # a finished run: nothing done, nothing rewritten
    print(result.summary())
    print(results_line(run_dir, result.files, ("checkpoint.pt",)))
    for line in result.highlights:      # what the problem's own outputs point at
        print(line)
    if result.first_stage is not None:
        print(f"first stage (the frames far from a fold): {result.first_stage.summary()}; "
              f"its run: {run_dir / FIRST_STAGE_DIR}")
        # both stages' curves side by side: the run directory holds tb/ and unique_frames/tb/
        print(f"tensorboard --logdir {shlex.quote(str(run_dir))}", flush=True)
    else:
        print(f"tensorboard --logdir {shlex.quote(str(run_dir / 'tb'))}", flush=True)
    return result.value(str(config["objective_metric"]))


def build_for_rank(config: dict[str, Any]) -> Any:
    """A torchrun worker's problem: the one rank 0 built, from rank 0's settings; a resume
    builds it on the run directory's mesh as rank 0 does, where this rank can read it."""
    threads = config.get("threads")
    if isinstance(threads, int) and not isinstance(threads, bool) and threads > 0:
        set_threads(threads)
    kept = resumed_mesh(Path(config["run_dir"])) if config.get("resume") and \
        config.get("run_dir") and Path(config["run_dir"]).is_dir() else None
    return build_problem(str(config["problem"].get("name")), dict(config["problem"]), kept)


if __name__ == "__main__":
    if distributed.launched() and distributed.rank() > 0:
        sys.exit(SESSION.serve(build_for_rank, resume_command))   # no Hydra, no files
    try:
        run_hydra_app(main, lambda: _started, guard=GUARD)
    finally:
        if distributed.launched():
            SESSION.stop()
