"""Checkpoints written by the version before the refiner became the camera optimizer's submodule still load.

tests/data/camera-optimizer-8e80474-{per-camera,per-image}.pt were written at commit 8e80474 by five training steps of
``S2CampCameraOptimizer`` (``refresh_every`` 3, 64 proxy points, the track prior of ``track_rms_px`` below) on the
cameras of ``cameras()``: its state dict (the refiner's tensors under the optimizer's own names; per image one latent
[n, 12]), Adam's state dict, and the refined cameras it gave. Loaded into today's optimizer, they give the same
refined cameras, and Adam continues with the same moments.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.compat import split_per_image_adam_state
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.method.pipeline import checkpoint_camera_count

DATA = Path(__file__).parent / "data"


def cameras() -> Cameras:
    """The four cameras the fixtures were written with."""
    c2w = []
    for angle in torch.linspace(0.0, 2.0 * math.pi, 5)[:-1]:
        position = torch.tensor([2.0 * math.cos(angle), 2.0 * math.sin(angle), 0.5])
        backward = position / position.norm()
        right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), backward)
        right = right / right.norm()
        rotation = torch.stack([right, torch.linalg.cross(backward, right), backward], -1)
        c2w.append(torch.cat([rotation, position[:, None]], -1))
    focal = torch.tensor([[50.0], [51.0], [50.0], [51.0]])
    return Cameras(
        camera_to_worlds=torch.stack(c2w), fx=focal, fy=focal, cx=32.0, cy=24.0, width=64, height=48,
        distortion_params=torch.tensor([-0.05, 0.01, 0, 0, 0, 0]).expand(4, 6).clone(),
        camera_type=CameraType.PERSPECTIVE,
    )  # fmt: skip


@pytest.mark.parametrize("intrinsics", ["per-camera", "per-image"])
def test_a_checkpoint_of_the_previous_version_loads_with_its_cameras_and_adam_state(intrinsics: str) -> None:
    saved = torch.load(DATA / f"camera-optimizer-8e80474-{intrinsics}.pt", weights_only=False)
    old_keys = set(saved["camera_optimizer"])
    assert "precond" in old_keys and not any(key.startswith("refiner.") for key in old_keys)  # the old layout
    config = S2CampCameraOptimizerConfig(intrinsics=intrinsics, refresh_every=3, sampling=SamplingConfig(num_points=64))
    optimizer = config.setup(num_cameras=4, device="cpu")
    optimizer.set_train_cameras(cameras())
    optimizer.set_track_prior(torch.tensor([0.3, 0.4, 0.3, 0.5]), track_observations=torch.full((4,), 40.0))
    optimizer.load_state_dict(saved["camera_optimizer"])
    refiner = optimizer.refiner
    assert not refiner.preconditioner_is_stale and refiner.last_refresh == 3
    torch.testing.assert_close(refiner.refined_c2w().detach(), saved["refined_c2w"], rtol=0, atol=1e-12)
    torch.testing.assert_close(refiner.refined_fields().detach(), saved["refined_fields"], rtol=0, atol=1e-12)
    adam = torch.optim.Adam(list(optimizer.parameters()), lr=1e-3)
    adam.load_state_dict(split_per_image_adam_state(saved["adam"], 6))
    old = saved["adam"]["state"]
    latents = (refiner.whitened_delta, refiner.whitened_intrinsics)
    for key in ("exp_avg", "exp_avg_sq"):
        if intrinsics == "per-image":  # one [n, 12] moment, now the pose's and the intrinsics'
            assert torch.equal(torch.cat([adam.state[p][key] for p in latents], -1), old[0][key])
        else:
            assert all(torch.equal(adam.state[p][key], old[i][key]) for i, p in enumerate(latents))
    # The pipeline's check of another scene's checkpoint reads the old key too.
    assert (
        checkpoint_camera_count({f"_model.camera_optimizer.{key}": v for key, v in saved["camera_optimizer"].items()})
        == 4
    )
