"""``CameraRefiner`` in plain PyTorch, no nerfstudio: perturbed cameras fitted to the pixels of known points.

The example of docs/USAGE.md ("Plain PyTorch: CameraRefiner"): the loop between the markers is that section's code.
"""

from __future__ import annotations

import subprocess
import sys

import torch

from s2camp_ns.core.camera import Intrinsics, apply_local_transform, project, se3_exp
from s2camp_ns.core.refiner import CameraRefiner

NUM_IMAGES = 4


def world_to_camera(c2w: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Camera-frame coordinates [n, l, 3] of world points [l, 3] seen by OpenCV cameras c2w [n, 3, 4]."""
    return apply_local_transform(points.expand(c2w.shape[0], -1, -1), c2w)


def scene() -> tuple[torch.Tensor, torch.Tensor, Intrinsics, torch.Tensor, Intrinsics]:
    """Four cameras on a line looking down +z at 300 points 3-5 units away: the true cameras and, perturbed by a
    known pose twist (about 0.03 units, 0.02 rad) and 4 px of focal length, the given ones."""
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(300, 3, generator=generator, dtype=torch.float64) * torch.tensor(
        [3.0, 2.0, 2.0]
    ) - torch.tensor([1.5, 1.0, -3.0])
    c2w = torch.zeros(NUM_IMAGES, 3, 4, dtype=torch.float64)
    c2w[:, :, :3] = torch.eye(3, dtype=torch.float64)
    c2w[:, 0, 3] = torch.linspace(-0.6, 0.6, NUM_IMAGES, dtype=torch.float64)
    truth = Intrinsics.create(fx=100.0, fy=100.0, cx=64.0, cy=48.0, width=128, height=96).to(dtype=torch.float64)
    truth = Intrinsics.from_tensors(truth.tensors().expand(NUM_IMAGES, -1).clone())
    twist = torch.randn(NUM_IMAGES, 6, generator=generator, dtype=torch.float64) * 0.02
    delta = se3_exp(twist)
    given_c2w = torch.cat([c2w[:, :, :3] @ delta[:, :, :3], c2w[:, :, 3:] + c2w[:, :, :3] @ delta[:, :, 3:]], dim=-1)
    given = truth.tensors().clone()
    given[:, :2] += 4.0  # fx, fy
    return points, given_c2w, Intrinsics.from_tensors(given), c2w, truth


def test_refiner_fits_perturbed_cameras_to_their_points_without_nerfstudio() -> None:
    points, c2w, intrinsics, true_c2w, truth = scene()
    observed, _ = project(world_to_camera(true_c2w, points), truth)  # [n, 300, 2], pixels of the true cameras

    def error(refiner: CameraRefiner) -> float:
        with torch.no_grad():
            pixels, _ = project(world_to_camera(refiner.refined_c2w(), points), refiner.refined_intrinsics())
        return float((pixels - observed).square().sum(dim=-1).mean().sqrt())

    # --- docs/USAGE.md example
    refiner = CameraRefiner(num_images=len(c2w), parameters="pose+focal")
    refiner.set_cameras(c2w, intrinsics)  # OpenCV c2w [n, 3, 4] and the core's Intrinsics; computes P
    adam = torch.optim.Adam(refiner.parameters(), lr=1e-3)
    before = error(refiner)
    for step in range(300):
        points_cam = apply_local_transform(points.expand(len(c2w), -1, -1), refiner.refined_c2w())  # [n, l, 3]
        pixels, _ = project(points_cam, refiner.refined_intrinsics())
        loss = (pixels - observed).square().mean()
        adam.zero_grad()
        loss.backward()
        adam.step()
        if step % 100 == 99:
            refiner.refresh(step, adam)  # P at the refined intrinsics; the cameras do not move
    # --- end of the example
    after = error(refiner)
    assert before > 3.0  # the perturbation is visible: several pixels RMS
    assert after < before / 10, (before, after)  # about 4 px RMS to well under half a pixel
    assert int(refiner.num_refreshes) == 4  # the initial P and three refreshes
    torch.testing.assert_close(refiner.refined_intrinsics().fx, truth.fx, atol=0.5, rtol=0)  # given: 4 px off


def test_a_refresh_does_not_move_the_cameras() -> None:
    points, c2w, intrinsics, _, _ = scene()
    refiner = CameraRefiner(num_images=NUM_IMAGES)
    refiner.set_cameras(c2w, intrinsics)
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():  # a small step of every latent: the intrinsics move, distortion stays monotonic
        refiner.whitened_delta.copy_(torch.randn(NUM_IMAGES, 6, generator=generator) * 1e-3)
        refiner.whitened_intrinsics.copy_(torch.randn(1, 6, generator=generator) * 1e-3)
    deltas = refiner.deltas().detach().clone()
    precond = refiner.precond.clone()
    refiner.refresh(step=1)
    assert not torch.equal(refiner.precond, precond)  # the intrinsics moved, so P did
    torch.testing.assert_close(refiner.deltas(), deltas, atol=1e-9, rtol=1e-6)  # a float32 latent


def test_p_is_bit_identical_when_built_twice_and_differs_per_layout() -> None:
    _, c2w, intrinsics, _, _ = scene()
    built = []
    for per_camera in (True, True, False):
        refiner = CameraRefiner(num_images=NUM_IMAGES, per_camera_intrinsics=per_camera)
        refiner.set_cameras(c2w, intrinsics)
        built.append(refiner)
    assert torch.equal(built[0].precond, built[1].precond) and torch.equal(built[0].precond_inv, built[1].precond_inv)
    assert built[0].precond.dtype == torch.float64 and tuple(built[0].precond.shape) == (NUM_IMAGES, 12, 12)
    # One physical camera (identical intrinsics): a pose latent per image, one intrinsics latent.
    assert tuple(built[0].whitened_delta.shape) == (NUM_IMAGES, 6) and tuple(built[0].whitened_intrinsics.shape) == (
        1,
        6,
    )
    # Per image: the same storage, one intrinsics row per image.
    assert tuple(built[2].whitened_delta.shape) == (NUM_IMAGES, 6)
    assert tuple(built[2].whitened_intrinsics.shape) == (NUM_IMAGES, 6)
    # P^T P = Sigma + damping for both layouts (paper eq. 17): the block-triangular factor is not the symmetric root.
    assert not torch.allclose(built[0].precond, built[2].precond)
    torch.testing.assert_close(
        built[0].precond.transpose(-1, -2) @ built[0].precond,
        built[2].precond.transpose(-1, -2) @ built[2].precond,
        atol=1e-9,
        rtol=1e-9,
    )


def test_the_core_refiner_imports_no_nerfstudio() -> None:
    code = (
        "import sys, s2camp_ns.core.refiner, s2camp_ns.core.track_prior; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'nerfstudio'))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]", result.stdout


def test_without_the_photometric_loss_the_latents_of_another_camera_model_get_no_gradient() -> None:
    """``photometric`` False zeroes the latents' gradients; an OPENCV model resizes them (its distortion columns), and
    the resized latents must keep that: before, they were made without the hook and the loss moved the cameras."""
    points, c2w, intrinsics, true_c2w, truth = scene()
    observed, _ = project(world_to_camera(true_c2w, points), truth)
    for per_camera in (True, False):
        refiner = CameraRefiner(num_images=NUM_IMAGES, per_camera_intrinsics=per_camera, photometric=False)
        refiner.set_camera_model("OPENCV")
        assert refiner.layout.num_params > 12  # the OPENCV layout: more columns than RADIAL's
        refiner.set_cameras(c2w, intrinsics)
        latents = [refiner.whitened_delta] + ([refiner.whitened_intrinsics] if per_camera else [])
        points_cam = apply_local_transform(points.expand(NUM_IMAGES, -1, -1), refiner.refined_c2w())
        pixels, _ = project(points_cam, refiner.refined_intrinsics())
        (pixels - observed).square().mean().backward()
        for latent in latents:
            assert latent.grad is not None and not bool(latent.grad.any()), per_camera
