"""``ns-render interpolate`` of an s2camp run whose eval split holds one camera (``s2camp_ns.scripts.render_path``).

With the data parser's default split (every 8th image held out) a scene of 8 images has a single eval camera, and
nerfstudio's interpolation of the eval cameras stopped with numpy's "need at least one array to stack". The unit
tests call the camera path nerfstudio's render calls; the slow test trains 2 steps on a generated 8-camera scene and
renders a video with the command's defaults.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hang_guard import HANG_GUARD_S
from nerfstudio.cameras import camera_paths, camera_utils
from nerfstudio.cameras.cameras import Cameras

from s2camp_bench import train_commands
from s2camp_ns.scripts import render_path

SCENE = {"num_cameras": 8, "width": 64, "height": 48, "points_per_image": 150, "seed": 0}
"""The smallest scene of the default split with one eval camera and more than one training camera."""
STEPS = 2
"""Seconds each of ns-train and ns-render may take: about 30 s each on an idle 2-core laptop, far more on a busy one."""
SINGLE_CAMERA_NOTE = "the pose source holds a single camera"
NERFSTUDIO_COPY_WARNING = "ignore:To copy construct from a tensor:UserWarning"
"""nerfstudio's get_interpolated_poses_many copies its result with torch.tensor(tensor) (not actionable here)."""


def _cameras(count: int) -> Cameras:
    """``count`` perspective cameras on a line, turning about y, with different focal lengths."""
    angles = torch.linspace(0.0, 0.6, count)
    c2w = torch.zeros(count, 3, 4)
    c2w[:, 0, 0], c2w[:, 0, 2] = torch.cos(angles), torch.sin(angles)
    c2w[:, 1, 1] = 1.0
    c2w[:, 2, 0], c2w[:, 2, 2] = -torch.sin(angles), torch.cos(angles)
    c2w[:, :, 3] = torch.stack([torch.linspace(0.0, 1.0, count), torch.zeros(count), torch.ones(count)], dim=-1)
    fx = torch.linspace(50.0, 60.0, count)[:, None]
    return Cameras(camera_to_worlds=c2w, fx=fx, fy=fx + 1.0, cx=32.0, cy=24.0, width=64, height=48)


def test_a_single_camera_path_holds_that_camera_for_each_step(capsys: pytest.CaptureFixture):
    """The path ns-render interpolate takes (``get_interpolated_camera_path``) through one camera: that camera, once
    per ``--interpolation-steps``, instead of numpy's "need at least one array to stack"."""
    render_path.install()
    cameras = _cameras(1)
    path = camera_paths.get_interpolated_camera_path(cameras, steps=3, order_poses=False)
    assert path.camera_to_worlds.shape == (3, 3, 4)
    assert torch.equal(path.camera_to_worlds, cameras.camera_to_worlds.expand(3, 3, 4))
    assert torch.equal(path.get_intrinsics_matrices(), cameras.get_intrinsics_matrices().expand(3, 3, 3))
    assert SINGLE_CAMERA_NOTE in capsys.readouterr().out
    ordered = camera_paths.get_interpolated_camera_path(cameras, steps=2, order_poses=True)
    assert torch.equal(ordered.camera_to_worlds, cameras.camera_to_worlds.expand(2, 3, 4))


@pytest.mark.filterwarnings(NERFSTUDIO_COPY_WARNING)
@pytest.mark.parametrize("order_poses", [False, True])
def test_two_cameras_or_more_keep_nerfstudios_path(order_poses: bool):
    render_path.install()
    nerfstudio = getattr(camera_utils, render_path._ORIGINAL)
    assert not hasattr(nerfstudio, render_path._INSTALLED)
    for count in (2, 5):
        cameras = _cameras(count)
        poses, ks = cameras.camera_to_worlds, cameras.get_intrinsics_matrices()
        expected = nerfstudio(poses, ks, steps_per_transition=4, order_poses=order_poses)
        got = camera_utils.get_interpolated_poses_many(poses, ks, steps_per_transition=4, order_poses=order_poses)
        assert got[0].shape == ((count - 1) * 4, 3, 4)
        for a, b in zip(got, expected, strict=True):
            assert a.dtype == b.dtype and torch.equal(a, b)


@pytest.mark.filterwarnings(NERFSTUDIO_COPY_WARNING)
def test_no_camera_or_no_step_is_refused_naming_the_option():
    render_path.install()
    poses, ks = _cameras(2).camera_to_worlds, _cameras(2).get_intrinsics_matrices()
    for steps in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match=r"--interpolation-steps must be an integer >= 1, got"):
            camera_utils.get_interpolated_poses_many(poses, ks, steps_per_transition=steps)
    assert camera_utils.get_interpolated_poses_many(poses, ks, steps_per_transition=np.int64(1))[0].shape == (1, 3, 4)
    with pytest.raises(ValueError, match=r"no camera to interpolate: .*--pose-source"):
        camera_utils.get_interpolated_poses_many(poses[:0], ks[:0], steps_per_transition=2)


def test_install_is_idempotent_and_keeps_nerfstudios_function():
    render_path.install()
    nerfstudio = getattr(camera_utils, render_path._ORIGINAL)
    assert render_path.install() is False
    assert getattr(camera_utils, render_path._ORIGINAL) is nerfstudio
    assert camera_paths.get_interpolated_poses_many is render_path.interpolated_poses_many
    assert camera_utils.get_interpolated_poses_many is render_path.interpolated_poses_many


def _run(command: list[str]) -> subprocess.CompletedProcess:
    tool = Path(command[0])
    if not (tool.is_absolute() and tool.exists()):
        pytest.fail(f"{command[0]} is not installed next to {sys.executable}")
    environment = {**train_commands.training_environment(), "COLUMNS": "200"}
    return subprocess.run(command, capture_output=True, text=True, timeout=HANG_GUARD_S, env=environment)


def _failure(result: subprocess.CompletedProcess, what: str) -> str:
    return (
        f"{what} exited with {result.returncode}\n--- stdout (tail) ---\n{result.stdout[-4000:]}\n"
        f"--- stderr (tail) ---\n{result.stderr[-4000:]}"
    )


@pytest.mark.slow
@pytest.mark.timeout(HANG_GUARD_S)
def test_ns_render_interpolate_writes_a_video_of_an_eight_camera_run(tmp_path: Path):
    """2 CPU steps of ``ns-train s2camp`` on 8 cameras (7 train, 1 eval), then ``ns-render interpolate`` with the
    default pose source (eval): a video of ``--interpolation-steps`` frames at the images' size."""
    import imageio_ffmpeg

    from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

    scene = make_scene(MakeSceneConfig(output_dir=tmp_path / "scene", **SCENE))
    outputs = tmp_path / "outputs"
    train = train_commands.ns_train_arguments("s2camp", scene, outputs, "render", "run", 2, 2, 256)
    trained = _run([*train, "--machine.device-type", "cpu", "--vis", "tensorboard"])
    assert trained.returncode == 0, _failure(trained, "ns-train s2camp")
    config = outputs / "render" / "s2camp" / "run" / "config.yml"
    assert config.is_file(), trained.stdout[-3000:]

    video = tmp_path / "out.mp4"
    scripts = Path(sys.executable).parent
    render = [str(scripts / "ns-render"), "interpolate", "--load-config", str(config)]
    rendered = _run([*render, "--interpolation-steps", str(STEPS), "--output-path", str(video)])
    assert rendered.returncode == 0, _failure(rendered, "ns-render interpolate")
    assert SINGLE_CAMERA_NOTE in rendered.stdout, rendered.stdout[-3000:]
    assert video.is_file()
    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    width, height = SCENE["width"], SCENE["height"]  # the full-size images: the scene has no images_4
    frames = [np.frombuffer(frame, dtype=np.uint8).reshape(height, width, 3) for frame in reader]
    assert tuple(meta["size"]) == (width, height), meta
    assert len(frames) == STEPS
