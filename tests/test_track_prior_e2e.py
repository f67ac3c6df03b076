"""The track prior inside ``ns-train s2camp``: the data parser's tracks reach the camera optimizer and the model's
callback applies the prior after every step (end to end, a handful of CPU steps)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_e2e import _failure, _run

from s2camp_ns.nerfstudio.train_commands import DATAPARSER_SUBCOMMAND, camera_schedule_arguments, ns_train_arguments

pytestmark = pytest.mark.slow

STEPS = 12


def _train(scene: Path, output: Path, prior: bool, dataparser: list[str] | None = None) -> dict:
    command = [
        *ns_train_arguments("s2camp", scene, output, "prior", f"prior-{prior}", STEPS, STEPS, 256),
        "--machine.device-type", "cpu",
        "--vis", "tensorboard",
        # A large camera step with no warm-up: without the prior the accurate cameras move at once.
        *camera_schedule_arguments(1e-2, 1e-2),
        "--pipeline.model.camera-optimizer.track-prior", str(prior),
        *(dataparser or []),
    ]  # fmt: skip
    result = _run(command, timeout=400)
    assert result.returncode == 0, _failure(result, "ns-train s2camp")
    checkpoint = output / "prior" / "s2camp" / f"prior-{prior}" / "nerfstudio_models" / f"step-{STEPS - 1:09d}.ckpt"
    return torch.load(checkpoint, map_location="cpu", weights_only=False)["pipeline"]


@pytest.mark.timeout(900)
def test_exact_tracks_hold_accurate_cameras_that_move_without_the_prior(tiny_scene: Path, tmp_path: Path) -> None:
    # The generated tracks are the exact projections of the true cameras (reprojection error ~1e-5 px): with the prior
    # the latents stay at the start; without it the same steps move them.
    keys = ("_model.camera_optimizer.whitened_delta", "_model.camera_optimizer.whitened_intrinsics")
    held = _train(tiny_scene, tmp_path, prior=True)
    free = _train(tiny_scene, tmp_path, prior=False)
    for key in keys:
        assert float(held[key].abs().max()) < 1e-6, key
        assert float(free[key].abs().max()) > 1e-3, key


@pytest.mark.timeout(900)
def test_exact_tracks_bring_perturbed_cameras_to_the_truth(tiny_scene: Path, tmp_path: Path) -> None:
    # The CamP perturbation moves the cameras after the sparse model was made: the tracks still say where the true
    # cameras are, so the prior's anchor is the truth (``core.track_fit``) and, with exact tracks (radius ~0), every
    # step ends there. Checked against the data parser's reference (true) cameras, not against the fit.
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
    from s2camp_ns.nerfstudio.dataparser import S2CampDataParserConfig

    perturbed = [DATAPARSER_SUBCOMMAND, "--perturbation.enabled", "True"]
    state = _train(tiny_scene, tmp_path, prior=True, dataparser=perturbed)
    config = S2CampDataParserConfig(data=tiny_scene)
    config.perturbation.enabled = True
    outputs = config.setup().get_dataparser_outputs("train")
    optimizer = S2CampCameraOptimizerConfig(track_prior=True).setup(num_cameras=outputs.cameras.shape[0], device="cpu")
    optimizer.set_camera_groups(outputs.metadata["camera_ids"])
    optimizer.set_train_cameras(outputs.cameras, points=outputs.metadata["points3D_xyz"])
    prefix = "_model.camera_optimizer."
    optimizer.load_state_dict({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}, strict=False)
    reference = outputs.metadata["reference_cameras"]
    given = outputs.cameras.camera_to_worlds.double()
    truth = reference.camera_to_worlds.double()
    assert float((given - truth).abs().max()) > 1e-2  # the perturbation is there to be undone
    refined = optimizer.refined_c2w(opengl=True)
    torch.testing.assert_close(refined, truth, atol=1e-4, rtol=0)
    torch.testing.assert_close(optimizer.refined_intrinsics().fx, reference.fx[:, 0].double(), atol=1e-2, rtol=0)
