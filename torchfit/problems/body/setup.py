"""A rigged body's set-up as a person follows it: the rig checked first, every step on the console.

:class:`~.problem.RiggedBody` builds in steps (reading the animation, checking the rig,
tetrahedralising, embedding, attaching the rig, the first simulation); each logs what it
does, its counts and its time (:mod:`torchfit.steps`, logger ``torchfit.setup``), so the
console shows the tet count, the number of driven vertices and where the tet cache is
before the first iteration. The rig check (:mod:`torchfit.mesh.rig_check`) runs before
anything is built or cached: a refused rig costs a second and writes nothing. Once the rig
is attached, :func:`report_rig` prints it once (bones, lengths, attach radius, driven
vertices per bone, and whether the file gave each or the reader derived it and how); the
run keeps it as ``rig.json``.
"""
from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path
from typing import Any, Iterator

from ...mesh import MeshError
from ...mesh import (Animation, AnimationError, KeptMesh, RigReport, Skeleton, TetMesh,
                     TetOptions, check_animation, default_cache_dir, rig_description,
                     rig_lines, tetrahedralize_canonical)
from ...physics import newton_progress
from ...steps import SETUP_LOGGER, count, step
from .frame import body_surface
from ..config import ProblemConfigError, require_setting

#: seconds between two progress lines of the first simulation (at most one per iteration)
FIRST_SIMULATION_BEAT_S = 5.0


def animation_summary(animation: Animation, in_file: int | None = None) -> str:
    """``2,466 surface vertices, 48 frames, a skeleton of 2 bones (weights given)``; where
    ``animation`` is a selection of the file's ``in_file`` frames: ``8 frames (4 of them
    used here)``."""
    used = animation.n_frames
    frames = f"{count(used)} frames" if in_file is None or in_file == used else \
        f"{count(in_file)} frames ({count(used)} of them used here)"
    text = f"{count(animation.n_vertices)} surface vertices, {frames}, "
    skeleton = animation.skeleton
    if skeleton is not None:
        weights = "weights given" if skeleton.weights is not None else "weights from distance"
        return text + f"a skeleton of {skeleton.n_bones} bones ({weights})"
    return text + f"{count(animation.driven.mask.sum())} driven surface vertices"


def check_rig(cfg: Any, animation: Animation) -> RigReport | None:
    """The rig against the frames (``problem.rig_check``, ``problem.rig_tolerance``);
    a failure is a :class:`ProblemConfigError` naming the frames, bones and likely cause."""
    if not cfg.rig_check:
        return None
    with step("checking the rig against the frames") as progress:
        try:
            report = check_animation(animation, cfg.rig_tolerance)
        except AnimationError as err:
            raise ProblemConfigError(f"{err} (problem.rig_check=false fits it anyway; "
                                     "problem.rig_tolerance sets the tolerance)") from err
        progress.result = report.line().removeprefix("rig check: ")
    return report


def report_rig(skeleton: Skeleton, drive: Any) -> dict:
    """The attached rig on the set-up's console, one line per bone then the attach radius and
    the weights (:func:`torchfit.mesh.rig_lines`), each saying whether the file gave it or
    how it was derived; returns the description ``rig.json`` keeps
    (:func:`torchfit.mesh.rig_description`; ``drive``: the :class:`~torchfit.mesh.rig.Drive`
    that counts the driven vertices per bone)."""
    description = rig_description(skeleton, drive)
    log = logging.getLogger(SETUP_LOGGER)
    for line in rig_lines(description):
        log.info("rig: %s", line)
    return description


@contextlib.contextmanager
def first_simulation(n_frames: int, n_tets: int, model: str) -> Iterator[None]:
    """Progress of a problem's first simulation: a start line, Newton's iterations and
    converged frames every ``FIRST_SIMULATION_BEAT_S`` seconds, the time at the end."""
    with step(f"first simulation of {count(n_frames)} frames ({count(n_tets)} tetrahedra, "
              f"{model})") as progress:
        last = [time.perf_counter()]

        def report(iteration: int, converged: int, frames: int) -> None:
            if time.perf_counter() - last[0] >= FIRST_SIMULATION_BEAT_S:
                last[0] = time.perf_counter()
                progress.beat(f"Newton iteration {iteration}, {converged} of {frames} frames "
                              "converged")

        with newton_progress(report):
            yield
        progress.result = f"{count(n_frames)} frames in equilibrium"


#: the widest fTetWild envelope accepted (a fraction of the bounding-box diagonal)
MAX_TET_EPSILON = 0.05
#: the highest fTetWild stop energy accepted (its default is 10)
MAX_TET_STOP_ENERGY = 1000.0


def check_tet_settings(cfg: Any) -> None:
    """The ``tet_*`` settings :func:`tet_options` hands to fTetWild (one-line
    :class:`ProblemConfigError` each)."""
    for key in ("tet_edge_length", "tet_epsilon", "tet_stop_energy"):
        require_setting(getattr(cfg, key) > 0, cfg, key, "must be positive")
    require_setting(cfg.tet_count is None or cfg.tet_count >= 1, cfg, "tet_count",
                    "must be a positive number of tetrahedra (or null)")
    require_setting(cfg.tet_edge_length <= 1, cfg, "tet_edge_length", "is a fraction of "
                    "the bounding-box diagonal: must lie in (0, 1] (e.g. 0.05)")
    # wider, fTetWild's envelope no longer follows the surface (a limb becomes a slab)
    require_setting(cfg.tet_epsilon <= MAX_TET_EPSILON, cfg, "tet_epsilon", "is the "
                    "envelope as a fraction of the bounding-box diagonal: must lie in (0, "
                    f"{MAX_TET_EPSILON:g}] (default 1e-3)")
    # fTetWild stops optimising once every element's AMIPS energy is below this (a
    # regular tetrahedron has 3); far above, elements too distorted to simulate remain
    require_setting(cfg.tet_stop_energy <= MAX_TET_STOP_ENERGY, cfg, "tet_stop_energy",
                    f"must lie in (0, {MAX_TET_STOP_ENERGY:g}] (fTetWild's element energy "
                    "where its optimisation stops; default 10)")


def tet_options(cfg: Any) -> TetOptions:
    """The tetrahedralisation options of the ``tet_*`` settings."""
    return TetOptions(edge_length_fac=cfg.tet_edge_length, epsilon=cfg.tet_epsilon,
                      stop_energy=cfg.tet_stop_energy, optimize=cfg.tet_optimize,
                      count=cfg.tet_count)


def tet_mesh(cfg: Any, animation: Animation, motion: Any = None,
             kept: KeptMesh | None = None) -> TetMesh:
    """The rest surface tetrahedralised with the ``tet_*`` settings (``tet_count``: a
    target count, :mod:`torchfit.mesh.tetwild.size`) in canonical form, in the body's
    principal frame (:func:`.frame.body_surface`; ``motion`` ``(F, V, 3)`` settles a round
    body's frame), cached in ``cache_dir``; the run's own mesh ``kept`` comes first where it
    is this surface's, from this file or another
    (:class:`torchfit.mesh.tetwild.store.KeptMesh`). The mesh's ``canonical`` is the
    canonical surface (for :meth:`~torchfit.mesh.tetwild.store.KeptMesh.frame_for`)."""
    options = tet_options(cfg)
    cache = Path(cfg.cache_dir).expanduser() / "tetmesh" if cfg.cache_dir else \
        default_cache_dir()
    try:
        surface = body_surface(animation.rest_vertices, animation.faces, motion)
        mesh = None if kept is None else kept.mesh_for(animation.rest_vertices,
                                                       animation.faces, options, surface)
        # the surface's warnings were given once, with the animation's name
        return mesh if mesh is not None else tetrahedralize_canonical(surface, options,
                                                                      cache_dir=cache)
    except MeshError as err:
        raise ProblemConfigError(f"{animation.path}: {err}") from err
