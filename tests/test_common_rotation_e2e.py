"""``fix_common_rotation`` inside ``ns-train s2camp``: the training callback removes the rotation all cameras share
after every step (end to end, a handful of CPU steps)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hang_guard import HANG_GUARD_S
from test_e2e import _failure, _run

from s2camp_bench.train_commands import camera_schedule_arguments, ns_train_arguments

pytestmark = [pytest.mark.slow, pytest.mark.timeout(HANG_GUARD_S)]

STEPS = 12


def test_the_trained_cameras_share_no_rotation_but_still_move(tiny_scene: Path, tmp_path: Path) -> None:
    command = [
        *ns_train_arguments("s2camp", tiny_scene, tmp_path, "gauge", "run", STEPS, STEPS, 256),
        "--machine.device-type", "cpu",
        "--vis", "tensorboard",
        # A large camera step with no warm-up, so the cameras move within a few steps.
        *camera_schedule_arguments(1e-2, 1e-2),
        "--pipeline.model.camera-optimizer.fix-common-rotation", "True",
        # The default track prior would hold these accurate cameras at the exact tracks' anchor: nothing would rotate.
        "--pipeline.model.camera-optimizer.track-prior", "False",
    ]  # fmt: skip
    result = _run(command)
    assert result.returncode == 0, _failure(result, "ns-train s2camp")
    checkpoint = tmp_path / "gauge" / "s2camp" / "run" / "nerfstudio_models" / f"step-{STEPS - 1:09d}.ckpt"
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["pipeline"]
    prefix = "_model.camera_optimizer.refiner."
    pose, intrinsics = state[prefix + "whitened_delta"].double(), state[prefix + "whitened_intrinsics"].double()
    assert intrinsics.shape[0] == 1  # the generated scene has one physical camera, shared by every image
    latent = torch.cat([pose, intrinsics.expand(pose.shape[0], -1)], dim=-1)  # [z_i; w_c] (eq. 15)
    phi = (state[prefix + "precond_inv"].double() @ latent[..., None])[..., 0]
    rotation = phi[:, 3:6]  # the layout's pose columns: rho (0..2), omega (3..5)
    assert float(rotation.std(dim=0).max()) > 1e-4  # the cameras rotated, each its own way
    assert float(rotation.mean(dim=0).abs().max()) < 1e-3 * float(rotation.std(dim=0).max())
