"""End-to-end: ``ns-train s2camp`` on transforms.json files as ``ns-process-data`` writes them, for a perspective
OPENCV camera with tangential distortion and an OPENCV_FISHEYE camera (issue 10: "change one word").

Each scene is generated with that camera model (s2camp-make-scene renders through pycolmap's model), converted with
nerfstudio's own ``colmap_to_json`` (what ``ns-process-data`` runs after COLMAP), and trained for a few CPU
iterations. The checkpoint must hold the camera optimizer of the model's parameter layout (distortion included) with
every latent coordinate moved.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hang_guard import HANG_GUARD_S

from s2camp_bench import train_commands
from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene
from s2camp_ns.core.camera import ParameterLayout

pytestmark = [pytest.mark.slow, pytest.mark.timeout(HANG_GUARD_S)]

ITERATIONS = 6
SCENES = {
    "OPENCV": dict(k1=-0.03, k2=0.004, p1=0.002, p2=-0.0015),
    "OPENCV_FISHEYE": dict(k1=0.02, k2=-0.004, k3=0.001, k4=-0.0002, fov="wide"),
}


def _ns_process_data_scene(model: str, root: Path) -> Path:
    """transforms.json + images/ of a generated scene, as ns-process-data leaves them; returns the json path."""
    from nerfstudio.process_data.colmap_utils import colmap_to_json

    config = MakeSceneConfig(
        output_dir=root / "colmap", num_cameras=8, width=48, height=36, points_per_image=60, camera_model=model,
        **SCENES[model],
    )  # fmt: skip
    scene = make_scene(config)
    data = root / "ns"
    shutil.copytree(scene / "images", data / "images")
    colmap_to_json(scene / "sparse" / "0", data)
    return data / "transforms.json"


@pytest.mark.parametrize("model", list(SCENES))
def test_ns_train_s2camp_on_ns_process_data_transforms(model: str, tmp_path: Path):
    transforms = _ns_process_data_scene(model, tmp_path)
    command = train_commands.ns_train_arguments(
        "s2camp",
        transforms,
        tmp_path / "outputs",
        experiment="scene",
        timestamp="run",
        iterations=ITERATIONS,
        steps_per_save=ITERATIONS,
        rays_per_batch=256,
    )
    command += ["--vis", "tensorboard", "--pipeline.model.camera-optimizer.refresh-every", "3"]
    command += train_commands.camera_schedule_arguments(lr=1e-3, lr_final=1e-4)
    if not Path(command[0]).exists():
        pytest.fail(f"{command[0]} is not installed next to {sys.executable}")
    result = subprocess.run(
        command, capture_output=True, text=True, timeout=HANG_GUARD_S, env={**train_commands.training_environment()}
    )
    assert result.returncode == 0, f"ns-train failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    assert "Traceback" not in result.stdout + result.stderr
    checkpoint = (
        tmp_path / "outputs" / "scene" / "s2camp" / "run" / "nerfstudio_models" / f"step-{ITERATIONS - 1:09d}.ckpt"
    )
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["pipeline"]
    # Intrinsics per physical camera (the default): a pose latent per image, one intrinsics latent for the camera.
    pose = state["_model.camera_optimizer.refiner.whitened_delta"]
    intrinsics = state["_model.camera_optimizer.refiner.whitened_intrinsics"]
    layout = ParameterLayout.from_preset("all", model)
    assert pose.shape == (7, 6)  # 8 images, every 8th held out
    assert intrinsics.shape == (1, layout.num_params - 6)
    assert layout.names[-2:] == (("p1", "p2") if model == "OPENCV" else ("k3", "k4"))
    assert (pose.abs().amax(dim=0) > 0).all() and (intrinsics.abs() > 0).all(), "every latent coordinate moved"
