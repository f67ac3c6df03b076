"""Reprojection drift of refined cameras against the true ones (s2camp_bench.drift)."""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_bench.drift import reprojection_drift
from s2camp_ns.core.alignment import Similarity
from s2camp_ns.core.camera import Intrinsics, se3_exp


def pinhole(fx: float, n: int = 1) -> Intrinsics:
    return Intrinsics.create(fx=[fx] * n, fy=[100.0] * n, cx=50.0, cy=50.0, width=100.0, height=100.0)


def identity_pose(centre: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> torch.Tensor:
    pose = torch.zeros(1, 3, 4, dtype=torch.float64)
    pose[0, :, :3] = torch.eye(3, dtype=torch.float64)
    pose[0, :, 3] = torch.tensor(centre, dtype=torch.float64)
    return pose


def test_hand_computed_drift_of_a_shifted_camera_with_a_longer_focal():
    # True camera at the origin looking down +z, fx = fy = 100, principal point (50, 50), 100x100 pixels.
    # Points: (0, 0, 10) -> u = 50; (1, 0, 10) -> u = 60; one behind the camera and one outside the image (ignored).
    points = torch.tensor([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [0.0, 0.0, -5.0], [100.0, 0.0, 10.0]])
    # Refined camera: centre moved by 0.1 along x, fx 110 (fy unchanged).
    # (0, 0, 10): x_cam = -0.1 -> u = 50 - 110 * 0.01 = 48.9, displacement 1.1 px;
    # (1, 0, 10): x_cam = 0.9 -> u = 50 + 110 * 0.09 = 59.9, displacement 0.1 px; v stays 50 for both.
    drift = reprojection_drift(points, identity_pose(), pinhole(100.0), identity_pose((0.1, 0.0, 0.0)),
                               pinhole(110.0), align=False)  # fmt: skip
    assert drift.pairs == 2
    assert drift.behind == 0
    assert drift.rms_px == pytest.approx(math.sqrt((1.1**2 + 0.1**2) / 2), abs=1e-12)
    assert drift.max_px == pytest.approx(1.1, abs=1e-12)


def test_identical_cameras_have_no_drift_and_a_vertical_shift_moves_v():
    points = torch.tensor([[0.0, 0.0, 10.0], [0.5, -0.5, 5.0]])
    same = reprojection_drift(points, identity_pose(), pinhole(100.0), identity_pose(), pinhole(100.0), align=False)
    assert same.rms_px == 0.0 and same.pairs == 2
    # Centre 0.2 down (+y): every point moves up by fy * 0.2 / z pixels: 2 px at z = 10, 4 px at z = 5.
    shifted = reprojection_drift(points, identity_pose(), pinhole(100.0), identity_pose((0.0, 0.2, 0.0)),
                                 pinhole(100.0), align=False)  # fmt: skip
    assert shifted.rms_px == pytest.approx(math.sqrt((2.0**2 + 4.0**2) / 2), abs=1e-12)


def _ring(n: int) -> torch.Tensor:
    """Cameras on a circle of radius 4 in the z = 0 plane, each looking at the origin (OpenCV axes)."""
    poses = []
    for k in range(n):
        angle = 2.0 * math.pi * k / n
        centre = torch.tensor([4.0 * math.cos(angle), 4.0 * math.sin(angle), 0.3 * (k % 2)], dtype=torch.float64)
        forward = -centre / torch.linalg.norm(centre)
        right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        right = right / torch.linalg.norm(right)
        down = torch.linalg.cross(forward, right)
        poses.append(torch.cat([torch.stack([right, down, forward], dim=1), centre[:, None]], dim=1))
    return torch.stack(poses)


def test_alignment_removes_a_similarity_of_the_refined_cameras():
    true = _ring(6)
    points = torch.randn(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.5
    rotation = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.3, -1.2, 2.0], dtype=torch.float64))[:, :3]
    gauge = Similarity(2.7, rotation, torch.tensor([1.0, -4.0, 0.5], dtype=torch.float64))
    refined = gauge.apply_to_poses(true)  # the same cameras in another frame of the world
    intrinsics = pinhole(100.0, 6)
    aligned = reprojection_drift(points, true, intrinsics, refined, intrinsics)
    assert aligned.pairs == 6 * 40
    assert aligned.rms_px < 1e-9
    unaligned = reprojection_drift(points, true, intrinsics, refined, intrinsics, align=False)
    assert unaligned.rms_px > 1.0 or unaligned.behind > 0


def test_points_behind_the_refined_camera_are_counted_and_left_out():
    points = torch.tensor([[0.0, 0.0, 10.0], [0.0, 0.0, 1.0]])
    # Refined camera 2 units forward: the second point is now behind it.
    with pytest.warns(UserWarning, match="behind their refined camera"):
        drift = reprojection_drift(points, identity_pose(), pinhole(100.0), identity_pose((0.0, 0.0, 2.0)),
                                   pinhole(100.0), align=False)  # fmt: skip
    assert (drift.pairs, drift.behind) == (1, 1)
    assert drift.rms_px == 0.0  # on the axis: u, v stay at the principal point


def test_bad_input_is_rejected_with_the_parameter_name():
    points = torch.tensor([[0.0, 0.0, 10.0]])
    pose, intrinsics = identity_pose(), pinhole(100.0)
    with pytest.raises(ValueError, match="points"):
        reprojection_drift(torch.zeros(0, 3), pose, intrinsics, pose, intrinsics, align=False)
    with pytest.raises(ValueError, match="refined_c2w"):
        reprojection_drift(points, pose, intrinsics, torch.zeros(2, 3, 4), intrinsics, align=False)
    with pytest.raises(ValueError, match="refined_intrinsics"):
        reprojection_drift(points, pose, intrinsics, pose, pinhole(100.0, 2), align=False)
    with pytest.raises(ValueError, match="true_c2w"):
        reprojection_drift(points, pose * math.nan, intrinsics, pose, intrinsics, align=False)
    with pytest.raises(ValueError, match="none is visible"):
        reprojection_drift(torch.tensor([[0.0, 0.0, -1.0]]), pose, intrinsics, pose, intrinsics, align=False)
    with pytest.raises(ValueError, match="at least 3 cameras"):
        reprojection_drift(points, pose, intrinsics, pose, intrinsics, align=True)
