"""End-to-end: ``ns-train s2camp`` / ``s2camp-camp`` on a generated scene, logged metrics, checkpoint, COLMAP export.

The module-scoped fixture runs the demo's "warm-start" recipe (``benchmarks/s2camp_bench/demo.py``) on the conftest's
tiny scene (12 cameras, 64x48): a short warm start of nerfacto on the accurate cameras, then ``ns-train s2camp`` resumed
from it with the training cameras perturbed by CamP's protocol (position, look-at, per-camera focal, shared dolly zoom),
jointly refining cameras and NeRF by the photometric loss alone (track prior and common-rotation removal off). Most
tests read that one pair of runs. Neither run passes ``--machine.device-type``: on a machine without CUDA the method
config must fall back to the CPU by itself.

What a run this short shows (measured when these tests were written): the focal error, dolly zoom included, falls by
about 75% (4.46 px -> 1.11 px), while rotation and position errors of CamP's size (0.005 normalized units, a fraction
of a pixel here) sit below the gradient noise of a 50-iteration run and grow to about 0.01 (printed, not asserted).
From scratch, without the warm start, none of the errors fell reliably within a few hundred CPU iterations.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from hang_guard import HANG_GUARD_S

from s2camp_bench import demo, train_commands

pytestmark = [pytest.mark.slow, pytest.mark.timeout(HANG_GUARD_S)]

WARM_START = 120
ITERATIONS = 50
LOG_EVERY = 10  # the demo's --logging.steps-per-log and --pipeline.model.camera-error-every
CPU_MESSAGE = "CUDA is not available: training on the CPU"


def _failure(result: subprocess.CompletedProcess, what: str) -> str:
    return (
        f"{what} exited with {result.returncode}\n--- stdout (tail) ---\n{result.stdout[-4000:]}\n"
        f"--- stderr (tail) ---\n{result.stderr[-4000:]}"
    )


def _run(command: list[str], **environment: str) -> subprocess.CompletedProcess:
    """Run an installed console script with the training environment (plus ``environment``), under the hang guard."""
    tool = Path(command[0])
    if not (tool.is_absolute() and tool.exists()):
        pytest.fail(f"{command[0]} is not installed next to {sys.executable}")
    return subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=HANG_GUARD_S,
        env={**train_commands.training_environment(), "COLUMNS": "200", **environment},
    )


@dataclass
class Runs:
    config: demo.DemoConfig
    warm_start: subprocess.CompletedProcess
    refine: subprocess.CompletedProcess
    commands: list[list[str]]

    @property
    def refine_dir(self) -> Path:
        return demo.run_dir(self.config, demo.REFINE_TIMESTAMP)

    @property
    def warm_start_dir(self) -> Path:
        return demo.run_dir(self.config, demo.WARM_START_TIMESTAMP)

    def check(self) -> None:
        assert self.warm_start.returncode == 0, _failure(self.warm_start, "ns-train s2camp (warm start)")
        assert self.refine.returncode == 0, _failure(self.refine, "ns-train s2camp (perturbed cameras)")


@pytest.fixture(scope="module")
def runs(tiny_scene: Path, tiny_scene_config, tmp_path_factory: pytest.TempPathFactory) -> Runs:
    config = demo.DemoConfig(
        scene_dir=tiny_scene,
        output_dir=tmp_path_factory.mktemp("e2e_outputs"),
        num_cameras=tiny_scene_config.num_cameras,
        width=tiny_scene_config.width,
        height=tiny_scene_config.height,
        recipe="warm-start",
        warm_start=WARM_START,
        iterations=ITERATIONS,
        rays_per_batch=512,
        # CamP's perturbation as published (the demo itself uses larger pose sigmas and more iterations).
        sigma_position=0.005,
        sigma_look_at=0.005,
        sigma_focal_length=0.02,
        sigma_dolly_z=0.05,
    )
    demo.check_config(config)
    commands = [demo.warm_start_command(config, tiny_scene), demo.refine_command(config, tiny_scene)]
    warm_start = _run(commands[0])
    refine = _run(commands[1]) if warm_start.returncode == 0 else warm_start
    return Runs(config, warm_start, refine, commands)


def _scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

    accumulator = EventAccumulator(str(run_dir), size_guidance={SCALARS: 0})
    accumulator.Reload()
    return {
        tag: [(event.step, event.value) for event in accumulator.Scalars(tag)] for tag in accumulator.Tags()["scalars"]
    }


def _errors(run_dir: Path, name: str) -> list[float]:
    return [value for _, value in _scalars(run_dir)[f"Train Metrics Dict/camera_errors/{name}"]]


def test_training_finishes_and_writes_checkpoints(runs: Runs):
    runs.check()
    assert (runs.warm_start_dir / "nerfstudio_models" / f"step-{WARM_START - 1:09d}.ckpt").is_file()
    # The perturbed run resumes from the warm start: its steps continue from there.
    assert runs.refine.stdout.count("Done loading Nerfstudio checkpoint") == 1, runs.refine.stdout[-3000:]
    # The warm start's P was computed for the unperturbed intrinsics: it is recomputed, not reused (safe resume).
    assert "intrinsics differ from those its P was computed for" in runs.refine.stdout + runs.refine.stderr
    checkpoints = sorted((runs.refine_dir / "nerfstudio_models").glob("step-*.ckpt"))
    assert [c.name for c in checkpoints] == [f"step-{WARM_START + ITERATIONS - 1:09d}.ckpt"]
    assert (runs.refine_dir / "config.yml").is_file()


def test_cpu_is_the_default_without_cuda(runs: Runs):
    """No ``--machine.device-type`` is passed: without CUDA each run uses the CPU and says so once, no traceback."""
    runs.check()
    for command, result in zip(runs.commands, (runs.warm_start, runs.refine), strict=True):
        assert not any(arg.startswith("--machine") for arg in command)
        output = result.stdout + result.stderr
        assert "Traceback" not in output
        if not torch.cuda.is_available():
            assert output.count(CPU_MESSAGE) == 1, output[-3000:]
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here: the CPU fallback is not exercised")
    assert "device_type: cpu" in (runs.refine_dir / "config.yml").read_text()


def test_metrics_are_logged_to_tensorboard(runs: Runs):
    runs.check()
    for run_dir in (runs.warm_start_dir, runs.refine_dir):
        scalars = _scalars(run_dir)
        assert "Train Loss" in scalars, sorted(scalars)
        assert all(np.isfinite(value) for _, value in scalars["Train Loss"])
        assert "Train Loss Dict/rgb_loss" in scalars, sorted(scalars)
        for name in ("rot_err_mean", "rot_err_max", "pos_err_mean", "pos_err_max", "focal_err_mean", "focal_err_max"):
            tag = f"Train Metrics Dict/camera_errors/{name}"
            assert tag in scalars, f"{tag} not logged in {run_dir}; logged: {sorted(scalars)}"
            assert all(np.isfinite(value) for _, value in scalars[tag])
        for error in ("rot_err", "pos_err", "focal_err"):  # each step's mean over the cameras is at most their max
            means, maxima = (
                scalars[f"Train Metrics Dict/camera_errors/{error}_mean"],
                scalars[f"Train Metrics Dict/camera_errors/{error}_max"],
            )
            assert [step for step, _ in means] == [step for step, _ in maxima]
            assert all(mean <= maximum * (1 + 1e-6) for (_, mean), (_, maximum) in zip(means, maxima, strict=True))
    # The warm start learns the scene: its photometric loss falls.
    loss = [value for _, value in _scalars(runs.warm_start_dir)["Train Loss Dict/rgb_loss"]]
    assert np.mean(loss[-3:]) < 0.7 * np.mean(loss[:3]), loss
    # The warm start does not move the (accurate) cameras.
    assert max(_errors(runs.warm_start_dir, "focal_err_max")) < 1e-3
    assert len(_errors(runs.refine_dir, "focal_err_mean")) >= ITERATIONS // LOG_EVERY - 1


def test_camera_refinement_reduces_the_focal_error(runs: Runs):
    """First vs last logged error of the perturbed run: the focal error (shared dolly zoom included) falls."""
    runs.check()
    focal = _errors(runs.refine_dir, "focal_err_mean")
    print(f"\nfocal_err_mean (px): {' '.join(f'{v:.3f}' for v in focal)}")
    for name in ("rot_err_mean", "pos_err_mean", "align_scale"):
        print(f"{name}: {' '.join(f'{v:.2e}' for v in _errors(runs.refine_dir, name))}")
    assert focal[0] > 2.0, f"the perturbation should give focal errors of a few pixels, got {focal[0]:.3f}"
    assert focal[-1] < 0.5 * focal[0], f"focal_err_mean did not halve: {focal[0]:.3f} -> {focal[-1]:.3f} px"
    # Pose errors of CamP's size are below this run's noise floor; they must stay small, not necessarily fall.
    assert max(_errors(runs.refine_dir, "rot_err_max")) < 0.05
    assert max(_errors(runs.refine_dir, "pos_err_max")) < 0.1


def test_eval_setup_loads_the_run_and_the_demo_table(runs: Runs, capsys: pytest.CaptureFixture):
    """nerfstudio's eval_setup loads the trained pipeline; the demo's table reads the start and refined errors."""
    runs.check()
    results = demo.camera_error_table(runs.refine_dir / "config.yml")
    start, refined = results["perturbed start"], results["after refinement"]
    logged = _errors(runs.refine_dir, "focal_err_mean")
    # The first logged errors are those after one step at a small learning rate: close to the unrefined start.
    assert start["focal_err_mean"] == pytest.approx(logged[0], rel=0.05)
    assert refined["focal_err_mean"] < 0.5 * start["focal_err_mean"]
    demo.print_table(results, "e2e")
    assert "after refinement" in capsys.readouterr().out


def test_export_cameras_writes_a_colmap_model(runs: Runs, tmp_path: Path):
    import pycolmap

    from s2camp_ns.core.alignment import camera_errors

    runs.check()
    output_dir = tmp_path / "refined" / "sparse" / "0"
    export = str(Path(sys.executable).with_name("s2camp-export-cameras"))
    command = [export, "--load-config", str(runs.refine_dir / "config.yml"), "--output-dir", str(output_dir)]
    result = _run(command)
    assert result.returncode == 0, _failure(result, "s2camp-export-cameras")
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (output_dir / name).is_file(), name

    info = json.loads((runs.config.scene_dir / "scene_info.json").read_text())
    eval_interval = 8  # the dataparser's default split: every 8th image is held out for evaluation
    train_images = [image for i, image in enumerate(info["images"]) if i % eval_interval != 0]
    reconstruction = pycolmap.Reconstruction(str(output_dir))
    assert reconstruction.num_images() == len(train_images)
    # intrinsics shared per physical camera (the default): one COLMAP camera, as in the generated scene
    assert reconstruction.num_cameras() == 1
    assert reconstruction.num_points3D() > 0
    _assert_exported_poses_follow_the_checkpoint_twist(runs.refine_dir, reconstruction)

    # Back in the input model's world frame and pixel units: close to the true cameras, up to what is left of the
    # perturbation. A transform left in normalized units, or a flipped axis, would be off by metres and radians.
    truth = {image["name"]: np.asarray(image["cam_from_world"]) for image in train_images}
    assert {image.name for image in reconstruction.images.values()} == set(truth)
    est_c2w, ref_c2w, est_f = [], [], []
    for image in reconstruction.images.values():
        camera = reconstruction.cameras[image.camera_id]
        assert (camera.width, camera.height) == (info["camera"]["width"], info["camera"]["height"])
        w2c = image.cam_from_world().matrix()
        est_c2w.append(np.concatenate([w2c[:, :3].T, -w2c[:, :3].T @ w2c[:, 3:]], axis=1))
        ref = truth[image.name]
        ref_c2w.append(np.concatenate([ref[:, :3].T, -ref[:, :3].T @ ref[:, 3:]], axis=1))
        est_f.append(camera.focal_length_x)
    ref_f = np.full(len(est_f), info["camera"]["fx"])
    errors = camera_errors(
        torch.tensor(np.stack(est_c2w)),
        torch.tensor(np.stack(ref_c2w)),
        torch.tensor(est_f),
        torch.tensor(ref_f),
        align=False,
    )
    ring_radius = info["config"]["ring_radius"]
    assert errors["pos_err_max"] < 0.1 * ring_radius, errors
    assert errors["rot_err_max"] < 0.05, errors
    assert errors["focal_err_max"] < 0.1 * info["camera"]["fx"], errors


def _twist_matrix(xi: np.ndarray) -> np.ndarray:
    """4x4 matrix of the twist xi = (rho, omega) in se(3) (``core.camera.se3_exp``'s order)."""
    rho, (wx, wy, wz) = xi[:3], xi[3:]
    return np.array([[0.0, -wz, wy, rho[0]], [wz, 0.0, -wx, rho[1]], [-wy, wx, 0.0, rho[2]], [0.0, 0.0, 0.0, 0.0]])


def _assert_exported_poses_follow_the_checkpoint_twist(run_dir: Path, reconstruction) -> None:
    """Each exported pose is the perturbed start pose moved by the local twist of the final checkpoint,
    c2w' = c2w expm(xi) with xi = (P^-1 phi_hat)[:6] (paper eq. 15; the camera optimizer's documented convention;
    with shared intrinsics phi_hat = [z_i; w_c] and P the block-triangular factor),
    exponentiated here with scipy's matrix exponential. The twists are of the order of 0.01 after this run and the
    tolerance 1e-5 (float32 cameras), so a twist applied with the wrong sign (c2w exp(-xi)) fails by 2 |xi|, which
    the comparison with the true cameras above (tolerance 0.05 rad, 10x the perturbation) cannot see."""
    import yaml
    from colmap_arrays import reconstruction_to_arrays
    from scipy.linalg import expm

    from s2camp_ns.data.colmap_writer import nerfstudio_to_reconstruction

    config = yaml.load((run_dir / "config.yml").read_text(), Loader=yaml.Loader)
    dataparser = config.pipeline.datamanager.dataparser
    dataparser.data = config.pipeline.datamanager.data
    start = dataparser.setup().get_dataparser_outputs("train")  # the perturbed cameras the run started from
    names = start.metadata["image_names"]
    start_model = nerfstudio_to_reconstruction(
        start.cameras, start.dataparser_transform, start.dataparser_scale, names, start.metadata["full_image_size"]
    )
    start_arrays, refined_arrays = reconstruction_to_arrays(start_model), reconstruction_to_arrays(reconstruction)
    (checkpoint,) = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    state = torch.load(checkpoint, map_location="cpu")["pipeline"]
    latent = state["_model.camera_optimizer.refiner.whitened_delta"].double()
    if (
        "_model.camera_optimizer.refiner.whitened_intrinsics" in state
    ):  # intrinsics shared per physical camera: [z_i; w_c]
        shared = state["_model.camera_optimizer.refiner.whitened_intrinsics"].double()
        assert shared.shape[0] == 1  # the generated scene has one COLMAP camera
        latent = torch.cat([latent, shared.expand(latent.shape[0], -1)], dim=-1)
    twists = (state["_model.camera_optimizer.refiner.precond_inv"] @ latent[..., None])[..., 0][:, :6].numpy()
    assert np.abs(twists[:, 3:]).max() > 1e-3  # the rotations moved well beyond the tolerance below

    def homogeneous(c2w: np.ndarray) -> np.ndarray:
        return np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])

    scale = float(start.dataparser_scale)
    for i, name in enumerate(names):
        before = homogeneous(start_arrays["c2w"][start_arrays["names"].index(name)])
        after = homogeneous(refined_arrays["c2w"][refined_arrays["names"].index(name)])
        motion = np.linalg.inv(before) @ after  # in the camera frame; translation in the input model's units
        expected = expm(_twist_matrix(twists[i]))
        np.testing.assert_allclose(motion[:3, :3], expected[:3, :3], atol=1e-5, rtol=0, err_msg=f"rotation of {name}")
        np.testing.assert_allclose(
            motion[:3, 3] * scale, expected[:3, 3], atol=1e-5, rtol=0, err_msg=f"translation of {name}"
        )


def test_s2camp_eval_aligns_held_out_views(runs: Runs, tmp_path: Path):
    """``s2camp-eval``: test-time alignment of the held-out views of the refined run, metrics written as JSON, what
    it is doing said on stderr."""
    runs.check()
    output = tmp_path / "aligned.json"
    tool = str(Path(sys.executable).with_name("s2camp-eval"))
    result = _run(
        [tool, "--load-config", str(runs.refine_dir / "config.yml"), "--output-path", str(output),
         "--alignment.steps", "10", "--alignment.rays", "128"],
    )  # fmt: skip
    assert result.returncode == 0, _failure(result, "s2camp-eval")
    payload = json.loads(output.read_text())
    held_out = len(range(0, runs.config.num_cameras, 8))
    assert len(payload["views"]) == held_out and payload["alignment"]["steps"] == 10
    for view in payload["views"]:
        assert 5.0 < view["psnr"] < 60.0 and 0.0 < view["ssim"] <= 1.0
        assert view["psnr"] > view["psnr_unaligned"] - 0.5, "ten small camera steps must not make the view worse"
    assert "PSNR before" in result.stdout
    # What it is doing, on stderr as it goes (not a terminal here: the lines, without the live bar).
    assert "s2camp-eval: loading" in result.stderr and "aligning the held-out views: 10" in result.stderr
    assert f"aligned {held_out} views in" in result.stderr


def test_ns_render_writes_a_video_of_the_refined_run(runs: Runs, tmp_path: Path):
    """``ns-render interpolate`` of the refined run, through our pipeline and model, writes an H.264 video. nerfstudio
    checks for an ``ffmpeg`` on PATH and mediapy pipes the frames into it; this machine may have none, so PATH holds
    imageio-ffmpeg's binary as ``ffmpeg`` (a test extra: the package itself brings no ffmpeg, docs/USAGE.md)."""
    import imageio_ffmpeg

    runs.check()
    scripts = Path(sys.executable).parent
    tools = tmp_path / "bin"
    tools.mkdir()
    (tools / "ffmpeg").symlink_to(imageio_ffmpeg.get_ffmpeg_exe())
    video = tmp_path / "render" / "interpolate.mp4"
    steps = 4
    command = [
        str(scripts / "ns-render"), "interpolate", "--load-config", str(runs.refine_dir / "config.yml"),
        "--output-path", str(video), "--interpolation-steps", str(steps), "--frame-rate", "4",
        "--rendered-output-names", "rgb", "--downscale-factor", "2",
    ]  # fmt: skip
    result = _run(command, PATH=str(tools))
    assert result.returncode == 0, _failure(result, "ns-render interpolate")
    assert "Could not find ffmpeg" not in result.stdout + result.stderr
    # Two held-out cameras (every 8th of 12), one transition of `steps` frames, at half the images' 64x48.
    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    frames = [np.frombuffer(frame, dtype=np.uint8).reshape(24, 32, 3) for frame in reader]
    assert meta["codec"].startswith("h264") and tuple(meta["size"]) == (32, 24), meta
    assert len(frames) == steps
    # A rendered scene, not a constant picture.
    assert all(frame.std() > 5.0 for frame in frames), [float(frame.std()) for frame in frames]


def test_camp_baseline_trains(tiny_scene: Path, tiny_scene_config, tmp_path: Path):
    """``ns-train s2camp-camp`` (random-sample preconditioner computed once) runs a few perturbed iterations."""
    config = demo.DemoConfig(
        scene_dir=tiny_scene,
        output_dir=tmp_path,
        num_cameras=tiny_scene_config.num_cameras,
        width=tiny_scene_config.width,
        height=tiny_scene_config.height,
        warm_start=0,
        iterations=5,
        rays_per_batch=256,
        method="s2camp-camp",
    )
    result = _run(demo.refine_command(config, tiny_scene))
    assert result.returncode == 0, _failure(result, "ns-train s2camp-camp")
    assert "Traceback" not in result.stdout + result.stderr
    run_dir = demo.run_dir(config, demo.REFINE_TIMESTAMP)
    assert (run_dir / "nerfstudio_models" / "step-000000004.ckpt").is_file()
    assert "method_name: s2camp-camp" in (run_dir / "config.yml").read_text()


RESUME_STEPS, RESUME_AT, REFRESH_EVERY = 20, 12, 8
"""The resume runs: 20 steps, resumed after step 12 (past the proposal sampler's warm-up of 10 steps, in which it
updates the proposal networks at every step whatever its counters say), P refreshed every 8 steps (0, 8 and 16: the
resumed steps cross the refresh at 16)."""


@dataclass
class ResumeRuns:
    runs: Path
    """Folder of the two runs: ``whole`` (steps 0-19) and ``resumed`` (steps 13-19 from whole's step-12 checkpoint)."""

    def checkpoint(self, timestamp: str, step: int) -> dict:
        return torch.load(self.runs / timestamp / "nerfstudio_models" / f"step-{step:09d}.ckpt", map_location="cpu")


@pytest.fixture(scope="module")
def resume_runs(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> ResumeRuns:
    """An uninterrupted run and the same run resumed from its step-12 checkpoint with ``--load-dir`` and
    ``--load-step``, as after a kill, both on one CPU thread (module constants)."""
    output = tmp_path_factory.mktemp("resume")
    perturbation = replace(demo.DemoConfig(), sigma_position=0.01, sigma_look_at=0.01)
    runs = output / "resume" / "s2camp"

    def train(timestamp: str, iterations: int, extra: list[str]) -> None:
        command = [
            *train_commands.ns_train_arguments("s2camp", tiny_scene, output, "resume", timestamp, iterations, 4, 256),
            "--save-only-latest-checkpoint", "False",
            "--vis", "tensorboard",
            "--pipeline.model.camera-optimizer.refresh-every", str(REFRESH_EVERY),
            *train_commands.camera_schedule_arguments(1e-3, 1e-4, RESUME_STEPS),
            *extra,
            *train_commands.perturbation_arguments(perturbation),
        ]  # fmt: skip
        result = _run(command, OMP_NUM_THREADS="1")
        assert result.returncode == 0, _failure(result, f"ns-train s2camp ({timestamp})")

    train("whole", RESUME_STEPS, [])  # checkpoints after steps 0, 4, 8, 12, 16 and 19
    resumed_from = ["--load-dir", str(runs / "whole" / "nerfstudio_models"), "--load-step", str(RESUME_AT)]
    train("resumed", RESUME_STEPS - 1 - RESUME_AT, resumed_from)  # steps 13-19
    return ResumeRuns(runs)


def _tensors(value, prefix: str = "") -> dict:
    """Every tensor and number in a checkpoint's nested dicts and lists, by its path."""
    if isinstance(value, dict):
        return {key: item for name, entry in value.items() for key, item in _tensors(entry, f"{prefix}/{name}").items()}
    if isinstance(value, list | tuple):
        return {key: item for i, entry in enumerate(value) for key, item in _tensors(entry, f"{prefix}/{i}").items()}
    return {prefix: value}


def test_interrupted_run_resumes_bit_identically(resume_runs: ResumeRuns):
    """The run resumed from step 12 ends with the uninterrupted run's step-19 checkpoint, bit for bit: every tensor of
    the field, the proposal networks, the camera optimizer (latent, P, P^-1, refresh counters), every optimizer's and
    scheduler's state, and the proposal sampler's counters. It relies on the checkpoint's random state and sampler
    counters (``nerfstudio/trainer.py``); without the counters the resumed sampler restarts its warm-up and the runs
    split at the first resumed step (measured: 70 of 204 entries differed). Both runs use one CPU thread: with two,
    multi-threaded CPU reductions, whose order torch does not fix, make the last bits differ."""
    whole, resumed = resume_runs.checkpoint("whole", 19), resume_runs.checkpoint("resumed", 19)
    compared = ("pipeline", "optimizers", "schedulers", "scalers", "sampler_state")
    expected = _tensors({key: whole[key] for key in compared})
    actual = _tensors({key: resumed[key] for key in compared})
    assert set(expected) == set(actual)
    tensors = [key for key, value in expected.items() if isinstance(value, torch.Tensor)]
    assert len(tensors) > 100 and any("/optimizers/camera_opt/state/" in key for key in tensors)
    for part in (
        "field.mlp_head",
        "proposal_networks.1",
        "camera_optimizer.refiner.whitened_delta",
        "optimizer.refiner.precond",
    ):
        assert any(part in key for key in tensors), part
    def same(value, other) -> bool:  # bit for bit; NaN (the prior's radii of an image without tracks) matches NaN
        if not isinstance(value, torch.Tensor):
            return value == other
        if torch.equal(value, other):
            return True
        both_nan = value.isnan() & other.isnan() if value.is_floating_point() else torch.zeros_like(value, dtype=bool)
        return value.shape == other.shape and bool(((value == other) | both_nan).all())

    different = [key for key, value in expected.items() if not same(value, actual[key])]
    assert not different, f"{len(different)} of {len(expected)} entries differ after resuming: {different[:20]}"
    assert int(whole["pipeline"]["_model.camera_optimizer.refiner.num_refreshes"]) == 3  # steps 0, 8 and 16
    resumed_state = resume_runs.checkpoint("whole", RESUME_AT)
    assert resumed_state["sampler_state"]["proposal_sampler"]["_step"] == RESUME_AT  # past the warm-up (< 10)
    delta = "_model.camera_optimizer.refiner.whitened_delta"
    assert not torch.equal(whole["pipeline"][delta], resumed_state["pipeline"][delta])  # the resumed steps moved it


def test_resumed_run_records_its_checkpoint_and_is_exported_and_evaluated(resume_runs: ResumeRuns, tmp_path: Path):
    """The resumed run's config.yml names the checkpoint it loaded (``load_checkpoint``; no ``load_dir`` and
    ``load_step``, which nerfstudio's eval_setup would look for in the resumed run's own folder, where there is no
    step 12); ``s2camp-export-cameras`` and ``s2camp-eval`` load its own last checkpoint."""
    import yaml

    run = resume_runs.runs / "resumed"
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    loaded = resume_runs.runs / "whole" / "nerfstudio_models" / f"step-{RESUME_AT:09d}.ckpt"
    assert config.load_checkpoint == loaded.resolve()
    assert config.load_dir is None and config.load_step is None
    export = str(Path(sys.executable).with_name("s2camp-export-cameras"))
    output_dir = tmp_path / "sparse" / "0"
    result = _run([export, "--load-config", str(run / "config.yml"), "--output-dir", str(output_dir)])
    assert result.returncode == 0, _failure(result, "s2camp-export-cameras (resumed run)")
    assert all((output_dir / name).is_file() for name in ("cameras.bin", "images.bin", "points3D.bin"))
    # The earlier form of --output-dir: the model there, the rest of the scene two folders up, said; the resumed run
    # wrote its own anchor tracks, so the export fits nothing.
    assert "ends in sparse/0" in " ".join(result.stderr.split()) and (tmp_path / "transforms.json").is_file()
    assert (run / "anchor_tracks.pt").is_file() and "Levenberg" not in result.stdout + result.stderr
    evaluate = str(Path(sys.executable).with_name("s2camp-eval"))
    output = tmp_path / "aligned.json"
    result = _run(
        [evaluate, "--load-config", str(run / "config.yml"), "--output-path", str(output),
         "--alignment.steps", "2", "--alignment.rays", "64"],
    )  # fmt: skip
    assert result.returncode == 0, _failure(result, "s2camp-eval (resumed run)")
    payload = json.loads(output.read_text())
    assert payload["step"] == 19 and payload["checkpoint"] == str(run / "nerfstudio_models" / "step-000000019.ckpt")


def test_demo_default_recipe_runs_the_method_defaults_from_scratch(tmp_path: Path):
    """``make demo`` trains ``s2camp`` as a user would: no camera option, schedule or checkpoint of its own."""
    config = replace(demo.DemoConfig(), output_dir=tmp_path)
    assert config.recipe == "default"
    command = demo.refine_command(config, tmp_path)
    assert command[1] == "s2camp"
    assert "--load-dir" not in command
    assert not [arg for arg in command if arg.startswith(("--optimizers.", "--pipeline.model.camera-optimizer."))]
    assert command[command.index("--perturbation.enabled") + 1] == "True"
    assert not demo.uses_warm_start(config)
    assert "default options, from scratch" in demo.protocol_notice(config)
    assert "warm-up" in demo.protocol_notice(replace(config, method="s2camp-camp"))
    # Options of the other recipe are refused by name instead of being ignored.
    with pytest.raises(ValueError, match="camera_lr applies to recipe 'warm-start' only, got 0.01"):
        demo.check_config(replace(config, camera_lr=0.01))
    demo.check_config(replace(config, recipe="warm-start", camera_lr=0.01))


def test_demo_commands_resume_and_perturb(tmp_path: Path):
    """Fast check of the warm-start recipe's command lines: the refinement resumes the warm start, perturbs the
    cameras and turns the track prior and the common-rotation removal off in both runs (same model, photometric loss
    alone)."""
    config = replace(demo.DemoConfig(), output_dir=tmp_path, recipe="warm-start")
    warm, refine = demo.warm_start_command(config, tmp_path), demo.refine_command(config, tmp_path)
    assert "--load-dir" not in warm and "--perturbation.enabled" not in warm
    assert refine[refine.index("--load-dir") + 1].endswith(f"{demo.WARM_START_TIMESTAMP}/nerfstudio_models")
    # Dataparser options come after its subcommand, at the end.
    assert refine.index(train_commands.DATAPARSER_SUBCOMMAND) < refine.index("--perturbation.enabled")
    assert refine[refine.index("--perturbation.enabled") + 1] == "True"
    for command in (warm, refine):
        assert command[command.index("--pipeline.model.camera-optimizer.track-prior") + 1] == "False"
        assert command[command.index("--pipeline.model.camera-optimizer.fix-common-rotation") + 1] == "False"
    assert "the track prior and the common-rotation removal are off" in demo.protocol_notice(config)
    scratch = demo.refine_command(replace(config, warm_start=0), tmp_path)
    assert "--load-dir" not in scratch
    with pytest.raises(ValueError, match="iterations"):
        demo.check_config(replace(config, iterations=0))
