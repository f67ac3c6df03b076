"""The camera-path quantities of ``s2camp-bench robustness --trace-every`` on hand-made cameras
(``benchmarks/s2camp_bench/regime_trace.py``)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from s2camp_bench.regime_trace import _consistency, camera_path_point, error_structure, rotation_vector
from s2camp_ns.core.camera import opengl_to_opencv, se3_exp


def _ring(n: int = 8, radius: float = 2.0) -> torch.Tensor:
    """OpenCV c2w of cameras on a ring looking at the origin (z forward = towards the centre)."""
    poses = []
    for angle in torch.linspace(0.0, 2.0 * math.pi, n + 1, dtype=torch.float64)[:-1].tolist():
        centre = torch.tensor([radius * math.cos(angle), radius * math.sin(angle), 0.0], dtype=torch.float64)
        forward = -centre / centre.norm()
        down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
        right = torch.linalg.cross(down, forward)
        poses.append(torch.cat([torch.stack([right, down, forward], dim=-1), centre[:, None]], dim=-1))
    return torch.stack(poses)


def _optimizer(given: torch.Tensor, refined: torch.Tensor, fx: torch.Tensor, refined_fx: torch.Tensor):
    intrinsics = torch.zeros(given.shape[0], 13, dtype=torch.float64)
    intrinsics[:, 0] = fx
    refiner = SimpleNamespace(
        base_c2w_cv=given,
        refined_c2w=lambda: refined,
        base_intrinsics=intrinsics,
        refined_intrinsics=lambda: SimpleNamespace(fx=refined_fx),
    )
    return SimpleNamespace(refiner=refiner)


def test_a_pure_similarity_is_all_gauge_and_no_error() -> None:
    given = _ring()
    refined = given.clone()
    refined[:, :, 3] = 1.1 * given[:, :, 3]  # every centre 10% further out: a scale of the world
    fx = torch.full((8,), 100.0, dtype=torch.float64)
    point = camera_path_point(_optimizer(given, refined, fx, fx), opengl_to_opencv(given), fx)
    assert point["gauge_scale"] == pytest.approx(0.1, abs=1e-9)
    assert point["gauge_rot"] == pytest.approx(0.0, abs=1e-6)
    assert point["rot_err"] == pytest.approx(0.0, abs=1e-6)
    assert point["pos_err"] == pytest.approx(0.0, abs=1e-9)
    # Each camera moved 0.2 units backwards along its axis; nothing rotated, no focal change.
    assert point["moved_pos"] == pytest.approx(0.2, rel=1e-9)
    assert point["forward_shift"] == pytest.approx(-0.2, rel=1e-9)
    assert point["moved_rot"] == pytest.approx(0.0, abs=1e-6)
    assert point["moved_focal"] == 0.0


def test_zoom_in_while_backing_away_correlates_focal_with_depth() -> None:
    given = _ring()
    refined = given.clone()
    backwards = torch.tensor([0.0, 0.1, 0.0, 0.2, 0.0, 0.1, 0.0, 0.3], dtype=torch.float64)
    refined[:, :, 3] = given[:, :, 3] - backwards[:, None] * given[:, :, 2]
    fx = torch.full((8,), 100.0, dtype=torch.float64)
    refined_fx = fx * (1.0 + 0.5 * backwards)  # keeps the centre's image size: focal grows with distance
    point = camera_path_point(_optimizer(given, refined, fx, refined_fx), opengl_to_opencv(given), fx)
    assert point["focal_forward_corr"] == pytest.approx(-1.0, abs=1e-9)
    assert point["moved_focal"] == pytest.approx(100.0 * 0.5 * float(backwards.mean()), rel=1e-9)
    assert point["focal_err"] == pytest.approx(point["moved_focal"], rel=1e-9)


def test_adam_consistency_is_one_for_a_constant_gradient_and_small_for_noise() -> None:
    for noise, low, high in ((False, 0.999, 1.001), (True, 0.1, 0.4)):
        parameter = torch.nn.Parameter(torch.zeros(64, 6))
        adam = torch.optim.Adam([parameter], lr=1e-3, betas=(0.9, 0.999))
        generator = torch.Generator().manual_seed(0)
        for _ in range(500):
            parameter.grad = torch.randn(64, 6, generator=generator) if noise else torch.ones(64, 6)
            adam.step()
        value = _consistency(adam.state[parameter], 0.9, 0.999)
        assert low < value < high, (noise, value)
    assert math.isnan(_consistency({}, 0.9, 0.999))


def _about_own_axis(poses: torch.Tensor, axis: int, angles: torch.Tensor) -> torch.Tensor:
    """Each camera rotated by its angle about its own x (0) or y (1) axis, centre kept."""
    rotated = poses.clone()
    for i, angle in enumerate(angles.tolist()):
        c, s = math.cos(angle), math.sin(angle)
        local = torch.eye(3, dtype=torch.float64)
        j, k = (1, 2) if axis == 0 else (2, 0)
        local[j, j], local[j, k], local[k, j], local[k, k] = c, -s, s, c
        rotated[i, :, :3] = poses[i, :, :3] @ local
    return rotated


def test_error_structure_finds_the_rotation_translation_ambiguity_by_hand() -> None:
    """Cameras pitched by theta_i (about their x axis) and moved by +D theta_i along their own y keep the image of
    the content at depth D (the point D z then sits at y = D sin(theta) - D theta, about 0): pitch against y
    correlates +1. Yawed by theta_i (about y) and moved by -D theta_i along their own x: yaw against x -1. The per-axis
    RMS is the RMS of the angles; the common part is their mean."""
    reference = _ring(n=8, radius=2.0)
    theta = torch.tensor([1.0, -2.0, 0.5, 3.0, -1.0, 2.0, -0.5, 1.5], dtype=torch.float64) * 1e-3
    depth = 2.0
    pitched = _about_own_axis(reference, 0, theta)
    pitched[:, :, 3] += depth * theta[:, None] * reference[:, :, 1]
    structure = error_structure(pitched, reference)
    assert structure["pitch_y_corr"] == pytest.approx(1.0, abs=1e-9)
    assert structure["rot_err_pitch"] == pytest.approx(math.degrees(float(theta.square().mean().sqrt())), rel=1e-6)
    assert structure["rot_err_yaw"] == pytest.approx(0.0, abs=1e-9)
    assert structure["rot_err_common"] == pytest.approx(math.degrees(float(theta.mean())), rel=1e-6)
    yawed = _about_own_axis(reference, 1, theta)
    yawed[:, :, 3] -= depth * theta[:, None] * reference[:, :, 0]
    structure = error_structure(yawed, reference)
    assert structure["yaw_x_corr"] == pytest.approx(-1.0, abs=1e-9)
    assert structure["rot_err_roll"] == pytest.approx(0.0, abs=1e-9)
    # Moved the other way, the image shifts add up instead of cancelling: the correlation flips.
    wrong = _about_own_axis(reference, 0, theta)
    wrong[:, :, 3] -= depth * theta[:, None] * reference[:, :, 1]
    assert error_structure(wrong, reference)["pitch_y_corr"] == pytest.approx(-1.0, abs=1e-9)


def test_rotation_vector_is_the_twist_that_made_the_rotation():
    """se3_exp of a pure rotation twist omega gives R; rotation_vector(I, R) returns omega, tiny to large angles;
    the identity gives zero, and r_a's own frame is used (r_a^T r_b)."""
    identity = torch.eye(3, dtype=torch.float64)[None]
    for omega in ([0.0, 0.0, 1e-9], [1e-4, -2e-4, 3e-4], [0.3, -0.5, 0.2], [0.0, 2.5, 0.0]):
        twist = torch.tensor([[0.0, 0.0, 0.0, *omega]], dtype=torch.float64)
        r = se3_exp(twist)[:, :, :3]
        torch.testing.assert_close(rotation_vector(identity, r)[0], twist[0, 3:], atol=1e-12, rtol=1e-9)
    assert torch.equal(rotation_vector(identity, identity), torch.zeros(1, 3, dtype=torch.float64))
    base = se3_exp(torch.tensor([[0.0, 0.0, 0.0, 0.4, 0.1, -0.7]], dtype=torch.float64))[:, :, :3]
    local = se3_exp(torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.05]], dtype=torch.float64))[:, :, :3]
    torch.testing.assert_close(
        rotation_vector(base, base @ local)[0], torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64), atol=1e-12, rtol=0
    )
