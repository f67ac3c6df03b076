"""Camera model: agreement with pycolmap's camera models, round trips, se(3) and input validation."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
import torch

from s2camp_ns.core.camera import (
    Intrinsics,
    ParameterLayout,
    apply_pose_delta,
    check_distortion_monotonic,
    pixel_to_ray_direction,
    project,
    project_with_delta,
    se3_exp,
    tangent_bounds,
    unproject,
)

ROOM_QUARTER = dict(fx=793.13, fy=793.49, cx=389.25, cy=259.375, width=778.0, height=518.0)


def _random_points_in_view(intrinsics: Intrinsics, count: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    pixels = torch.rand(1, count, 2, generator=generator, dtype=torch.float64)
    pixels = pixels * torch.stack([intrinsics.width, intrinsics.height], dim=-1)[:, None, :]
    depth = 0.3 + 20.0 * torch.rand(1, count, 1, generator=generator, dtype=torch.float64)
    tangents = unproject(pixels, intrinsics)
    return torch.cat([tangents, torch.ones_like(depth)], dim=-1) * depth


@pytest.mark.parametrize(
    ("model", "params", "kwargs"),
    [
        ("OPENCV", [793.13, 793.49, 389.25, 259.375, -0.05, 0.01, 0.0, 0.0], dict(k1=-0.05, k2=0.01)),
        ("RADIAL", [780.0, 380.0, 250.0, 0.03, -0.004], dict(k1=0.03, k2=-0.004)),
        ("PINHOLE", [793.13, 793.49, 389.25, 259.375], dict()),
    ],
)
def test_project_and_unproject_agree_with_pycolmap(model: str, params: list[float], kwargs: dict) -> None:
    if model == "RADIAL":
        intrinsics = Intrinsics.create(fx=780.0, fy=780.0, cx=380.0, cy=250.0, width=778, height=518, **kwargs)
    else:
        intrinsics = Intrinsics.create(**ROOM_QUARTER, **kwargs)
    camera = pycolmap.Camera(model=model, width=778, height=518, params=params)
    points = _random_points_in_view(intrinsics, 500, seed=1)
    pixels, _ = project(points, intrinsics)
    expected = camera.img_from_cam(points[0].numpy())
    np.testing.assert_allclose(pixels[0].numpy(), expected, rtol=1e-6)
    tangents = unproject(pixels, intrinsics)[0].numpy()
    np.testing.assert_allclose(tangents, camera.cam_from_img(expected), rtol=1e-6, atol=1e-9)


def test_skew_matches_calibration_matrix() -> None:
    intrinsics = Intrinsics.create(**ROOM_QUARTER, skew=3.5)
    points = _random_points_in_view(intrinsics, 100, seed=2)
    k_matrix = torch.tensor([[793.13, 3.5, 389.25], [0.0, 793.49, 259.375], [0.0, 0.0, 1.0]], dtype=torch.float64)
    homogeneous = points[0] @ k_matrix.T
    expected = homogeneous[:, :2] / homogeneous[:, 2:]
    pixels, _ = project(points, intrinsics)
    torch.testing.assert_close(pixels[0], expected, rtol=1e-12, atol=1e-9)


def test_pixel_ray_pixel_round_trip_with_distortion() -> None:
    intrinsics = Intrinsics.create(**ROOM_QUARTER, skew=1.0, k1=-0.08, k2=0.02)
    generator = torch.Generator().manual_seed(3)
    pixels = torch.rand(1, 2000, 2, generator=generator, dtype=torch.float64) * torch.tensor([778.0, 518.0])
    directions = pixel_to_ray_direction(pixels, intrinsics)
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones(1, 2000, dtype=torch.float64))
    reprojected, depth = project(directions * 7.0, intrinsics)
    assert (depth > 0).all()
    assert (reprojected - pixels).abs().max() < 1e-4


def test_round_trip_float32() -> None:
    intrinsics = Intrinsics.create(**ROOM_QUARTER, k1=0.05, k2=-0.01, dtype=torch.float32)
    pixels = torch.tensor([[[0.0, 0.0], [778.0, 518.0], [400.0, 10.0], [5.0, 500.0]]], dtype=torch.float32)
    reprojected, _ = project(pixel_to_ray_direction(pixels, intrinsics), intrinsics)
    assert (reprojected - pixels).abs().max() < 1e-2


def test_undistortion_is_differentiable_with_implicit_gradient() -> None:
    k1 = torch.tensor([-0.1], dtype=torch.float64, requires_grad=True)
    intrinsics = Intrinsics.create(**ROOM_QUARTER, k2=0.01)
    intrinsics = Intrinsics(**{**intrinsics.__dict__, "k1": k1})
    pixels = torch.tensor([[[700.0, 480.0]]], dtype=torch.float64)
    tangents = unproject(pixels, intrinsics)
    (grad,) = torch.autograd.grad(tangents[0, 0, 0], k1)
    step = 1e-6
    plus = unproject(pixels, Intrinsics(**{**intrinsics.__dict__, "k1": k1.detach() + step}))[0, 0, 0]
    minus = unproject(pixels, Intrinsics(**{**intrinsics.__dict__, "k1": k1.detach() - step}))[0, 0, 0]
    assert torch.isclose(grad[0], (plus - minus) / (2 * step), rtol=1e-6)


def test_se3_exp_is_a_rigid_transform_and_smooth_at_zero() -> None:
    generator = torch.Generator().manual_seed(4)
    xi = torch.randn(64, 6, generator=generator, dtype=torch.float64)
    xi[:8, 3:] *= 1e-5
    transform = se3_exp(xi)
    rotation = transform[:, :, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(rotation)
    torch.testing.assert_close(rotation @ rotation.transpose(1, 2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rotation), torch.ones(64, dtype=torch.float64))
    # Compare with the matrix exponential of the 4x4 twist matrix.
    twist = torch.zeros(64, 4, 4, dtype=torch.float64)
    twist[:, 0, 1], twist[:, 0, 2], twist[:, 1, 2] = -xi[:, 5], xi[:, 4], -xi[:, 3]
    twist[:, 1, 0], twist[:, 2, 0], twist[:, 2, 1] = xi[:, 5], -xi[:, 4], xi[:, 3]
    twist[:, :3, 3] = xi[:, :3]
    torch.testing.assert_close(transform, torch.linalg.matrix_exp(twist)[:, :3, :], atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(se3_exp(torch.zeros(1, 6, dtype=torch.float64))[0], torch.eye(3, 4).double())


def test_pose_delta_moves_the_camera_not_the_points() -> None:
    points = torch.tensor([[[0.0, 0.0, 5.0]]], dtype=torch.float64)
    forward = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(apply_pose_delta(points, forward), torch.tensor([[[0.0, 0.0, 4.0]]]).double())


def test_project_with_zero_delta_is_project() -> None:
    intrinsics = Intrinsics.create(**ROOM_QUARTER, k1=0.01)
    points = _random_points_in_view(intrinsics, 50, seed=5)
    torch.testing.assert_close(
        project_with_delta(points, intrinsics, torch.zeros(1, 16, dtype=torch.float64)), project(points, intrinsics)[0]
    )


@pytest.mark.parametrize(("k1", "k2"), [(-0.3, 0.0), (0.0, -0.5), (-0.4, 0.05)])
def test_distortion_folds_inside_image_are_rejected(k1: float, k2: float) -> None:
    # Wide field of view so that the fold lies inside the image.
    with pytest.raises(ValueError, match="k1, k2"):
        Intrinsics.create(fx=300.0, fy=300.0, cx=400.0, cy=300.0, width=800, height=600, k1=k1, k2=k2)


def test_mild_distortion_is_accepted() -> None:
    check_distortion_monotonic(Intrinsics.create(**ROOM_QUARTER, k1=-0.1, k2=0.02))
    check_distortion_monotonic(Intrinsics.create(**ROOM_QUARTER, k1=0.2, k2=0.1))


@pytest.mark.parametrize(
    ("field", "value"), [("fx", 0.0), ("fy", -1.0), ("width", 0.0), ("height", -5.0), ("cx", float("nan"))]
)
def test_bad_intrinsics_name_the_parameter(field: str, value: float) -> None:
    arguments = dict(ROOM_QUARTER)
    arguments[field] = value
    with pytest.raises(ValueError, match=rf"^{field} must"):
        Intrinsics.create(**arguments)


@pytest.mark.parametrize("k1", [0.0, -0.08, 0.08])
def test_tangent_bounds_project_inside_the_image(k1: float) -> None:
    intrinsics = Intrinsics.create(**ROOM_QUARTER, skew=2.0, k1=k1, k2=0.01 if k1 else 0.0)
    bounds = tangent_bounds(intrinsics)[0]
    a = torch.linspace(float(bounds[0]), float(bounds[1]), 41, dtype=torch.float64)
    b = torch.linspace(float(bounds[2]), float(bounds[3]), 41, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(a, b, indexing="ij"), dim=-1).reshape(1, -1, 2)
    pixels, _ = project(torch.cat([grid, torch.ones_like(grid[..., :1])], dim=-1), intrinsics)
    tolerance = 1e-6
    assert (pixels[..., 0] >= -tolerance).all() and (pixels[..., 0] <= 778 + tolerance).all()
    assert (pixels[..., 1] >= -tolerance).all() and (pixels[..., 1] <= 518 + tolerance).all()
    if k1 == 0.0:
        expected = torch.tensor(
            [-389.25 / 793.13, (778 - 389.25) / 793.13, -259.375 / 793.49, (518 - 259.375) / 793.49],
            dtype=torch.float64,
        )
        # Vertical edges are exact; skew slants the horizontal ones, so a_min/a_max move inwards.
        assert (bounds[2:] - expected[2:]).abs().max() < 1e-5 * 0.66
        assert bounds[0] >= expected[0] and bounds[1] <= expected[1]


def test_parameter_layout() -> None:
    assert ParameterLayout().num_params == 12
    assert ParameterLayout.from_preset("pose").indices == (0, 1, 2, 3, 4, 5)
    assert ParameterLayout.from_preset("pose+focal").names[-1] == "focal"
    assert ParameterLayout.from_preset("pose+intrinsics").num_params == 10
    expanded = ParameterLayout.from_preset("pose+focal").expand(torch.arange(7.0)[None])
    assert expanded[0, 6] == 6.0 and expanded[0, 7:].abs().sum() == 0
    with pytest.raises(ValueError, match="parameter preset"):
        ParameterLayout.from_preset("everything")
