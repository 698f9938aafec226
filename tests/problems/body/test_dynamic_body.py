"""``problem.dynamic=true`` on a rigged body (the capsule): contract, derivatives, slow
motion against the quasistatic body, held-out later window, refusals, recovery."""
from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml

import torchfit
from helpers.capsule_animation import write_capsule
from torchfit.mesh import load_animation
from torchfit.problems import ProblemConfigError, RiggedBody, build_problem

#: six frames of the capsule's bend (0 to 30 degrees, then held)
ANGLES = (0.0, 10.0, 20.0, 30.0, 30.0, 30.0)


def capsule(root: Path, fps: float | None = None, name: str = "capsule") -> Path:
    folder = root / name
    if not (folder / "animation.yaml").is_file():
        write_capsule(folder, angles=ANGLES)
        if fps is not None:
            manifest = yaml.safe_load((folder / "animation.yaml").read_text())
            manifest["fps"] = fps
            (folder / "animation.yaml").write_text(yaml.safe_dump(manifest))
    return folder


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("dynamic_body")


def settings(root: Path, **more) -> dict:
    return {"path": str(capsule(root)), "cache_dir": str(root / "cache"), "tet_count": 600,
            "grid": [2, 2, 3], "dynamic": True, "substeps": 2, **more}


@pytest.fixture(scope="module")
def synthetic(root) -> RiggedBody:
    return build_problem("animation", settings(root, target="synthetic", frames=[0, 1, 2, 3]))


def test_dynamic_flag_builds_the_body_in_time(synthetic, root):
    problem = synthetic
    assert isinstance(problem, RiggedBody) and problem.time.in_time and not problem.scale_free
    assert type(build_problem("animation", {**settings(root), "dynamic": False})) is RiggedBody
    n_field = 2 * 2 * 3
    assert problem.parameterization.n_params == n_field + 2
    # moduli in pascals: the blocks truth is E_blocks times E_reference (1e4 Pa)
    assert problem.cfg.E_blocks == pytest.approx([1.0e4, 4.0e4, 4.0e3])
    assert problem.cfg.E0_unit.value == "Pa"
    assert 1.0e4 < float(problem.field_true.max()) <= 4.0e4
    assert float(problem.field(problem.theta0).mean()) == pytest.approx(1.0e4)
    described = problem.describe()
    assert described["fps"] == 24.0 and described["substeps"] == 2
    assert described["steps"] == 3 * 2 and described["scheme"] == "bdf2"
    # lumped mass: density times the tetrahedra's volume
    volume = float(problem.mesh.signed_volumes().sum())
    assert described["mass"] == pytest.approx(1000.0 * volume, rel=1e-12)
    assert problem.x_true.shape == (4, problem.model.n_vertices, 3)
    truth = problem.metrics(problem.true_theta())
    assert truth["k_err_rel"] == pytest.approx(0.0, abs=1e-12)
    assert truth["misfit"] == pytest.approx(0.0, abs=1e-12)
    start = problem.metrics(problem.theta0)
    assert start["alpha_damping_err_rel"] == pytest.approx(0.5)       # 1.0 against 2.0
    assert start["k_err_rel_aligned"] > 0.1
    # an initial-value problem has no branches to choose: continuation=auto leaves it alone
    from torchfit.run.continuation import continuation_applies
    assert not continuation_applies(problem)


def test_fewer_frames_follow_the_same_trajectory(synthetic):
    """The rig's spline runs through the whole shot, so the body fitted on its first frames
    (a continuation's first stage, a shorter fit) moves exactly as the whole fit's body up
    to there: the truth of frames 0, 1 is the full problem's, reproduced to round-off."""
    first = synthetic.with_frames([0, 1])
    assert first.dirichlet_positions.shape == synthetic.dirichlet_positions.shape
    x = first.simulate(synthetic.time.true_input(synthetic.field_true))
    assert torch.allclose(x, synthetic.x_true[:2], rtol=0, atol=1e-12)


@pytest.mark.parametrize("scheme", ["bdf2", "backward_euler"])
def test_dynamic_body_derivatives(root, scheme):
    problem = build_problem("animation", settings(root, target="synthetic", frames=[0, 2, 3],
                                                  scheme=scheme))
    report = torchfit.verify(problem, at="truth", perturbation=0.1, dot_tol=1e-9)
    assert abs(report.taylor.rate - 2.0) <= 0.05, report.format()
    assert report.dot.rel_error <= 1e-9, report.format()
    # the dense Jacobian (tangents forward in time) against the adjoint's J^T w
    theta = problem.theta0
    J = problem.forward_jacobian(theta)
    w = torch.randn(J.shape[0], dtype=J.dtype, generator=torch.Generator().manual_seed(1))
    theta_leaf = theta.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(problem.forward(theta_leaf), theta_leaf, w)
    assert torch.allclose(J.T @ w, grad, rtol=1e-9, atol=1e-12 * float(grad.abs().max()))


def test_a_density_scale_among_the_parameters(root, tmp_path):
    """``problem.fit_density=true`` under gravity: theta ends with the density scale (start
    1: ``problem.density``), its derivatives verify (Taylor rate 2, dot test, the dense
    Jacobian against the adjoint), the truth's scale is reported, and the written material's
    density is ``problem.density`` times the fitted scale."""
    problem = build_problem("animation", settings(
        root, target="synthetic", frames=[0, 2, 3], fit_density=True, density_scale=1.5,
        gravity=[0.0, 0.0, -9.81]))
    n_field = 2 * 2 * 3
    assert problem.parameterization.n_params == n_field + 3
    assert problem.parameterization.scalar_names == ("alpha", "beta", "density_scale")
    assert float(problem.theta0[-1]) == 0.0                          # exp(0) = 1
    assert problem.metrics(problem.true_theta())["density_scale_err_rel"] == \
        pytest.approx(0.0, abs=1e-12)
    assert problem.metrics(problem.theta0)["density_scale_err_rel"] == pytest.approx(1 / 3)
    report = torchfit.verify(problem, at="truth", perturbation=0.1, dot_tol=1e-9)
    assert abs(report.taylor.rate - 2.0) <= 0.05, report.format()
    assert report.dot.rel_error <= 1e-9, report.format()
    theta = problem.theta0
    J = problem.forward_jacobian(theta)
    assert float(J[:, -1].abs().max()) > 0                             # the data see it
    w = torch.randn(J.shape[0], dtype=J.dtype, generator=torch.Generator().manual_seed(2))
    theta_leaf = theta.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(problem.forward(theta_leaf), theta_leaf, w)
    assert torch.allclose(J.T @ w, grad, rtol=1e-9, atol=1e-12 * float(grad.abs().max()))
    density, source = problem.poses.material_density(problem.simulation_input(problem.true_theta()))
    assert density == pytest.approx(1500.0, rel=1e-12) and "fitted" in source
    if importlib.util.find_spec("pxr") is not None:      # the layer an artist gets
        from pxr import Usd, UsdGeom

        from torchfit.reporting.body_files import write_usd
        truth = problem.true_theta()
        with torch.no_grad():
            x = problem.simulate(problem.simulation_input(truth))
        write_usd(tmp_path, problem, problem.observation.surface(x).numpy(), problem.field(truth).numpy(),
                  problem.poses.material_density(problem.simulation_input(truth)))
        stage = Usd.Stage.Open(str(tmp_path / "usd" / "body.usda"))
        tet = stage.GetDefaultPrim()
        written = UsdGeom.PrimvarsAPI(tet).GetPrimvar("density").Get()
        assert list(written) == pytest.approx([1500.0] * len(written))
        assert "fitted" in tet.GetCustomDataByKey("torchfit:densitySource")
    plain = build_problem("animation", settings(root))
    assert plain.poses.material_density(plain.simulation_input(plain.theta0))[0] == 1000.0
    with pytest.raises(ProblemConfigError, match="problem.density_scale=0.0: must be > 0"):
        build_problem("animation", settings(root, fit_density=True, density_scale=0.0))


def test_slow_motion_is_the_quasistatic_body(root):
    """Slowed down, the motion in time is the frame-by-frame equilibrium: the lag shrinks
    with the frame time T (first order: the damping force C v, v ~ 1 / T), below 1e-4 of the
    displacement slowed 1000x (0.024 fps); at 24 fps the flesh swings.

    Lightly damped flesh (alpha = 0.2 / s, beta = 1e-4 s): the lag is about
    alpha / (omega^2 T) + beta / T, and pytetwild's mesh (it varies run to run) sets the
    softest mode omega: slowed 100x, seven meshes gave 1.2e-5 to 1.4e-4 (alpha = 2 / s:
    2.4e-5 to 9.4e-4), so the 100x figure is measured in docs/notes/dynamics.md, not
    asserted here. Four substeps: with two (a 2 s step at 0.24 fps) the step's Newton
    stalled on 2 of 10 meshes (residual 2.7e-3, not halved in 10 iterations), with four on
    none of 6 (2026-12-02)."""
    common = {"cache_dir": str(root / "cache"), "tet_count": 1500, "grid": [2, 2, 3]}
    slow = capsule(root, fps=0.24, name="capsule_slow")
    quasistatic = build_problem("animation", {**common, "path": str(slow)})
    differences = {}
    for fps in (0.24, 0.024, 24.0):
        folder = slow if fps == 0.24 else capsule(root, fps=fps, name=f"capsule_{fps:g}")
        problem = build_problem("animation", {**common, "path": str(folder), "dynamic": True,
                                              "substeps": 4, "alpha0": 0.2, "beta0": 1e-4})
        assert problem.time.fps == fps
        assert problem.model.n_cells == quasistatic.model.n_cells   # one cached mesh
        physical = problem.simulation_input(problem.theta0)
        x = problem.simulate(physical)
        xq = quasistatic.simulate(physical[:-2])
        displacement = float((xq - problem.model.rest.points).norm(dim=-1).max())
        differences[fps] = float((x - xq).norm(dim=-1).max()) / displacement
    assert differences[0.24] < 1e-3, differences
    assert differences[0.024] < 1e-4, differences
    assert differences[0.024] < 0.2 * differences[0.24], differences
    assert differences[24.0] > 1e-2, differences


def test_validation_is_a_later_window(root):
    problem = build_problem("animation", settings(root, target="synthetic",
                                                  validation_frames=[4, 5]))
    assert problem.frame_numbers() == [0, 1, 2, 3]
    validation = problem.validation_problem()
    assert validation.frame_numbers() == [4, 5]
    # the held-out frames are simulated from t = 0 through the fitted window
    assert validation.dirichlet_positions.shape[0] == 6
    x = validation.simulate(validation.time.true_input(validation.field_true))
    assert torch.allclose(x, validation.x_true)
    with pytest.raises(ProblemConfigError, match="is not a later window: fitted frame 4"):
        build_problem("animation", settings(root, frames=[0, 4], validation_frames=[2, 3]))


@pytest.mark.parametrize("override, message", [
    ({"substeps": 0}, "problem.substeps=0: must be an integer >= 1"),
    # 10^12 steps to frame 5 ran without end (the step grid is built step by step)
    ({"substeps": 10**12}, r"problem.substeps=1000000000000: needs about .* for 5e\+12 "
                           r"implicit steps to frame 5 .*choose fewer problem.substeps"),
    ({"density": 0.0}, "problem.density=0.0: must be > 0"),
    # accepted before: Newton then took no step (the sweep in time, 2026-12-02)
    ({"newton_rtol": 1e12}, r"problem.newton_rtol=1000000000000.0: must be in \[0, 1\)"),
    ({"density": -1000.0}, "problem.density=-1000.0: must be > 0"),
    # accepted before (issue 50): a poor fit, called determined
    ({"density": 1e12}, r"problem.density=1000000000000.0: is not a density a body has: give "
                        r"kg/m\^3 within \[1, 100000\]"),
    ({"integrator": "torchdiffeq"}, "torchdiffeq does not apply to a body"),
    ({"validation_every": 2}, "hold out a later window"),
    ({"E_reference": 0.0}, "problem.E_reference=0.0: must be a positive"),
    ({"alpha0": -1.0, "transform": "identity"}, "is a negative damping coefficient"),
    ({"gravity": [0.0, -9.81]}, "problem.gravity=.*: must be null or three finite numbers"),
    ({"gravity": [0.0, 0.0, float("nan")]}, "problem.gravity=.*must be finite"),
    ({"gravity": [0.0, 0.0, -9.81], "dynamic": False}, "is read by the body in time only"),
])
def test_dynamic_settings_are_refused_with_one_line(root, override, message):
    with pytest.raises(ProblemConfigError, match=message) as err:
        build_problem("animation", settings(root, **override))
    assert "\n" not in str(err.value)


def test_a_material_layer_starts_the_body_in_time_in_pascals(root, tmp_path):
    """``problem.init_field`` in time: the layer's moduli become pascals by the unit it states
    (``Pa`` as written, ``relative to problem.E0`` times E0 in Pa, none: the units of the
    modulus settings), the damping starts at alpha0, beta0; an unknown unit is refused."""
    pytest.importorskip("pxr")
    import numpy as np

    from torchfit.mesh.formats.usd.writer import write_tet_mesh_usd

    base = build_problem("animation", settings(root, parameters="tet"))
    points, cells = np.asarray(base.mesh.points), np.asarray(base.mesh.cells)
    shape = 1.0 + 3.0 * (base.mesh.centroids()[:, 0] - points[:, 0].min()) / np.ptp(points[:, 0])

    def layer(name: str, values: np.ndarray, unit: str | None) -> str:
        material = {"youngsModulus": values, "poissonsRatio": np.full(len(cells), 0.45),
                    "density": np.full(len(cells), 1000.0)}
        return str(write_tet_mesh_usd(tmp_path / f"{name}.usda", points, cells,
                                      material=material,
                                      units=None if unit is None else {"youngsModulus": unit}))

    def start(path: str, **more) -> tuple[np.ndarray, list[float]]:
        problem = build_problem("animation", settings(root, parameters="tet", init_field=path,
                                                      alpha0=3.0, beta0=0.01, **more))
        field = problem.field(problem.theta0).numpy()
        return field, [float(v) for v in problem.time.scalars(problem.simulation_input(problem.theta0))]

    field, damping = start(layer("pa", 2.0e4 * shape, "Pa"))
    assert np.abs(field / (2.0e4 * shape) - 1).max() < 1e-6            # float32 in the layer
    assert damping == pytest.approx([3.0, 0.01], rel=1e-12)
    # what a scale-free fit writes: factors of its E0, here times E0 = 2 x 1e4 Pa
    field, _ = start(layer("relative", shape, "relative to problem.E0"), E0=2.0)
    assert np.abs(field / (2.0e4 * shape) - 1).max() < 1e-6
    # a painted layer states no unit: read as the modulus settings are
    painted = layer("painted", shape, None)
    field, _ = start(painted)                                          # factors of 1e4 Pa
    assert np.abs(field / (1.0e4 * shape) - 1).max() < 1e-6
    field, _ = start(painted, E0=5.0e3, E0_unit="Pa")                  # pascals
    assert np.abs(field / shape - 1).max() < 1e-6
    with pytest.raises(ProblemConfigError, match=r"problem.init_field=.*states the unit "
                                                 r"'kPa', which torchfit does not read") as err:
        start(layer("kilo", shape, "kPa"))
    assert "\n" not in str(err.value)


def test_under_gravity_the_body_starts_at_rest(root):
    """problem.gravity: the body starts in its static equilibrium under gravity for E0 (it
    sags below the rest shape) and, with the rig held still, stays there: no drop at t = 0;
    in weightlessness it is the rest shape. The time report names the steps and the error
    estimate. Gravity along the capsule's axis, the line of the few tetrahedron vertices its
    bones drive: across it the body swings round that line on some pytetwild meshes (2 in 8
    at E0 = 1e4 Pa), which a body too soft to hold itself shows on every mesh: refused."""
    still = root / "capsule_still"
    if not (still / "animation.yaml").is_file():
        write_capsule(still, angles=(0.0, 0.0, 0.0, 0.0))
    common = {"path": str(still), "cache_dir": str(root / "cache"), "tet_count": 600,
              "grid": [2, 2, 3], "dynamic": True, "substeps": 2}
    problem = build_problem("animation", {**common, "gravity": [0.0, 0.0, -9.81]})
    rest = problem.model.rest.points
    start = problem.time.system.x0.reshape(-1, 3)
    sag = start - rest
    mass = problem.time.system.mass.reshape(-1, 3)[:, 2]
    assert float((mass * sag[:, 2]).sum() / mass.sum()) < -1e-5      # the centre of mass drops
    # the driven vertices stay where the rig puts them at frame 0: the rest, to the round-off
    # of skinning it (1.7e-18 m on one pytetwild mesh)
    assert float(sag[torch.as_tensor(problem.dirichlet_vertices)].abs().max()) <= 1e-12
    x = problem.simulate(problem.simulation_input(problem.theta0))
    drift = float((x - start[None]).norm(dim=-1).max())
    assert drift <= 1e-6 * float(sag.norm(dim=-1).max()), drift
    weightless = build_problem("animation", common)
    assert torch.equal(weightless.time.system.x0.reshape(-1, 3), rest.to(weightless.time.system.x0))
    report = problem.time.report(problem.simulation_input(problem.theta0))
    assert report["steps"] == 3 * 2 and report["reference_steps"] == 12
    assert report["fps"] == 24.0 and report["substeps"] == 2 and report["scheme"] == "bdf2"
    assert 0.0 <= report["error_estimate"] <= 1e-6 * float(sag.norm(dim=-1).max())
    with pytest.raises(ProblemConfigError) as refused:              # 30 Pa: it cannot hang
        build_problem("animation", {**common, "gravity": [0.0, -9.81, 0.0], "E0": 0.003})
    message = str(refused.value)
    assert "\n" not in message and message.startswith("problem.gravity=[0.0, -9.81, 0.0]: ")
    assert "E0 = 30 Pa" in message and "raise problem.E0" in message


def test_the_folder_format_carries_its_frame_rate(root):
    folder = capsule(root, fps=30.0, name="capsule_30")
    assert load_animation(folder).fps == 30.0
    assert load_animation(capsule(root)).fps == 24.0
    bad = root / "capsule_bad"
    shutil.copytree(folder, bad)
    manifest = yaml.safe_load((bad / "animation.yaml").read_text())
    manifest["fps"] = -5
    (bad / "animation.yaml").write_text(yaml.safe_dump(manifest))
    with pytest.raises(Exception, match="fps must be a positive number"):
        load_animation(bad)


@pytest.mark.slow
def test_synthetic_recovery_of_field_and_damping(synthetic):
    """Levenberg-Marquardt on the dense Jacobian recovers the blocks field and damping."""
    result = torchfit.fit(synthetic, {"name": "levenberg_marquardt", "max_iter": 15},
                          options=torchfit.FitOptions(progress=False))
    metrics = result.metrics
    print({k: metrics[k] for k in ("k_err_rel", "k_err_rel_aligned", "alpha_damping_err_rel",
                                   "beta_damping_err_rel")}, "iterations", result.iterations)
    assert metrics["k_err_rel_aligned"] <= 1e-3, metrics
    assert metrics["alpha_damping_err_rel"] <= 1e-3, metrics
    assert metrics["beta_damping_err_rel"] <= 1e-3, metrics


@pytest.mark.slow
def test_fit_and_simulate_apps_in_time(root, tmp_path):
    """The fit app fits the capsule in time (synthetic target, held-out later window; its
    motion outputs draw without failing: the error over time, no 2-D strip of a 3-D body)
    and simulate runs the fitted material and damping on a new shot: OBJ frames, VTU, a USD
    point cache at the shot's frame rate."""
    from helpers.fit_app import run_fit_app
    from pxr import Usd

    from torchfit.run.simulating import simulate

    fit = tmp_path / "fit"
    done = run_fit_app(fit, "problem=animation", f"problem.path={capsule(root)}",
                       f"problem.cache_dir={root / 'cache'}", "problem.tet_count=600",
                       "problem.dynamic=true", "problem.substeps=2", "problem.grid=[2,2,3]",
                       "problem.frames=[0,1,2,3]", "problem.validation_frames=[4,5]",
                       "problem.target=synthetic", "solver.max_iter=1")
    assert done.returncode == 0, done.stderr[-2000:]
    log = (fit / "fit.log").read_text()
    assert "could not draw" not in log and "could not estimate" not in log, log[-2000:]
    assert "in time: 24 fps x 2 substeps = 6 BDF2 steps of 20.8 ms; integration error about" \
        in done.stdout, done.stdout
    timing = yaml.safe_load((fit / "result.json").read_text())["time_integration"]
    assert timing["reference_steps"] == 12 and 0.0 < timing["error_estimate_rel"] < 0.1
    assert (fit / "time_errors.png").is_file() and not (fit / "frames_strip.png").exists()
    summary = yaml.safe_load((fit / "result.json").read_text())
    assert summary["problem"]["dynamic"] is True and summary["problem"]["fps"] == 24.0
    shot = capsule(root, fps=30.0, name="capsule_shot30")
    result = simulate(fit, {"path": str(shot)}, tmp_path / "sim", progress_lines=False)
    assert result.state.shape[0] == len(ANGLES)
    assert len(list((tmp_path / "sim" / "frames").glob("*.obj"))) == len(ANGLES)
    assert (tmp_path / "sim" / "body.vtu").is_file()
    # no derivatives in simulate: no step's factorisation is kept (checkpoint_every=0)
    settings_used = json.loads((tmp_path / "sim" / "result.json").read_text())["settings"]
    assert settings_used["checkpoint_every"] == 0
    stage = Usd.Stage.Open(str(tmp_path / "sim" / "usd" / "frames.usda"))
    assert stage.GetTimeCodesPerSecond() == 30.0
    # the fitted damping beside the modulus, in the fit's layers and the simulation's
    from torchfit.mesh.formats.usd import read_damping
    fitted = (summary["alpha_damping"], summary["beta_damping"])
    for layer in (fit / "usd" / "body.usda", fit / "usd" / "material.usda",
                  tmp_path / "sim" / "usd" / "body.usda"):
        damping = read_damping(layer)
        assert (damping["alpha"], damping["beta"]) == ((fitted[0], "1/s"), (fitted[1], "s"))
        assert damping["w1"][0] == pytest.approx(summary["problem"]["damping_band"]["w1"])
    assert stage.GetEndTimeCode() == len(ANGLES) - 1


def test_write_arm_adds_keyframed_jiggle(tmp_path):
    """--jiggle overlays a damped oscillation after changes of speed on the folder's frames:
    frame 0 and the frames before the first change are the plain arm's; the jiggle then
    decays; the manifest carries --fps."""
    import subprocess
    import sys

    from torchfit.problems.body.procedural_arm import ArmShape, arm_animation, keyframed_jiggle

    jiggly = tmp_path / "jiggly"
    done = subprocess.run([sys.executable, "scripts/write_arm.py", str(jiggly), "--n-frames",
                           "24", "--jiggle", "1.0", "--fps", "30"], capture_output=True,
                          text=True, cwd=Path(__file__).resolve().parents[3])
    assert done.returncode == 0, done.stderr
    plain = arm_animation(ArmShape(n_frames=24))["frames"]
    b = load_animation(jiggly)
    assert b.fps == 30.0
    lag = torch.as_tensor(b.frames - plain).norm(dim=-1).amax(dim=-1)     # (F,)
    assert float(lag[0]) == 0.0 and float(lag.max()) > 1e-3
    # a uniform motion has no jiggle; a stop starts a decaying one
    x = torch.linspace(0, 1, 40, dtype=torch.float64).numpy()
    motion = (x[:, None, None] * 0.1).repeat(2, axis=1).repeat(3, axis=2)
    motion[20:] = motion[20]
    out = keyframed_jiggle(motion, torch.ones(2).numpy(), 24.0)
    assert abs(out[:20] - motion[:20]).max() < 1e-15
    after = abs(out[21:] - motion[21:]).max(axis=(1, 2))
    assert after[:6].max() > 10 * after[-6:].max() > 0


def test_a_time_step_the_integrator_cannot_take_is_refused_in_one_line(root, tmp_path):
    """A step whose Newton does not converge (here: one Newton iteration allowed, the bend
    needs more) is an UnstableStepError naming the step, its time and the setting (a failed
    trial inside a fit); at the fit's start the app refuses it: one error line, exit 2, and a
    synthetic truth that cannot be integrated is refused when the problem is built."""
    from helpers.fit_app import run_fit_app

    from torchfit.physics.dynamics import UnstableStepError

    problem = build_problem("animation", settings(root, frames=[0, 1, 2, 3], newton_max_iter=1))
    with pytest.raises(UnstableStepError) as err:
        problem.simulate(problem.simulation_input(problem.theta0))
    line = str(err.value)
    assert "\n" not in line and line.startswith("the implicit step to t = ")
    assert "did not converge" in line
    assert line.endswith("at 24 fps x 2 substeps: raise problem.substeps"), line
    with pytest.raises(ProblemConfigError, match=r"^problem.substeps=2: the body cannot be "
                       r"integrated with the synthetic target's true material \(problem.E_blocks, "
                       r"problem.E_regions, problem.alpha, problem.beta\): the implicit step to "
                       r"t = .*raise problem.substeps$"):
        build_problem("animation", settings(root, frames=[0, 1, 2, 3], newton_max_iter=1,
                                            target="synthetic"))
    run = tmp_path / "fit"
    done = run_fit_app(run, "problem=animation", f"problem.path={capsule(root)}",
                       f"problem.cache_dir={root / 'cache'}", "problem.tet_count=600",
                       "problem.dynamic=true", "problem.substeps=2", "problem.grid=[2,2,3]",
                       "problem.frames=[0,1,2,3]", "problem.newton_max_iter=1",
                       "solver.max_iter=1")
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert done.returncode == 2, done.stderr[-2000:]
    assert lines[-1].startswith("error: the fit's start cannot be simulated: the implicit "
                                "step to t = "), lines[-1]
    assert lines[-1].endswith("raise problem.substeps; the start is set by problem.E0, "
                              "problem.init_field, problem.alpha0, problem.beta0 (or init=)")
    assert not run.exists()          # the job made the directory: refused, nothing is left
    # the quasistatic body simulates its start before the solver does (the homogeneous
    # error of the run's description): refused the same way, naming the start's settings
    still = tmp_path / "still"
    done = run_fit_app(still, "problem=animation", f"problem.path={capsule(root)}",
                       f"problem.cache_dir={root / 'cache'}", "problem.tet_count=600",
                       "problem.grid=[2,2,3]", "problem.frames=[0,1,2,3]",
                       "problem.newton_max_iter=1", "solver.max_iter=1")
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert done.returncode == 2 and len(lines) == 1, done.stderr[-2000:]
    assert lines[0].startswith("error: the fit's start cannot be simulated: Newton did not "
                               "converge") and lines[0].endswith(
        "the start is set by problem.E0, problem.init_field (or init=)"), lines[0]
    assert not still.exists()


@pytest.mark.slow
def test_the_body_in_time_bounds_its_damping_by_the_physics(root, tmp_path):
    """The capsule's band: w1 at E0 (the lowest mode of K0 u = w^2 M u with the rig's
    vertices held, against scipy's dense generalised eigenproblem), w_frames = pi x 24 fps;
    the solver's bounds on log alpha, log beta are log(2 w1), log(2 / max(w1, w_frames));
    a rig target reports the damping and its ratios but no *_err_rel (no truth); the fit
    app refuses problem.beta0=1e12 in one line naming the bound and the ratio, exit 2,
    nothing written."""
    import math

    import numpy as np
    import scipy.linalg

    from helpers.fit_app import run_fit_app

    problem = build_problem("animation", settings(root, frames=[0, 1, 2, 3]))
    band, system = problem.time.band, problem.time.system
    free = system.free_dofs.numpy()
    field = torch.full((system.n_field,), float(problem.cfg.E0), dtype=torch.float64)
    pattern = system.elastic.tangent_pattern
    stiffness = pattern.to_scipy(pattern.assemble(system.rest_stiffness_contributions(field)))
    lowest = scipy.linalg.eigh(stiffness.toarray()[np.ix_(free, free)],
                               np.diag(system.mass.numpy()[free]), eigvals_only=True,
                               subset_by_index=[0, 0])[0]
    assert band.w1 == pytest.approx(math.sqrt(lowest), rel=1e-8)
    assert band.w_frames == pytest.approx(math.pi * 24.0, rel=1e-12)
    lower, upper = problem.theta_bounds()
    assert float(upper[-2]) == pytest.approx(math.log(2 * band.w1), rel=1e-12)
    assert float(upper[-1]) == pytest.approx(math.log(2 / band.w_high), rel=1e-12)
    assert float(lower[-1]) == -math.inf
    metrics = problem.metrics(problem.theta0)
    assert metrics["beta_damping"] == pytest.approx(0.008)
    assert metrics["damping_ratio_w1"] == pytest.approx(1.0 / (2 * band.w1) + 0.004 * band.w1)
    assert not any(k.endswith("_err_rel") and "damping" in k for k in metrics), metrics
    # on the bound: the summary line says the damping explains the motion
    at_bound = problem.simulation_input(problem.theta0).clone()
    at_bound[-1] = band.beta_max
    report = problem.time.damping_report(at_bound)
    assert report["on_bound"] == ["beta"] and report["explains_motion"]
    assert report["note"].startswith("the damping rather than the material explains the motion")
    assert not problem.time.damping_report(problem.simulation_input(problem.theta0))[
        "explains_motion"]
    # the integration error against the fitted error: a warning above half of it
    start = problem.simulation_input(problem.theta0)
    estimate = problem.time.report(start)["error_estimate"]
    assert "warnings" not in problem.time.report(start, {"surface_err_mean": 2.5 * estimate})
    warnings = problem.time.report(start, {"surface_err_mean": 1.5 * estimate})["warnings"]
    assert len(warnings) == 1 and warnings[0].startswith("the integration error (about ") \
        and warnings[0].endswith("raise problem.substeps"), warnings
    run = tmp_path / "fit"
    done = run_fit_app(run, "problem=animation", f"problem.path={capsule(root)}",
                       f"problem.cache_dir={root / 'cache'}", "problem.tet_count=600",
                       "problem.dynamic=true", "problem.substeps=2", "problem.grid=[2,2,3]",
                       "problem.beta0=1e12", "solver.max_iter=1")
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert done.returncode == 2 and len(lines) == 1, done.stderr[-2000:]
    assert lines[0].startswith("error: problem.beta0=1000000000000.0: gives the damping ratio "
                               "zeta = beta w / 2 = ") and "(pi x 24 frames/s of the " \
        "animation, the highest frequency they show), above 1 (critical damping, ZETA_MAX): " \
        "beta must be at most 2 ZETA_MAX / w = " in lines[0], lines[0]
    assert not run.exists()
