"""End-to-end: ``ns-train s2camp`` / ``s2camp-camp`` on a generated scene, its logged metrics, the COLMAP export.

One short ``ns-train s2camp`` run (module-scoped fixture) with perturbed cameras on the conftest's tiny scene is shared
by most tests here. It runs without ``--machine.device-type``: on a machine without CUDA the method config must fall
back to the CPU by itself. Slow (about a minute of training on two CPU cores), but part of ``make test``.

What a run this short can show (measured while writing these tests, see docs in ``s2camp_ns/demo.py``): photometric
refinement from a NeRF trained for a few dozen steps reliably reduces large per-camera focal-length errors, while
pose errors of the CamP protocol's size sit below the gradient-noise floor of such a run. So the perturbation here is
a large per-camera focal error (sigma 10%) on top of CamP's small pose perturbation, without the shared dolly zoom
(focal against distance, a near-ambiguity that only long runs resolve), and the test asserts the focal error falls.
The camera learning rate grows exponentially from 1e-5 to 1e-3 over the run: cameras wait for the NeRF to learn
something before they move (moving them against a blurry NeRF only adds noise).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from s2camp_ns.demo import SMALL_MODEL

pytestmark = pytest.mark.slow

BIN = Path(sys.executable).parent
ITERATIONS = 200
LOG_EVERY = 10
RAYS = 512
DATAPARSER = "s2camp-data"
"""Subcommand of S2CamP's dataparser (entry point ``nerfstudio.dataparser_configs``); its options follow it."""
CPU_MESSAGE = "CUDA is not available: training on the CPU"


def _tool(name: str) -> str:
    path = BIN / name
    if not path.exists():
        pytest.fail(f"{path} not found: the package's console scripts must be installed next to {sys.executable}")
    return str(path)


def _environment() -> dict[str, str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"}
    # Idle OpenMP threads must not spin: on a loaded 2-core machine spinning makes nerfacto 5-10x slower.
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return env


def _run(command: list[str], timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=_environment())


def _failure(result: subprocess.CompletedProcess, what: str) -> str:
    return (
        f"{what} exited with {result.returncode}\n--- stdout (tail) ---\n{result.stdout[-4000:]}\n"
        f"--- stderr (tail) ---\n{result.stderr[-4000:]}"
    )


@dataclass
class TrainedRun:
    result: subprocess.CompletedProcess
    run_dir: Path
    scene: Path

    @property
    def config(self) -> Path:
        return self.run_dir / "config.yml"

    @property
    def output(self) -> str:
        return self.result.stdout + self.result.stderr


def train_command(method: str, scene: Path, output_dir: Path, iterations: int, extra: list[str]) -> list[str]:
    """``ns-train`` with tensorboard logging, no evaluation, and the given iterations; no device flag."""
    return [
        _tool("ns-train"), method,
        "--data", str(scene),
        "--output-dir", str(output_dir),
        "--experiment-name", "e2e",
        "--timestamp", "run",
        "--vis", "tensorboard",
        "--max-num-iterations", str(iterations),
        "--steps-per-save", str(iterations),
        "--steps-per-eval-batch", "0",
        "--steps-per-eval-image", "0",
        "--steps-per-eval-all-images", "0",
        "--logging.steps-per-log", str(LOG_EVERY),
        "--pipeline.datamanager.train-num-rays-per-batch", str(RAYS),
        *SMALL_MODEL,
        *extra,
    ]  # fmt: skip


@pytest.fixture(scope="module")
def trained(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> TrainedRun:
    """One ``ns-train s2camp`` run with perturbed cameras, shared by the tests of this module."""
    output_dir = tmp_path_factory.mktemp("e2e_s2camp")
    command = train_command(
        "s2camp",
        tiny_scene,
        output_dir,
        ITERATIONS,
        [
            "--pipeline.model.camera-error-every", str(LOG_EVERY),
            "--optimizers.camera-opt.optimizer.lr", "1e-5",
            "--optimizers.camera-opt.scheduler.warmup-steps", "0",
            "--optimizers.camera-opt.scheduler.lr-final", "1e-3",
            "--optimizers.camera-opt.scheduler.max-steps", str(ITERATIONS),
            DATAPARSER,
            "--perturbation.enabled", "True",
            "--perturbation.sigma-focal-length", "0.1",
            "--perturbation.sigma-dolly-z", "0",
        ],
    )  # fmt: skip
    result = _run(command, timeout=420)
    return TrainedRun(result, output_dir / "e2e" / "s2camp" / "run", tiny_scene)


def _scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

    accumulator = EventAccumulator(str(run_dir), size_guidance={SCALARS: 0})
    accumulator.Reload()
    return {
        tag: [(event.step, event.value) for event in accumulator.Scalars(tag)] for tag in accumulator.Tags()["scalars"]
    }


@pytest.mark.timeout(480)
def test_training_finishes_and_writes_a_checkpoint(trained: TrainedRun):
    assert trained.result.returncode == 0, _failure(trained.result, "ns-train s2camp")
    assert trained.config.is_file()
    checkpoints = sorted((trained.run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    assert checkpoints, f"no checkpoint in {trained.run_dir / 'nerfstudio_models'}"
    assert checkpoints[-1].name == f"step-{ITERATIONS - 1:09d}.ckpt"


@pytest.mark.timeout(480)
def test_cpu_is_the_default_without_cuda(trained: TrainedRun):
    """No ``--machine.device-type`` was passed: without CUDA the run uses the CPU and says so once."""
    assert trained.result.returncode == 0, _failure(trained.result, "ns-train s2camp")
    assert "Traceback" not in trained.output
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here: the CPU fallback is not exercised")
    assert trained.output.count(CPU_MESSAGE) == 1, trained.output[-4000:]
    assert "device_type: cpu" in trained.config.read_text()


@pytest.mark.timeout(480)
def test_metrics_are_logged_to_tensorboard(trained: TrainedRun):
    assert trained.result.returncode == 0, _failure(trained.result, "ns-train s2camp")
    scalars = _scalars(trained.run_dir)
    assert "Train Loss" in scalars, sorted(scalars)
    assert all(np.isfinite(value) for _, value in scalars["Train Loss"])
    assert "Train Loss Dict/rgb_loss" in scalars, sorted(scalars)
    for name in ("rot_err_mean", "rot_err_max", "pos_err_mean", "pos_err_max", "focal_err_mean", "focal_err_max"):
        tag = f"Train Metrics Dict/camera_errors/{name}"
        assert tag in scalars, f"{tag} not logged; logged: {sorted(scalars)}"
        assert len(scalars[tag]) >= ITERATIONS // LOG_EVERY - 2
        assert all(np.isfinite(value) and value >= 0 for _, value in scalars[tag])
    # Training makes progress: the photometric loss of the last logs is below that of the first ones.
    loss = [value for _, value in scalars["Train Loss Dict/rgb_loss"]]
    assert np.mean(loss[-3:]) < 0.7 * np.mean(loss[:3]), loss


@pytest.mark.timeout(480)
def test_camera_refinement_reduces_the_focal_error(trained: TrainedRun):
    """The perturbed focal lengths move back towards the true ones (first vs last logged error)."""
    assert trained.result.returncode == 0, _failure(trained.result, "ns-train s2camp")
    scalars = _scalars(trained.run_dir)
    focal = scalars["Train Metrics Dict/camera_errors/focal_err_mean"]
    first, last = focal[0][1], focal[-1][1]
    print(f"focal_err_mean {first:.3f} px -> {last:.3f} px; all logged: {[round(v, 3) for _, v in focal]}")
    for name in ("rot_err_mean", "pos_err_mean"):
        values = scalars[f"Train Metrics Dict/camera_errors/{name}"]
        print(f"{name} {values[0][1]:.2e} -> {values[-1][1]:.2e}")
    assert first > 2.0, f"the perturbation should give focal errors of several pixels, got {first:.3f}"
    # CPU training is not bit-reproducible across machines and loads: the last value jitters by a few percent
    # around a falling curve (one CI run: 5.09 -> min 4.78 -> last 4.89 px). Require a clear fall at some point of
    # the run and a net fall at its end.
    best = min(value for _, value in focal)
    assert best < 0.95 * first, f"focal_err_mean never fell 5% below its start: {first:.3f} -> min {best:.3f} px"
    assert last < first, f"focal_err_mean ended above its start: {first:.3f} -> {last:.3f} px"


@pytest.mark.timeout(480)
def test_export_cameras_writes_a_colmap_model(trained: TrainedRun, tmp_path: Path):
    import pycolmap

    from s2camp_ns.core.alignment import camera_errors

    assert trained.result.returncode == 0, _failure(trained.result, "ns-train s2camp")
    output_dir = tmp_path / "refined" / "sparse" / "0"
    command = [_tool("s2camp-export-cameras"), "--load-config", str(trained.config), "--output-dir", str(output_dir)]
    result = _run(command, timeout=240)
    assert result.returncode == 0, _failure(result, "s2camp-export-cameras")
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (output_dir / name).is_file(), name

    info = json.loads((trained.scene / "scene_info.json").read_text())
    eval_interval = 8  # the dataparser's default split: every 8th image is held out for evaluation
    train_images = [image for i, image in enumerate(info["images"]) if i % eval_interval != 0]
    reconstruction = pycolmap.Reconstruction(str(output_dir))
    assert reconstruction.num_images() == len(train_images)
    assert reconstruction.num_cameras() == len(train_images)  # one camera per image: intrinsics are per image
    assert reconstruction.num_points3D() > 0

    # Back in the input model's world frame and pixel units: close to the true cameras, up to the perturbation.
    truth = {image["name"]: np.asarray(image["cam_from_world"]) for image in train_images}
    assert {image.name for image in reconstruction.images.values()} == set(truth)
    est_c2w, ref_c2w, est_f, ref_f = [], [], [], []
    for image in reconstruction.images.values():
        camera = reconstruction.cameras[image.camera_id]
        assert (camera.width, camera.height) == (info["camera"]["width"], info["camera"]["height"])
        w2c = image.cam_from_world().matrix()
        est_c2w.append(np.concatenate([w2c[:, :3].T, -w2c[:, :3].T @ w2c[:, 3:]], axis=1))
        ref = truth[image.name]
        ref_c2w.append(np.concatenate([ref[:, :3].T, -ref[:, :3].T @ ref[:, 3:]], axis=1))
        est_f.append(camera.focal_length_x)
        ref_f.append(info["camera"]["fx"])
    errors = camera_errors(
        torch.tensor(np.stack(est_c2w)),
        torch.tensor(np.stack(ref_c2w)),
        torch.tensor(est_f),
        torch.tensor(ref_f),
        align=False,
    )
    ring_radius = info["config"]["ring_radius"]
    # Perturbation (sigma 0.005 normalized units, about 0.02 scene units) plus refinement drift; a transform left
    # in normalized units or a flipped axis would be off by metres and radians.
    assert errors["pos_err_max"] < 0.1 * ring_radius, errors
    assert errors["rot_err_max"] < 0.1, errors
    assert errors["focal_err_max"] < 0.35 * info["camera"]["fx"], errors


@pytest.mark.timeout(300)
def test_camp_baseline_trains(tiny_scene: Path, tmp_path: Path):
    """``ns-train s2camp-camp`` (random-sample preconditioner computed once) runs a few iterations."""
    iterations = 5
    command = train_command(
        "s2camp-camp", tiny_scene, tmp_path, iterations, [DATAPARSER, "--perturbation.enabled", "True"]
    )
    result = _run(command, timeout=280)
    assert result.returncode == 0, _failure(result, "ns-train s2camp-camp")
    assert "Traceback" not in result.stdout + result.stderr
    run_dir = tmp_path / "e2e" / "s2camp-camp" / "run"
    assert (run_dir / "nerfstudio_models" / f"step-{iterations - 1:09d}.ckpt").is_file()
    assert "s2camp-camp" in (run_dir / "config.yml").read_text()
