"""The track prior inside ``ns-train s2camp``: the data parser's tracks reach the camera optimizer and the model's
callback applies the prior after every step (end to end, a handful of CPU steps)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hang_guard import HANG_GUARD_S
from test_e2e import _failure, _run

from s2camp_bench.train_commands import camera_schedule_arguments, ns_train_arguments

pytestmark = [pytest.mark.slow, pytest.mark.timeout(HANG_GUARD_S)]

STEPS = 12


def _train(scene: Path, output: Path, prior: bool) -> dict:
    command = [
        *ns_train_arguments("s2camp", scene, output, "prior", f"prior-{prior}", STEPS, STEPS, 256),
        "--machine.device-type", "cpu",
        "--vis", "tensorboard",
        # A large camera step with no warm-up: without the prior the accurate cameras move at once.
        *camera_schedule_arguments(1e-2, 1e-2),
        "--pipeline.model.camera-optimizer.track-prior", str(prior),
        "s2camp-data", "--refine-keypoints", "False",  # exact tracks: refining them would move them
    ]  # fmt: skip
    result = _run(command)
    assert result.returncode == 0, _failure(result, "ns-train s2camp")
    checkpoint = output / "prior" / "s2camp" / f"prior-{prior}" / "nerfstudio_models" / f"step-{STEPS - 1:09d}.ckpt"
    return torch.load(checkpoint, map_location="cpu", weights_only=False)["pipeline"]


def test_exact_tracks_hold_accurate_cameras_that_move_without_the_prior(tiny_scene: Path, tmp_path: Path) -> None:
    # The generated tracks are the exact projections of the true cameras (reprojection error ~1e-5 px): with the prior
    # the latents stay at the start; without it the same steps move them.
    keys = ("_model.camera_optimizer.refiner.whitened_delta", "_model.camera_optimizer.refiner.whitened_intrinsics")
    held = _train(tiny_scene, tmp_path, prior=True)
    free = _train(tiny_scene, tmp_path, prior=False)
    for key in keys:
        assert float(held[key].abs().max()) < 1e-6, key
        assert float(free[key].abs().max()) > 1e-3, key
