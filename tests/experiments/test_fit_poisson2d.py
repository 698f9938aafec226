"""``experiments/fit.py problem=poisson2d`` run as a user runs it: its TensorBoard images,
scalars and hparams (read back from the event files) and its PNGs."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import metadata as hparams_metadata
from tensorboard.util import tensor_util
from conftest import run_fit_app

REPO = Path(__file__).resolve().parents[2]


def fit(run_dir: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return run_fit_app(run_dir, *overrides, timeout=timeout)


@pytest.fixture(scope="module")
def split_bregman_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("poisson2d") / "sb"
    proc = fit(run_dir, "problem=poisson2d", "problem.N=8", "problem.noise=1e-3",
               "solver=split_bregman", "solver.max_iter=5", "snapshot_iterations=[1]",
               "snapshot_every=2", "progress=false")
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    result = json.loads((run_dir / "result.json").read_text())
    acc = EventAccumulator(str(run_dir / "tb"), size_guidance={"images": 0, "tensors": 0})
    acc.Reload()
    return run_dir, proc, result, acc


def last_value(acc: EventAccumulator, tag: str) -> tuple[int, float]:
    event = acc.Tensors(tag)[-1]
    return event.step, float(tensor_util.make_ndarray(event.tensor_proto))


def test_images_at_the_expected_steps(split_bregman_run):
    _, _, result, acc = split_bregman_run
    last = result["iterations"]
    assert last == 5
    steps = [0, 1, 2, 4, 5]         # 0, snapshot 1, every 2nd, the last
    assert [e.step for e in acc.Images("field/k_image")] == steps
    assert [e.step for e in acc.Images("field/k_error_aligned_image")] == steps
    assert [e.step for e in acc.Images("field/k_true_image")] == [0]
    assert [e.step for e in acc.Images("field/k_panels")] == [last]
    for tag in ("field/k_image", "field/k_error_aligned_image", "field/k_true_image"):
        # 7 x 7 cells, each 16 x 16 pixels
        assert {(e.width, e.height) for e in acc.Images(tag)} == {(112, 112)}, tag


def test_scalars_and_final_metrics(split_bregman_run):
    _, _, result, acc = split_bregman_run
    last = result["iterations"]
    tensors = set(acc.Tags()["tensors"])
    assert {"fit/misfit", "fit/tv", "metrics/k_err_rel_aligned", "metrics/u_err_2"} <= tensors
    assert last_value(acc, "fit/misfit") == (last, pytest.approx(result["misfit"], rel=1e-12))
    assert last_value(acc, "metrics/k_err_rel_aligned") == \
        (last, pytest.approx(result["k_err_rel_aligned"], rel=1e-12))
    assert last_value(acc, "final/iterations") == (last, last)
    assert last_value(acc, "final/wall_s") == (last, pytest.approx(result["wall_s"], rel=1e-12))


def test_hparams_session(split_bregman_run):
    _, _, _, acc = split_bregman_run
    content = acc.PluginTagToContent("hparams")
    start = hparams_metadata.parse_session_start_info_plugin_data(
        content["_hparams_/session_start_info"])
    hp = start.hparams
    assert hp["solver.name"].string_value == "split_bregman"
    assert hp["problem.name"].string_value == "poisson2d"
    assert hp["problem.N"].number_value == 8
    assert hp["problem.noise"].number_value == 1e-3
    assert hp["problem.data"].string_value == "dense"
    assert hp["problem.pattern"].string_value == "blocks"
    assert hp["problem.seed"].number_value == 0
    assert hp["solver.isotropic"].WhichOneof("kind") == "bool_value"
    for key in ("solver.mu_rel", "solver.beta_rel", "solver.tau", "solver.max_iter"):
        assert hp[key].WhichOneof("kind") == "number_value", key
    assert "solver.mu" not in hp                      # None: automatic, left out
    assert "_hparams_/session_end_info" in content


def test_pngs(split_bregman_run):
    run_dir, proc, _, _ = split_bregman_run
    for name, min_size in (("field.png", (800, 250)), ("error_curves.png", (500, 500)),
                           ("snapshots.png", (400, 300))):
        with Image.open(run_dir / name) as image:
            assert image.format == "PNG"
            assert image.size[0] >= min_size[0] and image.size[1] >= min_size[1], name
        assert name in proc.stdout
    assert "could not draw" not in proc.stdout + proc.stderr
