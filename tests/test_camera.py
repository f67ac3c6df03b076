"""Camera model: agreement with pycolmap's camera models, round trips, se(3) and input validation."""

from __future__ import annotations

import math
import re
import warnings
from decimal import Decimal, getcontext

import mpmath
import numpy as np
import pycolmap
import pytest
import torch

from s2camp_ns.core.camera import (
    PARAMETER_NAMES,
    Intrinsics,
    ParameterLayout,
    apply_pose_delta,
    in_image,
    opengl_to_opencv,
    pixel_to_ray_direction,
    project,
    project_with_delta,
    se3_exp,
    tangent_bounds,
    unproject,
)
from s2camp_ns.core.distortion import check_distortion_monotonic, fisheye_fold_angle, fisheye_terms, image_grid

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


# ----------------------------------------------------------------------------------------------------------------
# Tests added from the mutation-testing run (docs/mutation-testing.md): each pins a behaviour that a surviving
# mutant changed, against an independent expected value.


def _fold_radius_by_scan(k1: float, k2: float) -> float:
    """Distorted radius r (1 + k1 r^2 + k2 r^4) at its first local maximum, found on a dense grid of r."""
    r = np.linspace(0.0, 10.0, 1_000_001)
    distorted = r * (1.0 + k1 * r**2 + k2 * r**4)
    falling = np.nonzero(np.diff(distorted) <= 0.0)[0]
    assert falling.size, "this distortion does not fold before r = 10"
    return float(distorted[: falling[0] + 1].max())


# A skewed camera with an off-centre principal point; its corner tangents come from inverting K with numpy.
SKEWED = dict(fx=100.0, fy=90.0, cx=30.0, cy=70.0, skew=20.0, width=200.0, height=120.0)


def _corner_tangent_radius(camera: dict) -> float:
    k_matrix = np.array(
        [[camera["fx"], camera["skew"], camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]]
    )
    corners = np.array([[u, v, 1.0] for u in (0.0, camera["width"]) for v in (0.0, camera["height"])]).T
    rays = np.linalg.solve(k_matrix, corners)
    return float(np.hypot(rays[0], rays[1]).max())


@pytest.mark.parametrize(
    ("k1", "k2"),
    [
        (-0.1, 0.0),  # k2 = 0: the derivative 1 + 3 k1 r^2 is linear in r^2
        (0.0, -0.02),  # k2 < 0: one positive root
        (0.05, -0.01),  # k1 > 0, k2 < 0
        (-0.1, 0.001),  # k1 < 0 < k2: two positive roots, the smaller one is the fold
        (-0.1, 0.00448),  # the two roots nearly coincide
    ],
)
def test_fold_check_rejects_exactly_beyond_the_fold(k1: float, k2: float) -> None:
    """The image corners may reach just inside the fold of the distorted radius, not just beyond it."""
    fold = _fold_radius_by_scan(k1, k2)
    corner = _corner_tangent_radius(SKEWED)
    for margin, accepted in ((1.0 - 1e-4, True), (1.0 + 1e-4, False)):
        # Scaling fx, fy and skew by c divides every tangent by c: choose c so that the corners reach margin * fold.
        c = corner / (margin * fold)
        camera = {**SKEWED, "fx": SKEWED["fx"] * c, "fy": SKEWED["fy"] * c, "skew": SKEWED["skew"] * c}
        intrinsics = Intrinsics.create(**camera, k1=k1, k2=k2, validate=False)
        if accepted:
            check_distortion_monotonic(intrinsics)
        else:
            with pytest.raises(ValueError, match="non-monotonic"):
                check_distortion_monotonic(intrinsics)


def test_fold_check_rejects_a_double_root_inside_the_image() -> None:
    # k1 = -0.5, k2 = 0.1125: 1 + 3 k1 s + 5 k2 s^2 = (1 - 0.75 s)^2, exactly zero at s = 4/3, where Newton's
    # undistortion divides by zero; the distorted radius there is sqrt(4/3) (1 - 2/3 + 0.1125 * 16/9) = 0.6158.
    fold = math.sqrt(4.0 / 3.0) * (1.0 - 2.0 / 3.0 + 0.1125 * 16.0 / 9.0)
    for corner, accepted in ((0.99 * fold, True), (1.01 * fold, False)):
        f = 100.0 * math.sqrt(2.0) / corner  # square 200 x 200 image, centred principal point
        intrinsics = Intrinsics.create(
            fx=f, fy=f, cx=100.0, cy=100.0, width=200, height=200, k1=-0.5, k2=0.1125, validate=False
        )
        if accepted:
            check_distortion_monotonic(intrinsics)
        else:
            with pytest.raises(ValueError, match="non-monotonic"):
                check_distortion_monotonic(intrinsics)


def test_pincushion_distortion_never_folds_even_for_a_very_wide_camera() -> None:
    # k1, k2 > 0: the derivative 1 + 3 k1 s + 5 k2 s^2 is positive for every s >= 0 (corner tangent radius 14).
    check_distortion_monotonic(
        Intrinsics.create(fx=10.0, fy=10.0, cx=100.0, cy=100.0, width=200, height=200, k1=0.1, k2=0.004)
    )


def test_in_image_is_the_closed_image_in_front_of_the_camera() -> None:
    intrinsics = Intrinsics.create(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    points = torch.tensor(
        [
            [-0.5, -0.5, 1.0],  # pixel (0, 0), a corner: inside
            [0.5, 0.5, 1.0],  # pixel (100, 100), the opposite corner: inside
            [-0.5, 0.5, 1.0],  # pixel (0, 100)
            [0.0, 0.0, 1.0],  # principal point
            [-0.5 - 1e-9, 0.0, 1.0],  # just left of the image
            [0.0, 0.5 + 1e-9, 1.0],  # just below the image
            [0.0, 0.0, 0.0],  # the camera centre: projects to the principal point at depth 0
            [0.0, 0.0, -1.0],  # behind the camera
            [0.1, 0.0, 1e-13],  # next to the camera plane: far outside the image, not at u = fx x + cx
            [math.nan, 0.0, 1.0],  # a non-finite point masks only itself
        ],
        dtype=torch.float64,
    )[None]
    pixels, depth = project(points, intrinsics)
    torch.testing.assert_close(
        pixels[0, :4], torch.tensor([[0.0, 0.0], [100.0, 100.0], [0.0, 100.0], [50.0, 50.0]]).double()
    )
    assert float(pixels[0, 8, 0]) > 1e9
    mask = in_image(pixels, depth, intrinsics)
    assert mask[0].tolist() == [True, True, True, True, False, False, False, False, False, False]


def test_project_with_delta_matches_pycolmap_after_a_finite_update() -> None:
    """Finite pose and intrinsics deltas: exp of the 4x4 twist for the pose, pycolmap's OPENCV model for pixels."""
    intrinsics = Intrinsics.create(**ROOM_QUARTER, k1=-0.05, k2=0.01)
    points = _random_points_in_view(intrinsics, 50, seed=6)
    delta = torch.tensor(
        [[0.05, -0.02, 0.1, 0.02, -0.03, 0.01, 12.0, -3.0, 2.5, 0.0, 0.01, -0.004]], dtype=torch.float64
    )
    twist = torch.zeros(4, 4, dtype=torch.float64)
    omega, rho = delta[0, 3:6], delta[0, :3]
    twist[0, 1], twist[0, 2], twist[1, 2] = -omega[2], omega[1], -omega[0]
    twist[1, 0], twist[2, 0], twist[2, 1] = omega[2], -omega[1], omega[0]
    twist[:3, 3] = rho
    transform = torch.linalg.matrix_exp(twist)
    moved = (points[0] - transform[:3, 3]) @ transform[:3, :3]  # x' = R^T (x - t)
    camera = pycolmap.Camera(
        model="OPENCV",
        width=778,
        height=518,
        params=[793.13 + 12.0, 793.49 + 12.0, 389.25 - 3.0, 259.375 + 2.5, -0.05 + 0.01, 0.01 - 0.004, 0.0, 0.0],
    )
    expected = camera.img_from_cam(moved.numpy())
    np.testing.assert_allclose(project_with_delta(points, intrinsics, delta)[0].numpy(), expected, rtol=1e-9)


def _series(theta2: Decimal, first_factorial: int) -> Decimal:
    """sum_k (-theta^2)^k / (2k + first_factorial)!, to 40 digits."""
    total, term, k = Decimal(0), Decimal(1) / math.factorial(first_factorial), 0
    while abs(term) > Decimal("1e-40"):
        total += term
        k += 1
        term = term * -theta2 / ((2 * k + first_factorial - 1) * (2 * k + first_factorial))
    return total


def test_se3_exp_small_angle_branch_matches_the_series_to_rounding() -> None:
    """Just below the Taylor threshold (theta = 0.999e-3), R and t equal the exact series to float64 rounding."""
    getcontext().prec = 40
    omega = [0.999e-3 * c for c in (0.6, -0.48, 0.64)]  # unit axis (0.6, -0.48, 0.64)
    rho = [0.7, -1.1, 0.9]
    theta2 = sum(Decimal(w) * Decimal(w) for w in omega)
    coef_a, coef_b, coef_c = _series(theta2, 1), _series(theta2, 2), _series(theta2, 3)
    w = [[Decimal(0), -Decimal(omega[2]), Decimal(omega[1])],
         [Decimal(omega[2]), Decimal(0), -Decimal(omega[0])],
         [-Decimal(omega[1]), Decimal(omega[0]), Decimal(0)]]  # fmt: skip
    w2 = [[sum(w[i][k] * w[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
    eye = [[Decimal(int(i == j)) for j in range(3)] for i in range(3)]
    rotation = [[eye[i][j] + coef_a * w[i][j] + coef_b * w2[i][j] for j in range(3)] for i in range(3)]
    v = [[eye[i][j] + coef_b * w[i][j] + coef_c * w2[i][j] for j in range(3)] for i in range(3)]
    translation = [sum(v[i][k] * Decimal(rho[k]) for k in range(3)) for i in range(3)]
    expected = torch.tensor(
        [[float(rotation[i][j]) for j in range(3)] + [float(translation[i])] for i in range(3)], dtype=torch.float64
    )
    got = se3_exp(torch.tensor([rho + omega], dtype=torch.float64))[0]
    torch.testing.assert_close(got, expected, atol=1e-15, rtol=0)


def test_se3_exp_takes_any_batch_shape() -> None:
    xi = torch.randn(2, 3, 6, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    batched = se3_exp(xi)
    assert batched.shape == (2, 3, 3, 4)
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(se3_exp(xi[i, j]), batched[i, j], atol=1e-15, rtol=0)
    assert se3_exp(xi[0, 0]).shape == (3, 4)


def test_presets_are_the_named_layouts() -> None:
    assert ParameterLayout.from_preset("pose") == ParameterLayout(
        pose=True, focal=False, principal_point=False, skew=False, distortion=False
    )
    assert ParameterLayout.from_preset("pose+focal") == ParameterLayout(
        pose=True, focal=True, principal_point=False, skew=False, distortion=False
    )
    assert ParameterLayout.from_preset("pose+intrinsics") == ParameterLayout(
        pose=True, focal=True, principal_point=True, skew=True, distortion=False
    )
    assert ParameterLayout.from_preset("all") == ParameterLayout(True, True, True, True, True)
    message = "parameter preset must be one of 'pose', 'pose+focal', 'pose+intrinsics', 'all', got 'everything'"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        ParameterLayout.from_preset("everything")


def test_expand_takes_any_batch_shape_and_checks_the_columns() -> None:
    layout = ParameterLayout.from_preset("pose+focal")  # columns 0-6
    single = layout.expand(torch.arange(1.0, 8.0))
    assert single.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0] + [0.0] * (len(PARAMETER_NAMES) - 7)
    batched = layout.expand(torch.ones(2, 3, 7))
    assert batched.shape == (2, 3, len(PARAMETER_NAMES))
    assert batched[..., :7].eq(1).all() and batched[..., 7:].eq(0).all()
    with pytest.raises(ValueError, match=r"^delta must have 7 columns for this layout, got 5$"):
        layout.expand(torch.zeros(3, 5))
    with pytest.raises(ValueError, match=r"^delta must have 7 columns for this layout, got 5$"):
        layout.expand(torch.zeros(5))


def test_intrinsics_in_units_of_the_image_size_are_valid() -> None:
    """Positive means > 0, not >= 1: a camera in normalised units (image 0.9 wide) is valid."""
    intrinsics = Intrinsics.create(fx=0.5, fy=0.6, cx=0.45, cy=0.3, width=0.9, height=0.6)
    assert intrinsics.fx.item() == 0.5 and intrinsics.height.item() == 0.6


@pytest.mark.parametrize(("field", "value"), [("fx", -1.0), ("fy", 0.0), ("width", -5.0), ("height", 0.0)])
def test_zero_or_negative_focal_and_size_are_rejected(field: str, value: float) -> None:
    arguments = {**ROOM_QUARTER, field: value}
    with pytest.raises(ValueError, match=rf"^{field} must lie in \(0, inf\), got {value:g}"):
        Intrinsics.create(**arguments)


def _undistort_1d(a_d: float, k1: float, k2: float) -> float:
    """Real root a of k2 a^5 + k1 a^3 + a = a_d nearest to a_d (numpy polynomial roots)."""
    roots = np.roots([k2, 0.0, k1, 0.0, 1.0, -a_d])
    real = roots[np.abs(roots.imag) < 1e-12].real
    return float(real[np.argmin(np.abs(real - a_d))])


def test_tangent_bounds_of_a_barrel_camera_are_the_edge_midpoints() -> None:
    """Barrel distortion with a centred principal point: the innermost tangent of each edge is at its midpoint."""
    k1, k2 = -0.08, 0.01
    intrinsics = Intrinsics.create(fx=150.0, fy=140.0, cx=100.0, cy=50.0, width=200, height=100, k1=k1, k2=k2)
    a_min, a_max = _undistort_1d(-100.0 / 150.0, k1, k2), _undistort_1d(100.0 / 150.0, k1, k2)
    b_min, b_max = _undistort_1d(-50.0 / 140.0, k1, k2), _undistort_1d(50.0 / 140.0, k1, k2)
    inset_a, inset_b = 1e-5 * (a_max - a_min), 1e-5 * (b_max - b_min)
    expected = torch.tensor([[a_min + inset_a, a_max - inset_a, b_min + inset_b, b_max - inset_b]], dtype=torch.float64)
    torch.testing.assert_close(tangent_bounds(intrinsics), expected, atol=1e-12, rtol=0)


def test_opengl_to_opencv_flips_the_camera_y_and_z_axes() -> None:
    # An OpenGL camera at (1, 2, 3) looking down the world -z axis with world y up: OpenCV's y (down) is world -y and
    # its z (forward) is world -z, so the point (1, 2, 1), two units in front of it, has OpenCV depth +2.
    c2w_gl = torch.tensor([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]], dtype=torch.float64)
    expected = torch.tensor([[1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 2.0], [0.0, 0.0, -1.0, 3.0]], dtype=torch.float64)
    c2w_cv = opengl_to_opencv(c2w_gl)
    assert torch.equal(c2w_cv, expected)
    point_cam = c2w_cv[:, :3].T @ (torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64) - c2w_cv[:, 3])
    assert point_cam.tolist() == [0.0, 0.0, 2.0]
    assert torch.equal(opengl_to_opencv(c2w_cv), c2w_gl)  # its own inverse
    homogeneous = torch.cat([c2w_gl, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
    assert torch.equal(opengl_to_opencv(homogeneous), torch.cat([expected, homogeneous[3:]]))
    batched = opengl_to_opencv(torch.stack([c2w_gl, 2.0 * c2w_gl]))
    assert torch.equal(batched, torch.stack([expected, 2.0 * expected]))
    with pytest.raises(ValueError, match=re.escape("c2w must have shape [..., 3, 4] or [..., 4, 4], got (3, 3)")):
        opengl_to_opencv(torch.eye(3))


def test_fisheye_terms_match_a_50_digit_reference_on_both_branches() -> None:
    """h = theta / rho, theta^2 and q = (z / R - h) / rho^2 near the axis (Taylor branch, rho / z < 1e-4) and off it."""
    mpmath.mp.dps = 50
    cases = [  # (rho / z, z): Taylor branch just inside its limit, at z != 1; general branch, also at small z
        (0.99e-4, 2.0),
        (0.5e-4, 0.5),
        (0.999e-4, 0.03),
        (1e-2, 1.0),
        (0.5, 0.01),
        (0.7, 1.3),
        (3.0, -0.4),  # behind the camera (theta > 90 degrees)
    ]
    points, expected = [], []
    for t, z in cases:
        rho = t * abs(z)
        x, y = 0.6 * rho, 0.8 * rho
        points.append([x, y, z])
        mx, my, mz = mpmath.mpf(x), mpmath.mpf(y), mpmath.mpf(z)
        mrho2 = mx * mx + my * my
        theta = mpmath.atan2(mpmath.sqrt(mrho2), mz)
        h = theta / mpmath.sqrt(mrho2)
        expected.append([float(h), float(theta * theta), float((mz / (mrho2 + mz * mz) - h) / mrho2)])
    terms = fisheye_terms(torch.tensor([points], dtype=torch.float64))
    got = torch.stack([terms.h[0], terms.theta2[0], terms.q[0]], dim=-1)
    torch.testing.assert_close(got, torch.tensor(expected, dtype=torch.float64), rtol=1e-11, atol=0)
    centre = fisheye_terms(torch.zeros(1, 1, 3, dtype=torch.float64))
    assert all(bool(torch.isfinite(v).all()) for v in (centre.h, centre.theta2, centre.q, centre.norm2))


def test_fisheye_fold_angle_brackets_the_root_of_the_slope() -> None:
    """The returned fold is the last scan sample (pi / 4096 apart) below the first root of theta_d'(theta)."""
    # One coefficient per camera, so theta_fold solves 1 + (2j + 1) k_j theta^(2j) = 0 in closed form; the last
    # camera does not fold (theta_fold = pi).
    ks = [(-0.5, 0, 0, 0), (-0.3, 0, 0, 0), (0, -0.05, 0, 0), (0, 0, -0.01, 0), (0, 0, 0, -0.002), (0, 0, 0, 0)]
    roots = [(-1.0 / (3 * k[0])) ** 0.5 if k[0] else None for k in ks]
    roots[2], roots[3], roots[4] = (1.0 / 0.25) ** 0.25, (1.0 / 0.07) ** (1 / 6), (1.0 / 0.018) ** 0.125
    intrinsics = Intrinsics.create(
        fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100, model="fisheye", validate=False,
        k1=[k[0] for k in ks], k2=[k[1] for k in ks], k3=[k[2] for k in ks], k4=[k[3] for k in ks],
    )  # fmt: skip
    theta_fold, theta_d_fold = fisheye_fold_angle(intrinsics)
    step = math.pi / 4096
    for i, root in enumerate(roots):
        if root is None:
            assert theta_fold[i].item() == math.pi
        else:
            assert root - step < theta_fold[i].item() <= root, i
        t2 = theta_fold[i].item() ** 2
        k1, k2, k3, k4 = ks[i]
        expected = theta_fold[i].item() * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4)
        assert math.isclose(theta_d_fold[i].item(), expected, rel_tol=1e-12), i
    theta32, theta_d32 = fisheye_fold_angle(intrinsics.to(dtype=torch.float32))
    assert theta32.dtype == torch.float32 and theta_d32.dtype == torch.float32


def test_folding_fisheye_is_rejected_with_its_coefficients() -> None:
    # Camera 1's theta_d stops increasing at theta = sqrt(1/0.9) = 1.054 rad (theta_d = 0.70); its corners
    # reach theta_d = sqrt(2) * 50 / 30 = 2.36, far beyond.
    with pytest.raises(ValueError) as error:
        Intrinsics.create(
            fx=[30.0, 30.0], fy=[30.0, 30.0], cx=50.0, cy=50.0, width=100, height=100, model="fisheye",
            k1=[0.0, -0.3], k2=0.0, k3=0.0, k4=0.0,
        )  # fmt: skip
    message = str(error.value)
    assert message.startswith("k1, k2, k3, k4 = (-0.3, 0, 0, 0) of fisheye camera 1 make theta_d(theta) stop ")
    assert message.endswith("; allowed are coefficients with theta_d increasing up to the image corners")


def test_tangent_bounds_refuse_a_fisheye_by_name() -> None:
    fisheye = Intrinsics.create(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100, model="fisheye")
    message = (
        "tangent_bounds needs a perspective camera, got model 'fisheye': a fisheye's field of view has no tangent "
        "box; sample its image instead (preconditioner.sample_proxy_points does)"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        tangent_bounds(fisheye)


def test_tangent_bounds_of_a_pincushion_camera_are_its_undistorted_corners() -> None:
    """Pincushion distortion bends the border outwards: the box corners are the undistorted image corners."""
    k1, k2 = 0.05, 0.01
    intrinsics = Intrinsics.create(fx=150.0, fy=140.0, cx=100.0, cy=50.0, width=200, height=100, k1=k1, k2=k2)
    a_d, b_d = 100.0 / 150.0, 50.0 / 140.0  # the corner (200, 100) in distorted tangents; the others by symmetry
    r_d = math.hypot(a_d, b_d)
    r = _undistort_1d(r_d, k1, k2)
    a, b = a_d * r / r_d, b_d * r / r_d
    expected = torch.tensor([[-a * (1 - 2e-5), a * (1 - 2e-5), -b * (1 - 2e-5), b * (1 - 2e-5)]], dtype=torch.float64)
    torch.testing.assert_close(tangent_bounds(intrinsics), expected, atol=1e-12, rtol=0)


def test_image_grid_is_the_border_and_an_interior_lattice_in_the_intrinsics_dtype():
    """edge = 4 per side: u in {0, 1/3, 2/3, 1} along each side; interior = 4: the 4 x 4 lattice of the same values,
    row by row; both scaled by (W, H) of each camera (1/3 is not a float32 number: the dtype shows)."""
    intrinsics = Intrinsics.create(fx=300.0, fy=300.0, cx=150.0, cy=100.0, width=[640.0, 300.0], height=[480.0, 200.0])
    grid = image_grid(intrinsics, edge=4, interior=4)
    t = [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0]
    border = [(u, 0.0) for u in t] + [(u, 1.0) for u in t] + [(0.0, u) for u in t] + [(1.0, u) for u in t]
    inner = [(a, b) for a in t for b in t]
    size = torch.tensor([[640.0, 480.0], [300.0, 200.0]], dtype=torch.float64)
    expected = torch.tensor(border + inner, dtype=torch.float64)[None] * size[:, None, :]
    assert grid.dtype == torch.float64 and grid.shape == (2, 32, 2)
    torch.testing.assert_close(grid, expected, atol=1e-12, rtol=0)
    assert image_grid(intrinsics.to(dtype=torch.float32), edge=4, interior=3).dtype == torch.float32


def test_image_grid_passes_meshgrid_its_indexing():
    """torch warns (once per process, always under set_warn_always) when meshgrid gets no indexing argument."""
    intrinsics = Intrinsics.create(fx=300.0, fy=300.0, cx=150.0, cy=100.0, width=640.0, height=480.0)
    previous = torch.is_warn_always_enabled()
    torch.set_warn_always(True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            image_grid(intrinsics, edge=4, interior=3)
    finally:
        torch.set_warn_always(previous)


def test_from_tensors_defaults_to_a_perspective_camera():
    intrinsics = Intrinsics.create(fx=300.0, fy=301.0, cx=150.0, cy=100.0, width=320.0, height=200.0, k1=-0.01)
    again = Intrinsics.from_tensors(intrinsics.tensors())
    assert again.model == "perspective" and torch.equal(again.tensors(), intrinsics.tensors())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_strong_tangential_distortion_of_a_wide_camera_is_accepted_and_undistorts(dtype: torch.dtype) -> None:
    """p1 = 0.08 on a 94 x 77 degree camera (corner tangents up to 1.07): x_d = x (1 + 2 p1 y),
    y_d = y + p1 (x^2 + 3 y^2), whose Jacobian (1 + 2 p1 y)(1 + 6 p1 y) - 4 p1^2 x^2 stays positive at the corner
    (0, 0) preimage, (x, y) = (-1.40, -1.49). Accepted in float32 too (the check runs in float64), and undistortion
    inverts the distortion at the corners and edge midpoints."""
    intrinsics = Intrinsics.create(fx=300.0, fy=300.0, cx=320.0, cy=240.0, width=640, height=480, p1=0.08, dtype=dtype)
    p1, (xd, yd) = 0.08, (-320.0 / 300.0, -240.0 / 300.0)
    # y + p1 (xd^2 / (1 + 2 p1 y)^2 + 3 y^2) = yd, times (1 + 2 p1 y)^2: a quartic in y (numpy's roots).
    quartic = np.polynomial.Polynomial([-yd, 1.0, 3 * p1]) * np.polynomial.Polynomial([1.0, 2 * p1]) ** 2 + p1 * xd**2
    y = max(r.real for r in quartic.roots() if abs(r.imag) < 1e-12)
    x = xd / (1 + 2 * p1 * y)
    assert (1 + 2 * p1 * y) * (1 + 6 * p1 * y) - 4 * p1**2 * x**2 > 0.1
    pixels = torch.tensor([[[0.0, 0.0], [640.0, 0.0], [0.0, 480.0], [640.0, 480.0], [320.0, 0.0], [0.0, 240.0]]])
    camera64 = intrinsics.to(dtype=torch.float64)
    back, _ = project(pixel_to_ray_direction(pixels.double(), camera64), camera64)
    torch.testing.assert_close(back, pixels.double(), atol=1e-9, rtol=0)


def test_a_tangential_fold_names_the_camera_its_coefficients_and_the_first_pixel_in_full() -> None:
    """Camera 1's p1 = 0.09: the image corner (0, 0), tangents (-320/300, -240/300), has no undistorted preimage (the
    quartic of the test above has no real root), and it is the first point of the check's grid (border first)."""
    p1, (xd, yd) = 0.09, (-320.0 / 300.0, -240.0 / 300.0)
    quartic = np.polynomial.Polynomial([-yd, 1.0, 3 * p1]) * np.polynomial.Polynomial([1.0, 2 * p1]) ** 2 + p1 * xd**2
    assert all(abs(r.imag) > 1e-3 for r in quartic.roots())
    message = (
        "k1, k2, k3, k4, p1, p2 = (0, 0, 0, 0, 0.09, 0) of camera 1 make the distortion fold inside the image: it is "
        "not invertible at pixel (0.0, 0.0); allowed are coefficients whose distortion stays one-to-one over the "
        "whole image"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        Intrinsics.create(fx=300.0, fy=300.0, cx=320.0, cy=240.0, width=640, height=480, p1=[0.001, 0.09])


def test_tangential_distortion_just_inside_its_fold_is_accepted() -> None:
    """p1 = 0.082 on the 640 x 480, f = 300 camera: every pixel of a 17 x 13 grid (corners included) has an undistorted
    preimage (the largest real root of the quartic above) where the Jacobian (1 + 2 p1 y)(1 + 6 p1 y) - 4 p1^2 x^2 is
    still positive, but only just at the corner (0, 0) (about 0.1; p1 = 0.084 has no preimage there). Undistortion
    must converge there within its iterations."""
    p1 = 0.082
    smallest = math.inf
    for u in np.linspace(0.0, 640.0, 17):
        for v in np.linspace(0.0, 480.0, 13):
            xd, yd = (u - 320.0) / 300.0, (v - 240.0) / 300.0
            poly = np.polynomial.Polynomial
            quartic = poly([-yd, 1.0, 3 * p1]) * poly([1.0, 2 * p1]) ** 2 + p1 * xd**2
            y = max(r.real for r in quartic.roots() if abs(r.imag) < 1e-9)
            x = xd / (1 + 2 * p1 * y)
            smallest = min(smallest, (1 + 2 * p1 * y) * (1 + 6 * p1 * y) - 4 * p1**2 * x**2)
    assert 0.05 < smallest < 0.15
    intrinsics = Intrinsics.create(fx=300.0, fy=300.0, cx=320.0, cy=240.0, width=640, height=480, p1=p1)
    corner = torch.zeros(1, 1, 2, dtype=torch.float64)
    back, _ = project(pixel_to_ray_direction(corner, intrinsics), intrinsics)
    torch.testing.assert_close(back, corner, atol=1e-9, rtol=0)


def test_radial_helpers_default_to_the_two_coefficient_model() -> None:
    """Without k3, k4: D'(r^2) = k1 + 2 k2 r^2, and s = r / r_d solves s (1 + k1 r^2 + k2 r^4) = 1 (r = s r_d)."""
    from s2camp_ns.core.distortion import distortion_slope, undistort_scale

    r2 = torch.tensor([0.0, 0.25, 1.0, 2.0], dtype=torch.float64)
    k1, k2 = torch.tensor(-0.05, dtype=torch.float64), torch.tensor(0.01, dtype=torch.float64)
    torch.testing.assert_close(distortion_slope(r2, k1, k2), k1 + 2.0 * k2 * r2, atol=1e-15, rtol=0)
    r_d = r2.sqrt()
    r = undistort_scale(r2, k1, k2) * r_d
    torch.testing.assert_close(r * (1.0 + k1 * r**2 + k2 * r**4), r_d, atol=1e-12, rtol=0)


def test_intrinsics_built_without_the_opencv_terms_get_zero_ones() -> None:
    """The nine-field constructor of the radial model: k3, k4, p1, p2 default to zeros shaped and typed like k1."""
    one = torch.tensor([1.0, 2.0], dtype=torch.float64)
    k1 = torch.tensor([-0.01, 0.02], dtype=torch.float64)
    intrinsics = Intrinsics(300.0 * one, 300.0 * one, 160.0 * one, 100.0 * one, 0.0 * one, k1, 0.0 * one, 320.0 * one,
                            200.0 * one)  # fmt: skip
    for name in ("k3", "k4", "p1", "p2"):
        value = getattr(intrinsics, name)
        assert torch.equal(value, torch.zeros(2, dtype=torch.float64)) and value.dtype == torch.float64


def test_undistortion_takes_the_radial_path_exactly_when_there_is_no_tangential_term() -> None:
    """p1 = p2 = 0: the scalar radial inverse (undistort_scale with all four k) bit for bit; p1 or p2 alone: the 2-D
    inverse, which the forward distortion maps back onto the distorted tangents."""
    from s2camp_ns.core.distortion import distort_tangents, undistort_scale, undistort_tangents

    a_d = torch.tensor([[0.3, -0.5, 0.7]], dtype=torch.float64)
    b_d = torch.tensor([[0.2, 0.4, -0.6]], dtype=torch.float64)
    base = dict(fx=300.0, fy=300.0, cx=320.0, cy=240.0, width=640, height=480, k1=-0.05, k2=0.01)
    radial = Intrinsics.create(**base, k3=0.002, k4=-0.0005)
    ks = (getattr(radial, name)[:, None] for name in ("k1", "k2", "k3", "k4"))
    scale = undistort_scale(a_d * a_d + b_d * b_d, *ks)
    a, b = undistort_tangents(a_d, b_d, radial)
    assert torch.equal(a, a_d * scale) and torch.equal(b, b_d * scale)
    for name in ("p1", "p2"):
        camera = Intrinsics.create(**base, **{name: 0.002})
        fa, fb = distort_tangents(*undistort_tangents(a_d, b_d, camera), camera)
        torch.testing.assert_close(torch.stack([fa, fb]), torch.stack([a_d, b_d]), atol=1e-12, rtol=0)
