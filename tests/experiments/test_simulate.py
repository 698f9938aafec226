"""experiments/simulate.py: a fitted material on an animation of the same body (a capsule with
a two-bone rig, not the arm): the frames and errors of the ``init=`` / ``max_iter=0`` route,
OBJ and VTU out, one-line refusals that write nothing.

The apps run in the test's process (:func:`run_simulate_app`, :func:`helpers.apps.run_app`);
the simulate app's smoke test runs it as a subprocess
(:func:`test_a_fit_of_another_problem_is_refused_with_one_line`)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import meshio
import numpy as np
import pytest
import torch

from helpers.apps import run_app
from helpers.capsule_animation import write_capsule
from helpers.fit_app import REPO, run_fit_app
from helpers.runs import tree_digest
from torchfit.mesh.formats.folder import load_animation, write_animation
from torchfit.problems import build_problem
from torchfit.run import FitOptions, fit
from torchfit.run.options import FitConfigError
from torchfit.run.simulating import simulate

#: the capsule's fit: small mesh, 12 grid parameters, two iterations
FIT = ("problem=animation", "problem.tet_edge_length=0.15", "problem.grid=[2,2,3]",
       "solver.max_iter=2", "threads=1")
#: another animation of the capsule: four frames, other bends
OTHER_ANGLES = (5.0, 12.0, 20.0, 35.0)


def run_simulate_app(run_dir, *overrides, env=None):
    """``python experiments/simulate.py hydra.run.dir=<run_dir> <overrides>`` from the
    repository root, in this process."""
    return run_app("simulate.py", f"hydra.run.dir={run_dir}", *overrides, env=env)


def run_simulate_app_process(run_dir, *overrides, env=None):
    """:func:`run_simulate_app` as a subprocess (the app's smoke test)."""
    environment = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    environment.update(env or {})
    return subprocess.run([sys.executable, "experiments/simulate.py", f"hydra.run.dir={run_dir}",
                           *overrides], cwd=REPO, env=environment, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A fitted capsule run (its own mesh cache), the animation it fitted, another one."""
    root = tmp_path_factory.mktemp("simulate")
    folder = write_capsule(root / "capsule")
    other = write_capsule(root / "capsule_other", angles=OTHER_ANGLES)
    cache = root / "cache"
    run = root / "fit"
    proc = run_fit_app(run, *FIT, f"problem.path={folder}", f"problem.cache_dir={cache}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {"root": root, "run": run, "folder": folder, "other": other, "cache": cache}


def test_the_fit_keeps_its_mesh(fitted):
    with np.load(fitted["run"] / "mesh.npz") as mesh:
        cells = mesh["cells"]
        assert cells.shape[1] == 4 and len(cells) > 100
        rest = load_animation(fitted["folder"]).rest_vertices
        np.testing.assert_array_equal(mesh["surface_vertices"], rest)
    result = json.loads((fitted["run"] / "result.json").read_text())
    assert result["problem"]["n_tets"] == len(cells)


@pytest.mark.slow      # two apps and a fit route on the capsule (about 40 s on 2 free cores)
def test_simulate_reproduces_the_init_route_on_another_animation(fitted):
    """The same frames (to Newton's tolerance) and per-frame errors as a fit started at the
    fitted parameters that takes no step, on an animation the fit never saw; without the
    mesh cache (the run keeps its mesh)."""
    root = fitted["root"]
    new = (f"problem.path={fitted['other']}",)
    route = root / "route"
    proc = run_fit_app(route, *FIT[:3], "solver.max_iter=0", "threads=1", *new,
                       f"problem.cache_dir={fitted['cache']}", f"init={fitted['run']}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = root / "sim"
    proc = run_simulate_app(out, f"run={fitted['run']}", *new, "problem.cache_dir=", "threads=1",
                            env={"TORCHFIT_CACHE_DIR": str(root / "empty-cache")})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "frame 4/4" in proc.stdout + proc.stderr
    assert proc.stdout.count("simulated 4 frames") == 1
    assert not (root / "empty-cache" / "tetmesh").exists()      # nothing tetrahedralised
    ours, theirs = np.load(out / "frames.npz"), np.load(route / "frames.npz")
    scale = np.abs(theirs["positions"]).max()
    # simulate solves frame by frame and the route all frames at once, so round-off differs:
    # they end apart within Newton's tolerance (measured 6.5e-9 of the scale with one thread
    # each, 2026-12-02), hence 1e-7. On some pytetwild meshes round-off in a line search
    # sends one route of a frame to another equilibrium (2.5e-3 m on 0.16 m in one suite
    # run): such a frame must still be an equilibrium of the fitted material in both routes.
    apart = np.abs(ours["positions"] - theirs["positions"]).reshape(4, -1).max(1) > 1e-7 * scale
    assert not apart.all(), "every frame apart"
    result = json.loads((out / "result.json").read_text())
    compared = json.loads((route / "model_comparison.json").read_text())
    np.testing.assert_allclose(np.asarray(result["per_frame"]["surface_err_mean"])[~apart],
                               np.asarray(compared["fitted"]["corotated"]
                                          ["surface_err_mean_per_frame"])[~apart],
                               rtol=1e-6, atol=1e-12)
    assert_equilibria(fitted, [ours["positions"], theirs["positions"]])
    assert result["n_frames"] == 4 and len(result["per_frame"]["newton_iterations"]) == 4
    # OBJ on the user's vertices and faces, one per frame; VTU with per-frame displacement
    animation = load_animation(fitted["other"])
    objs = sorted((out / "frames").glob("frame_*.obj"))
    assert len(objs) == 4
    lines = objs[2].read_text().splitlines()
    vertices = np.array([[float(v) for v in line.split()[1:]] for line in lines
                         if line.startswith("v ")])
    assert len(vertices) == animation.n_vertices
    assert sum(line.startswith("f ") for line in lines) == len(animation.faces)
    np.testing.assert_array_equal(vertices, ours["surface"][2])
    vtu = meshio.read(out / "body.vtu")
    assert sorted(k for k in vtu.point_data) == [f"displacement_{f:03d}" for f in range(4)]
    np.testing.assert_allclose(vtu.points + vtu.point_data["displacement_003"],
                               ours["positions"][3], atol=1e-12)
    assert (out / "simulation.png").stat().st_size > 1000


def assert_equilibria(fitted, states):
    """Each of ``states`` ``(F, n, 3)`` is, in every frame, an equilibrium of the fitted
    material on the other animation: its free residual at most 1e-7 of the one at the
    animated pose (measured: simulate's up to 8e-11, the route's 1.2e-9, 2026-12-02)."""
    sim = simulate(fitted["run"], {"path": str(fitted["other"]),
                                   "cache_dir": str(fitted["cache"])}, progress_lines=False)
    problem = sim.problem
    equilibrium = problem.poses.quasistatic.equilibrium
    free = equilibrium.free_dofs
    field = sim.field.to(torch.float64)
    start = problem.start_positions.reshape(problem.n_frames, -1)
    reference = problem.model.residual(start, field)[:, free].norm(dim=1)
    for state in states:
        x = torch.as_tensor(state, dtype=torch.float64).reshape(len(state), -1)
        residual = problem.model.residual(x, field)[:, free].norm(dim=1)
        assert (residual <= 1e-7 * reference).all(), (residual / reference).tolist()


def test_simulate_on_the_fitted_animation_is_the_fits_cold_evaluation(fitted):
    """Frame by frame, the equilibria the fit's evaluation of its final parameters computes
    cold (every frame at once, from the animated pose: what init= with max_iter=0 gives),
    and the errors the fit reports for them."""
    result = simulate(fitted["run"], {"cache_dir": str(fitted["cache"])}, progress_lines=False)
    problem = result.problem
    with torch.no_grad(), problem.warm_starts.independent():
        cold = problem.simulate(result.field)
    scale = float(cold.abs().max())
    assert float((result.state - cold).abs().max()) <= 1e-8 * scale
    assert result.frame_errors["surface_err_mean"].shape == (3,)
    np.testing.assert_allclose(result.frame_errors["surface_err_mean"],
                               problem.frame_errors(cold)["surface_err_mean"], rtol=1e-9)
    saved = torch.load(fitted["run"] / "params.pt", weights_only=True)
    assert torch.equal(result.field, saved["field"])


def test_another_body_is_refused_with_one_line_and_nothing_written(fitted):
    """A rest surface that is not the fitted one (the capsule 5 % larger): exit 2, one
    line naming the animation, no run directory."""
    animation = load_animation(fitted["folder"])
    larger = fitted["root"] / "larger"
    write_animation(larger, 1.05 * animation.rest_vertices, animation.faces,
                    1.05 * animation.frames, skeleton=animation.skeleton)
    out = fitted["root"] / "refused"
    proc = run_simulate_app(out, f"run={fitted['run']}", f"problem.path={larger}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and errors[0].startswith("error: "), proc.stderr
    assert "not the fitted body" in errors[0] and "rest surface" in errors[0]
    assert not out.exists()


@pytest.mark.parametrize("into", ["the fit", "a simulation", "a params.pt"])
def test_simulate_into_a_run_directory_of_a_fit_or_simulation_is_refused(fitted, tmp_path,
                                                                          into):
    """``hydra.run.dir=<the fitted run>`` (or a directory holding another simulation, or a
    ``params.pt``): refused up front in one line saying to choose another
    ``hydra.run.dir``; the directory is left byte-identical (no simulate.log, no .hydra/)."""
    if into == "the fit":
        target = fitted["run"]
    else:
        target = tmp_path / "taken"
        (target / ".hydra").mkdir(parents=True)
        (target / ".hydra" / "config.yaml").write_text("problem: {}\n")
        name = "result.json" if into == "a simulation" else "params.pt"
        (target / name).write_bytes(b'{"simulated_frames": 4}' if name == "result.json"
                                    else b"not a checkpoint")
    before = tree_digest(target)
    stat = {p: p.stat().st_mtime_ns for p in target.rglob("*")}
    proc = run_simulate_app(target, f"run={fitted['run']}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and errors[0].startswith(f"error: hydra.run.dir={target.resolve()}"), \
        proc.stderr
    assert "choose another hydra.run.dir" in errors[0] and "problem.path" not in errors[0]
    assert ("is the fitted run" in errors[0]) == (into == "the fit")
    assert tree_digest(target) == before
    assert {p: p.stat().st_mtime_ns for p in target.rglob("*")} == stat
    assert not (target / "simulate.log").exists()


def test_a_changed_parameterisation_is_refused(fitted):
    out = fitted["root"] / "grid"
    proc = run_simulate_app(out, f"run={fitted['run']}", "problem.grid=[3,3,3]")
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error: problem.grid=[3, 3, 3]: simulate keeps")
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_params_of_another_parameter_count_or_problem_are_refused(fitted, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(fitted["run"], copy)
    params = torch.load(copy / "params.pt", weights_only=True)
    params["theta"] = torch.zeros(len(params["theta"]) + 1, dtype=torch.float64)
    torch.save(params, copy / "params.pt")
    with pytest.raises(FitConfigError, match=r"has \(13,\) parameters, this body's "
                                             r"parameterisation has \(12,\)"):
        simulate(copy, {"cache_dir": str(fitted["cache"])}, tmp_path / "out",
                 progress_lines=False)
    params["theta"] = params["theta"][:-1] + 0.5        # not the field params.pt holds
    torch.save(params, copy / "params.pt")
    with pytest.raises(FitConfigError, match="map to another field"):
        simulate(copy, {"cache_dir": str(fitted["cache"])}, tmp_path / "out",
                 progress_lines=False)
    assert not (tmp_path / "out").exists()


def test_a_fit_of_another_problem_is_refused_with_one_line(tmp_path):
    """A spring chain's run (fitted from Python: no .hydra/, its settings in result.json):
    exit 2, one line, nothing written. The simulate app's smoke test: the app as a
    subprocess."""
    spring = tmp_path / "spring"
    fit(build_problem("spring1d", {"n": 8}), {"name": "gauss_newton", "max_iter": 1},
        run_dir=spring, options=FitOptions(progress=False))
    with pytest.raises(FitConfigError, match="is a fit of problem spring1d; simulate applies"):
        simulate(spring, progress_lines=False)
    out = tmp_path / "out"
    proc = run_simulate_app_process(out, f"run={spring}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines() == [
        f"error: run={spring} is a fit of problem spring1d; simulate applies the material of "
        "a body fitted to an animation (problem=animation or arm3d)"]
    assert not out.exists()
    proc = run_simulate_app_process(out, "problem.path=/nowhere")
    assert proc.returncode == 2 and proc.stderr.startswith("error: run=<the directory of a "
                                                           "fitted run> is required")
    assert not out.exists()


@pytest.mark.slow      # a resumed fit of the capsule through the app
def test_a_resume_without_the_cache_uses_the_runs_mesh(fitted, tmp_path):
    """The cache entry gone: the resume builds the body on the run's mesh.npz (the
    checkpoint's mesh digest agrees) and continues; nothing is tetrahedralised."""
    run = tmp_path / "fit"
    shutil.copytree(fitted["run"], run)
    before = (run / "mesh.npz").read_bytes()
    cache, away = fitted["cache"], tmp_path / "cache-away"
    cache.rename(away)
    try:
        proc = run_fit_app(run, *FIT[:3], "solver.max_iter=3", "threads=1",
                           f"problem.path={fitted['folder']}", f"problem.cache_dir={cache}",
                           "resume=true")
        assert not (cache / "tetmesh").exists()
    finally:
        shutil.rmtree(cache, ignore_errors=True)
        away.rename(cache)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (run / "mesh.npz").read_bytes() == before
    assert json.loads((run / "result.json").read_text())["iterations"] == 3


@pytest.mark.slow      # a fit with held-out frames and four simulations (about 30-60 s)
def test_simulate_takes_its_frames_from_the_animation_it_is_given(fitted, tmp_path):
    """The fit's ``frames`` and ``validation_frames`` do not apply to ``simulate``: a fit that
    held out frames 4 and 5 of six simulates a three-frame shot, every frame of its own
    animation by default and with ``frames=null``, and its held-out frames when asked."""
    six = write_capsule(tmp_path / "capsule_six", angles=(0.0, 8.0, 15.0, 22.0, 30.0, 36.0))
    run = tmp_path / "fit"
    proc = run_fit_app(run, *FIT[:3], "solver.max_iter=1", "threads=1", f"problem.path={six}",
                       "problem.validation_frames=[4,5]", f"problem.cache_dir={fitted['cache']}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    # one set-up on the console: the held-out frames' body is built quietly; the frame
    # count says what the file holds and what is used
    console = proc.stdout + proc.stderr
    assert console.count("reading the animation") == 2          # its start and end lines
    assert "6 frames (4 of them used here)" in console
    assert console.count("attaching the rig") == 2
    cache = {"cache_dir": str(fitted["cache"])}
    # a second shot with fewer frames than the fit's validation frames reach
    shot = simulate(run, {**cache, "path": str(fitted["folder"])}, progress_lines=False)
    assert shot.state.shape[0] == 3
    for settings, frames in (({}, 6), ({"frames": None}, 6), ({"frames": [4, 5]}, 2)):
        result = simulate(run, {**cache, **settings}, progress_lines=False)
        assert result.state.shape[0] == frames
        assert result.problem.frame_numbers() == ([4, 5] if frames == 2 else list(range(6)))
    # through the app, as the guide types it
    out = tmp_path / "sim"
    proc = run_simulate_app(out, f"run={run}", f"problem.path={fitted['folder']}",
                            "problem.frames=null", f"problem.cache_dir={fitted['cache']}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((out / "result.json").read_text())["n_frames"] == 3
    (line,) = [x for x in proc.stdout.splitlines() if x.startswith("results: ")]
    for name in ("frames/", "body.vtu", "frames.npz", "usd/", "simulation.png"):
        assert name in line, (name, line)
