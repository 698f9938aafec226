"""Simulate a fitted material on an animation of the same body: ``simulate``.

A fitted run (its directory, or its ``params.pt`` inside it) and the settings of an
animation in; the simulated frames, their surface error against the animation and the files
of :mod:`torchfit.reporting.simulation` out. What the ``init=<run> solver.max_iter=0`` route
of a fit computes for its frames, without the homogeneous baseline, the Jacobian, the model
comparison and the fit's outputs: one cold Newton solve per frame, from the animated pose.

The body is built from the settings the run was fitted with (``.hydra/config.yaml``, else
``result.json``'s ``config``), overridden by ``settings`` (another animation: ``path``, or
the arm's ``max_flexion``, ``n_frames``, ...; ``frames``; Newton's tolerances), on the
fitted body's own tetrahedral mesh (the run's ``mesh.npz``; a run without one: the mesh
cache, checked against the checkpoint's mesh digest). Refused with one line
(:class:`~.options.FitConfigError`), before anything is written, where the
parameterisation does not match: a run of a problem that is not a body, a setting of the
parameterisation or material changed (:data:`FITTED_SETTINGS`), an animation whose rest
surface (vertices, faces) is not the fitted body's, a ``params.pt`` of another parameter
count, field or transform, or one whose field the body's parameterisation does not
reproduce. The animation's frames may differ from the fit's in number and poses: every
frame of it is simulated unless ``settings`` names ``frames`` (the fit's ``frames`` and its
held-out frames, :data:`FIT_ONLY_SETTINGS`, do not apply).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
import yaml
from torch import Tensor

from ..errors import ConfigurationError
from ..linalg import set_threads
from ..problems import PROBLEMS, RiggedBody, build_problem
from ..problems.body import RUN_MESH_FILE, fitted_mesh, read_run_mesh
from ..reporting import (CHECKPOINT_FILE, PARAMS_FILE, PROGRESS_LOGGER, RESULT_FILE,
                         comparison_picture, ensure_progress_visible, fitted_damping,
                         modulus_units, write_frames, write_json)
from .directory import check_writable
from .lock import hold
from .options import FitConfigError
from .start import read_params

progress = logging.getLogger(PROGRESS_LOGGER)

#: settings of a body that make its parameterisation and material: simulate keeps the fit's
FITTED_SETTINGS = ("name", "parameters", "grid", "transform", "model", "nu", "E0",
                   "tet_edge_length", "tet_epsilon", "tet_stop_energy", "tet_optimize",
                   "dtype")
#: settings of the fit alone, reset before the overrides: where its field started (the
#: fitted parameters replace it) and which frames it fitted and held out (simulate takes its
#: frames from the animation it is given: every frame unless ``problem.frames`` says)
FIT_ONLY_SETTINGS = {"init_field": "", "frames": None, "validation_frames": None,
                     "validation_every": 0}
#: settings ``simulate`` sets for itself (a user's override still wins): it takes no
#: derivatives, so a body in time keeps no step's factorisation (``checkpoint_every=0``:
#: about ``2 sqrt(S)`` states; with every step's factor a 240-frame shot of the short arm
#: held 15 GB)
SIMULATE_SETTINGS = {"checkpoint_every": 0}
#: relative difference allowed between the fitted field and the one ``theta`` maps to here
_FIELD_RTOL = 1e-9


@dataclasses.dataclass
class FittedRun:
    """What ``simulate`` reads of a fitted run (:func:`read_fitted_run`)."""

    directory: Path
    theta: Tensor
    field: Tensor | None
    field_name: str | None
    transform: str | None
    settings: dict[str, Any]
    inputs: dict[str, str] | None


@dataclasses.dataclass
class SimulationResult:
    """The simulated frames of a fitted material and their errors.

    Attributes:
        state: tetrahedron vertex positions ``(F, n, 3)``.
        surface: the user's surface vertices ``(F, V, 3)``.
        frame_errors: per frame ``(F,)``: ``surface_err_mean``, ``surface_err_max`` (m),
            ``joint_volume_change``, ``inverted_tets``.
        newton_iterations, frame_seconds: per frame.
        wall_s: the whole call (building the body included).
        run_dir, files: where the outputs went (``None``, ``[]``: no directory).
    """

    fitted: Path
    problem: Any
    state: Tensor
    surface: Tensor
    field: Tensor
    frame_errors: dict[str, np.ndarray]
    newton_iterations: list[int]
    frame_seconds: list[float]
    wall_s: float
    run_dir: Path | None = None
    files: list[Path] = dataclasses.field(default_factory=list)

    @property
    def surface_err_mean(self) -> float:
        return float(np.mean(self.frame_errors["surface_err_mean"]))

    def summary(self) -> str:
        errors = self.frame_errors["surface_err_mean"]
        # the animation's frame number, not the index into the simulated selection
        worst = int(self.problem.frame_numbers()[int(np.argmax(errors))])
        inverted = int(np.count_nonzero(self.frame_errors["inverted_tets"]))
        # in time the integrator counts steps, not Newton iterations per frame (it said "0")
        work = f"{self.problem.integrator.n_steps} time steps" if \
            self.problem.time.in_time else f"{sum(self.newton_iterations)} Newton iterations"
        return (f"simulated {len(errors)} frames of {self.problem.animation.path.parent.name} "
                f"with the material of {self.fitted}: mean surface error "
                f"{1e3 * self.surface_err_mean:.4g} mm (worst frame {worst}: "
                f"{1e3 * float(errors.max()):.4g} mm), {work}, {inverted} frames with inverted tetrahedra, {self.wall_s:.1f} s")

    def as_dict(self) -> dict[str, Any]:
        per_frame = {k: np.asarray(v).tolist() for k, v in self.frame_errors.items()}
        return {"status": "done", "fitted_run": str(self.fitted),
                "animation": str(self.problem.animation.path),
                "n_frames": int(self.state.shape[0]),
                "frame_names": list(self.problem.frame_names()),
                "surface_err_mean": self.surface_err_mean,
                "surface_err_max": float(np.max(self.frame_errors["surface_err_max"])),
                "per_frame": {**per_frame, "newton_iterations": list(self.newton_iterations),
                              "seconds": list(self.frame_seconds)},
                "n_tets": int(self.problem.model.n_cells),
                "n_params": int(self.problem.parameterization.n_params),
                "wall_s": self.wall_s}


def read_fitted_run(path: str | Path) -> FittedRun:
    """The fitted ``theta`` (and field, its name and transform), the problem settings it was
    fitted with and the checkpoint's input digests of the run at ``path`` (its directory or
    its ``params.pt``). Raises :class:`FitConfigError` (one line naming the file)."""
    path = Path(path).expanduser()
    params = path / PARAMS_FILE if path.is_dir() else path
    directory = params.parent
    if not params.is_file():
        raise FitConfigError(f"run={path}: no {PARAMS_FILE} there; give the directory of a "
                             "finished fit (it holds params.pt)")
    saved = read_params(params, f"run={params}")
    theta = saved["theta"]
    field = saved.get("field") if isinstance(saved.get("field"), Tensor) else None
    return FittedRun(directory, theta.detach(), field, saved.get("field_name"),
                     saved.get("transform"), _fitted_settings(directory),
                     _input_digests(directory / CHECKPOINT_FILE))


def _fitted_settings(directory: Path) -> dict[str, Any]:
    """The problem settings of the fit: ``.hydra/config.yaml``, else ``result.json``."""
    hydra_config, result = directory / ".hydra" / "config.yaml", directory / RESULT_FILE
    try:
        if hydra_config.is_file():
            settings = (yaml.safe_load(hydra_config.read_text()) or {}).get("problem")
        elif result.is_file():
            settings = json.loads(result.read_text()).get("config", {}).get("problem")
        else:
            settings = None
    except (OSError, ValueError, yaml.YAMLError, AttributeError) as e:
        raise FitConfigError(f"run={directory}: cannot read the settings it was fitted with "
                             f"({' '.join(str(e).split())[:120]})") from None
    if not isinstance(settings, dict) or not settings.get("name"):
        raise FitConfigError(f"run={directory}: no problem settings found ({hydra_config} or "
                             f"{result}); give the directory of a fit, which holds them")
    return dict(settings)


def _input_digests(checkpoint: Path) -> dict[str, str] | None:
    if not checkpoint.is_file():
        return None
    try:
        with open(checkpoint, "rb") as f:
            payload = torch.load(f, map_location="cpu", weights_only=True)
        return dict(payload.get("inputs") or {}) or None
    except Exception:  # noqa: BLE001  (only a cross-check: the field check still applies)
        return None


def simulate(run: str | Path, settings: Mapping[str, Any] | None = None,
             run_dir: str | Path | None = None, *, threads: int | None = None,
             progress_lines: bool = True) -> SimulationResult:
    """Simulate the material fitted in ``run`` on an animation of the same body (module
    docstring).

    Args:
        run: the fitted run's directory, or its ``params.pt``.
        settings: problem settings over the fit's (the new animation: ``path``; for the arm
            ``max_flexion``, ``n_frames``, ...; ``frames``: ``None`` for all).
        run_dir: where the outputs go (created; :mod:`torchfit.reporting.simulation` and
            ``result.json``); ``None``: no files.
        threads: torch / MKL threads (``None`` or 0: leave as they are).
        progress_lines: one line per frame (frame i/F, Newton iterations, seconds).
    Raises:
        FitConfigError: a mismatch of parameterisation or body, a bad run (nothing written).
        ConfigurationError: any other bad setting (nothing written).
    """
    start = time.perf_counter()
    fitted = read_fitted_run(run)
    run_path = None if run_dir is None else Path(run_dir).resolve()
    if run_path is not None:
        check_run_dir(run_path, fitted.directory)
    problem = build_fitted_body(fitted, dict(settings or {}))
    theta = check_parameters(fitted, problem)
    if run_path is not None:
        check_writable(run_path)
    if threads:
        set_threads(threads)
    if progress_lines:
        ensure_progress_visible()
    with hold(run_path):
        field = problem.field(theta).detach()
        if getattr(problem.cfg, "dynamic", False):
            state, iterations, seconds = simulate_motion(problem, theta, progress_lines)
        else:
            state, iterations, seconds = simulate_frames(problem, field, progress_lines)
        with torch.no_grad():
            errors = problem.frame_errors(state)
            surface = problem.observation.surface(state)
        result = SimulationResult(fitted.directory, problem, state, surface, field, errors,
                                  iterations, seconds, 0.0, run_path)
        if run_path is not None:
            run_path.mkdir(parents=True, exist_ok=True)
            result.files = write_frames(run_path, problem, state, field,
                                        problem.poses.material_density(
                                            problem.simulation_input(theta)),
                                        fitted_damping(problem, theta))
            worst = int(np.argmax(errors["surface_err_mean"]))
            result.files.append(comparison_picture(run_path, problem, state, worst,
                                                   problem.frame_names()))
        result.wall_s = time.perf_counter() - start
        if run_path is not None:
            write_json(run_path / RESULT_FILE, {**result.as_dict(),
                                                "modulus_units": modulus_units(problem).as_dict(),
                                                "settings": _plain(problem.cfg)})
            result.files.append(run_path / RESULT_FILE)
    return result


#: files that make a directory a fit's or a simulation's: simulate never writes into one
RUN_FILES = (RESULT_FILE, PARAMS_FILE)


def check_run_dir(run_dir: str | Path, fitted_dir: str | Path | None = None,
                  setting: str = "run_dir") -> None:
    """Refuse (:class:`FitConfigError`, one line naming ``setting``) an output directory
    that is the fitted run ``fitted_dir`` or holds a fit or a simulation (:data:`RUN_FILES`):
    the simulation's ``result.json``, frames and logs would mix with (or replace) theirs."""
    run_dir = Path(run_dir).expanduser().resolve()
    fitted = None if fitted_dir is None else Path(fitted_dir).expanduser().resolve()
    held = [name for name in RUN_FILES if (run_dir / name).exists()]
    if fitted is not None and run_dir == fitted:
        what = f"is the fitted run of run={fitted}"
    elif held:
        what = f"already holds a fit or a simulation ({', '.join(held)})"
    else:
        return
    raise FitConfigError(f"{setting}={run_dir} {what}: a simulation writes its own "
                         f"{RESULT_FILE}, frames and logs; choose another {setting} (a new or "
                         f"empty directory), nothing was written")


def build_fitted_body(fitted: FittedRun, overrides: dict[str, Any]) -> RiggedBody:
    """The body of the fit with ``overrides`` (another animation of it), on the fit's mesh."""
    name = str(fitted.settings.get("name"))
    entry = PROBLEMS.get(name)
    if entry is None or not issubclass(entry.problem_class, RiggedBody):
        raise FitConfigError(f"run={fitted.directory} is a fit of problem {name}; simulate "
                             "applies the material of a body fitted to an animation "
                             "(problem=animation or arm3d)")
    for key in FITTED_SETTINGS:
        if key in overrides and overrides[key] != fitted.settings.get(key):
            raise FitConfigError(f"problem.{key}={overrides[key]}: simulate keeps the fitted "
                                 f"parameterisation and material ({key} "
                                 f"{fitted.settings.get(key)!r} in {fitted.directory}); leave "
                                 "it out")
    merged = {**fitted.settings, **FIT_ONLY_SETTINGS, **SIMULATE_SETTINGS, **overrides}
    mesh_file = fitted.directory / RUN_MESH_FILE
    stored = None
    if mesh_file.is_file():
        try:
            stored = read_run_mesh(mesh_file)
        except ConfigurationError as e:
            raise FitConfigError(f"run={fitted.directory}: {e}") from None
        except Exception as e:  # noqa: BLE001  (MeshError: an unreadable mesh.npz)
            raise FitConfigError(f"run={fitted.directory}: {' '.join(str(e).split())}; "
                                 "simulate needs the fitted body's mesh") from None
    problem = build_problem(name, merged, None if stored is None else fitted_mesh(stored))
    assert isinstance(problem, RiggedBody)
    if stored is None and fitted.inputs and "tet mesh" in fitted.inputs:
        now = problem.input_digests()["tet mesh"]
        if now != fitted.inputs["tet mesh"]:
            raise FitConfigError(f"run={fitted.directory} has no {RUN_MESH_FILE} and the mesh "
                                 f"cache gives another tetrahedral mesh ({now}, fitted on "
                                 f"{fitted.inputs['tet mesh']}): simulate needs the fitted "
                                 "body's mesh (the same cache entry, or a run that keeps it)")
    return problem


def check_parameters(fitted: FittedRun, problem: RiggedBody) -> Tensor:
    """``theta`` of the fit, checked against ``problem``'s parameterisation."""
    where = f"run={fitted.directory / PARAMS_FILE}"
    in_time, simulated_in_time = bool(fitted.settings.get("dynamic")), bool(problem.cfg.dynamic)
    if in_time and not simulated_in_time:    # (was a parameter count pointing at problem.grid)
        raise FitConfigError(f"run={fitted.directory} was fitted in time (problem.dynamic=true):"
                             " its parameters are the field and the damping; simulate it in "
                             "time with problem.dynamic=true")
    if simulated_in_time and not in_time:
        raise FitConfigError(f"problem.dynamic=true: run={fitted.directory} was fitted frame by "
                             "frame (quasistatic) and holds no damping; simulate it with "
                             "problem.dynamic=false, or fit it in time first")
    n = problem.parameterization.n_params
    for key, saved, ours in (("field", fitted.field_name, problem.field_name),
                             ("transform", fitted.transform, problem.parameterization.transform)):
        if saved is not None and saved != ours:
            raise FitConfigError(f"{where} holds a {key} {saved!r}, this body's is {ours!r}; "
                                 "give a fit of the same parameterisation")
    if fitted.theta.shape != (n,):
        raise FitConfigError(f"{where} has {tuple(fitted.theta.shape)} parameters, this "
                             f"body's parameterisation has ({n},); give a fit of the same "
                             "parameters (problem.parameters, problem.grid)")
    theta = fitted.theta.to(dtype=problem.theta0.dtype, device=problem.theta0.device)
    if not bool(torch.isfinite(theta).all()):
        raise FitConfigError(f"{where} holds parameters that are not finite")
    if fitted.field is not None:
        field = problem.field(theta).detach().cpu().to(torch.float64)
        saved = fitted.field.to(torch.float64)
        if saved.shape != field.shape or not torch.allclose(field, saved, rtol=_FIELD_RTOL,
                                                            atol=0.0):
            raise FitConfigError(f"{where}: its parameters map to another field on this body "
                                 f"({tuple(field.shape)} tetrahedra against "
                                 f"{tuple(saved.shape)} fitted): the mesh or the "
                                 "parameterisation is not the fit's")
    return theta


def simulate_frames(problem: RiggedBody, field: Tensor,
                    progress_lines: bool = True) -> tuple[Tensor, list[int], list[float]]:
    """Every frame's equilibrium for ``field``, one cold Newton solve per frame from the
    animated pose (as the fit's evaluation of a new point): positions ``(F, n, 3)``, Newton
    iterations and seconds per frame; a progress line per frame. A frame that repeats an
    earlier frame's pose (the same rig positions and start: an animation that plays back)
    gets that frame's solution (0 iterations), which its own solve would reproduce."""
    states: list[Tensor] = []
    iterations: list[int] = []
    seconds: list[float] = []
    seen: dict[bytes, int] = {}
    total = problem.n_frames
    names = problem.frame_names()
    quasistatic = problem.poses.quasistatic
    with torch.no_grad(), problem.warm_starts.independent():
        for f in range(total):
            tick = time.perf_counter()
            rig = problem.dirichlet_positions[f:f + 1].to(field)
            start = problem.start_positions[f:f + 1].to(field)
            pose = rig.cpu().numpy().tobytes() + start.cpu().numpy().tobytes()
            if pose in seen:
                states.append(states[seen[pose]])
                iterations.append(0)
                seconds.append(time.perf_counter() - tick)
                if progress_lines:
                    progress.info("frame %d/%d (%s): the pose of frame %d/%d, its solution",
                                  f + 1, total, names[f], seen[pose] + 1, total)
                continue
            seen[pose] = f
            x = quasistatic(field, rig, x_init=start)
            states.append(x[0])
            iterations.append(int(sum(quasistatic.last_newton_iterations)))
            seconds.append(time.perf_counter() - tick)
            if progress_lines:
                progress.info("frame %d/%d (%s): %d Newton iterations, %.2f s", f + 1, total,
                              names[f], iterations[-1], seconds[-1])
    return torch.stack(states), iterations, seconds


def simulate_motion(problem: Any, theta: Tensor, progress_lines: bool = True
                    ) -> tuple[Tensor, list[int], list[float]]:
    """The body in time (``problem.dynamic=true``) with the fitted field and damping: one
    integration from frame 0 through the shot, positions ``(F, n, 3)`` at its frames; the
    Newton iterations are not counted per frame (0), the seconds are the integration's
    spread evenly over the frames."""
    tick = time.perf_counter()
    with torch.no_grad():
        x = problem.simulate(problem.simulation_input(theta))
    wall = time.perf_counter() - tick
    frames = int(x.shape[0])
    if progress_lines:
        steps = problem.integrator.n_steps
        progress.info("integrated %d frames at %g fps (%d %s steps of %.4g s) in %.1f s",
                      frames, problem.time.fps, steps, problem.cfg.scheme.value, problem.time.dt,
                      wall)
    return x, [0] * frames, [wall / frames] * frames


def _plain(cfg: Any) -> dict[str, Any]:
    from .options import plain_settings

    out = plain_settings(cfg)
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in out.items()}
