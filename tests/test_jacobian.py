"""Analytic Jacobian (paper eq. 4) against torch.func autodiff and finite differences; Gram matrix (eq. 5)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.func import jacrev

from s2camp_ns.core.camera import (
    NUM_CAMERA_PARAMS,
    Intrinsics,
    ParameterLayout,
    pixel_to_ray_direction,
    project_with_delta,
    unproject,
)
from s2camp_ns.core.jacobian import gram_matrix, projection_jacobian, relative_gram_error


def _camera_and_points(seed: int, count: int = 64) -> tuple[Intrinsics, torch.Tensor]:
    intrinsics = Intrinsics.create(
        fx=[793.1, 410.0],
        fy=[793.5, 405.0],
        cx=[389.2, 330.0],
        cy=[259.4, 210.0],
        width=[778, 640],
        height=[518, 420],
        skew=[0.0, 1.5],
        k1=[-0.05, 0.02],
        k2=[0.01, -0.003],
    )
    generator = torch.Generator().manual_seed(seed)
    pixels = torch.rand(2, count, 2, generator=generator, dtype=torch.float64)
    pixels = pixels * torch.stack([intrinsics.width, intrinsics.height], dim=-1)[:, None, :]
    depth = 0.4 + 30.0 * torch.rand(2, count, 1, generator=generator, dtype=torch.float64)
    tangents = unproject(pixels, intrinsics)
    return intrinsics, torch.cat([tangents, torch.ones_like(depth)], dim=-1) * depth


def _autodiff_jacobian(points: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    """All 16 columns by torch.func.jacrev of project_with_delta."""

    def stacked_projection(delta: torch.Tensor) -> torch.Tensor:
        return project_with_delta(points, intrinsics, delta)

    jacobian = jacrev(stacked_projection)(torch.zeros(intrinsics.num_cameras, NUM_CAMERA_PARAMS, dtype=torch.float64))
    # [n, l, 2, n, 16] -> per-camera block [n, l, 2, 16]
    return torch.stack([jacobian[i, :, :, i, :] for i in range(intrinsics.num_cameras)])


def _finite_difference_jacobian(points: torch.Tensor, intrinsics: Intrinsics, step: float = 1e-6) -> torch.Tensor:
    columns = []
    for k in range(NUM_CAMERA_PARAMS):
        delta = torch.zeros(intrinsics.num_cameras, NUM_CAMERA_PARAMS, dtype=torch.float64)
        delta[:, k] = step
        central = project_with_delta(points, intrinsics, delta) - project_with_delta(points, intrinsics, -delta)
        columns.append(central / (2 * step))
    return torch.stack(columns, dim=-1)


def _distorted_camera_and_points(model: str, seed: int, count: int = 48) -> tuple[Intrinsics, torch.Tensor]:
    """Two cameras with every coefficient of ``model`` nonzero (perspective: also nerfstudio's r^8 k4), and points
    from pixels all over the image; fisheye points reach past 90 degrees, one sits on the axis, one next to it."""
    if model == "fisheye":
        intrinsics = Intrinsics.create(
            fx=[170.0, 200.0],
            fy=[168.0, 203.0],
            cx=[322.0, 300.0],
            cy=[239.0, 250.0],
            width=[640, 600],
            height=[480, 500],
            skew=[0.0, 0.8],
            k1=[0.04, -0.02],
            k2=[-0.004, 0.006],
            k3=[0.001, -0.0005],
            k4=[0.0001, 0.00002],
            model="fisheye",
        )
    else:
        intrinsics = Intrinsics.create(
            fx=[500.0, 410.0],
            fy=[505.0, 405.0],
            cx=[322.0, 300.0],
            cy=[239.0, 250.0],
            width=[640, 600],
            height=[480, 500],
            skew=[0.0, 1.5],
            k1=[-0.06, 0.03],
            k2=[0.01, -0.004],
            k3=[-0.001, 0.0008],
            k4=[0.0002, -0.0001],
            p1=[0.002, -0.0015],
            p2=[-0.001, 0.0025],
        )
    generator = torch.Generator().manual_seed(seed)
    pixels = torch.rand(2, count, 2, generator=generator, dtype=torch.float64)
    pixels = pixels * torch.stack([intrinsics.width, intrinsics.height], dim=-1)[:, None, :]
    pixels[:, 0] = torch.stack([intrinsics.cx, intrinsics.cy], dim=-1)  # on the optical axis
    pixels[:, 1] = pixels[:, 0] + 1e-5  # next to it (Taylor branch of the fisheye)
    depth = 0.4 + 30.0 * torch.rand(2, count, 1, generator=generator, dtype=torch.float64)
    return intrinsics, pixel_to_ray_direction(pixels, intrinsics) * depth


def test_analytic_jacobian_matches_autodiff() -> None:
    intrinsics, points = _camera_and_points(seed=0)
    _, analytic, _ = projection_jacobian(points, intrinsics)
    expected = _autodiff_jacobian(points, intrinsics)[..., list(ParameterLayout().indices)]
    torch.testing.assert_close(analytic, expected, rtol=1e-9, atol=1e-9)


def test_analytic_jacobian_matches_finite_differences() -> None:
    intrinsics, points = _camera_and_points(seed=1, count=32)
    _, analytic, _ = projection_jacobian(points, intrinsics)
    numeric_all = _finite_difference_jacobian(points, intrinsics)
    for column, k in enumerate(ParameterLayout().indices):
        numeric = numeric_all[..., k]
        scale = numeric.abs().max().clamp(min=1.0)
        assert (analytic[..., column] - numeric).abs().max() / scale < 1e-6, f"column {k}"


# Layouts whose columns together cover all 16 parameters for each projection.
COVERING_LAYOUTS = {
    "perspective": ("FULL_OPENCV", "OPENCV_FISHEYE"),  # the second adds the perspective k4 (r^8) column
    "fisheye": ("OPENCV_FISHEYE", "FULL_OPENCV"),  # the second adds the (zero) p1, p2 columns
}


@pytest.mark.parametrize("model", ["perspective", "fisheye"])
def test_every_parameter_matches_autodiff_and_finite_differences(model: str) -> None:
    intrinsics, points = _distorted_camera_and_points(model, seed=11)
    autodiff = _autodiff_jacobian(points, intrinsics)
    numeric = _finite_difference_jacobian(points, intrinsics)
    covered = set()
    for camera_model in COVERING_LAYOUTS[model]:
        layout = ParameterLayout(camera_model=camera_model)
        _, analytic, mask = projection_jacobian(points, intrinsics, layout)
        assert mask.all(), "every point is in the image"
        for column, k in enumerate(layout.indices):
            torch.testing.assert_close(analytic[..., column], autodiff[..., k], rtol=1e-9, atol=1e-7, msg=f"{k}")
            scale = numeric[..., k].abs().max().clamp(min=1.0)
            assert (analytic[..., column] - numeric[..., k]).abs().max() / scale < 1e-6, f"column {k}"
            covered.add(k)
    assert covered == set(range(NUM_CAMERA_PARAMS))
    if model == "fisheye":
        assert (points[..., 2] < 0).any(), "fisheye points must reach past 90 degrees"
        assert autodiff[..., 14:].abs().max() == 0  # no tangential terms in the fisheye model


@pytest.mark.parametrize("preset", ["pose", "pose+focal", "pose+intrinsics"])
def test_layout_selects_columns(preset: str) -> None:
    intrinsics, points = _camera_and_points(seed=2, count=8)
    layout = ParameterLayout.from_preset(preset)
    _, full, _ = projection_jacobian(points, intrinsics)
    _, selected, _ = projection_jacobian(points, intrinsics, layout)
    torch.testing.assert_close(selected, full[..., list(layout.indices)])


def test_mask_drops_points_outside_the_image_and_behind_the_camera() -> None:
    intrinsics = Intrinsics.create(fx=100.0, fy=100.0, cx=50.0, cy=40.0, width=100, height=80)
    points = torch.tensor([[[0.0, 0.0, 1.0], [10.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.1, 0.1, 2.0]]]).double()
    _, jacobian, mask = projection_jacobian(points, intrinsics)
    assert mask.tolist() == [[True, False, False, True]]
    sigma, count = gram_matrix(jacobian, mask, intrinsics.image_scale())
    assert count.tolist() == [2]
    kept = jacobian[0, [0, 3]] / 100.0
    expected = torch.einsum("lik,lij->kj", kept, kept) / 2
    torch.testing.assert_close(sigma[0], expected)


def test_gram_is_a_mean_so_duplicating_points_changes_nothing() -> None:
    intrinsics, points = _camera_and_points(seed=3, count=50)
    _, jacobian, mask = projection_jacobian(points, intrinsics)
    sigma, _ = gram_matrix(jacobian, mask, intrinsics.image_scale())
    doubled = torch.cat([points, points], dim=1)
    _, jacobian2, mask2 = projection_jacobian(doubled, intrinsics)
    sigma2, count2 = gram_matrix(jacobian2, mask2, intrinsics.image_scale())
    torch.testing.assert_close(sigma, sigma2)
    assert (count2 == 100).all()
    assert torch.allclose(sigma, sigma.transpose(1, 2))
    assert (torch.linalg.eigvalsh(sigma) > -1e-12).all()


def test_gram_does_not_depend_on_resolution() -> None:
    intrinsics, points = _camera_and_points(seed=4, count=40)
    _, jacobian, mask = projection_jacobian(points, intrinsics)
    sigma, _ = gram_matrix(jacobian, mask, intrinsics.image_scale())
    half = Intrinsics.create(
        fx=intrinsics.fx / 2,
        fy=intrinsics.fy / 2,
        cx=intrinsics.cx / 2,
        cy=intrinsics.cy / 2,
        width=intrinsics.width / 2,
        height=intrinsics.height / 2,
        skew=intrinsics.skew / 2,
        k1=intrinsics.k1,
        k2=intrinsics.k2,
    )
    _, jacobian_half, mask_half = projection_jacobian(points, half)
    sigma_half, _ = gram_matrix(jacobian_half, mask_half, half.image_scale())
    # Pixel-unit parameters (focal, principal point, skew) scale with the resolution: compare the others.
    keep = [0, 1, 2, 3, 4, 5, 10, 11]  # columns of the default (RADIAL) layout
    torch.testing.assert_close(sigma_half[:, keep][:, :, keep], sigma[:, keep][:, :, keep], rtol=1e-10, atol=1e-12)


def test_empty_camera_gives_zero_gram_not_nan() -> None:
    intrinsics = Intrinsics.create(fx=100.0, fy=100.0, cx=50.0, cy=40.0, width=100, height=80)
    points = torch.tensor([[[0.0, 0.0, -1.0]]]).double()
    _, jacobian, mask = projection_jacobian(points, intrinsics)
    sigma, count = gram_matrix(jacobian, mask, intrinsics.image_scale())
    assert count.item() == 0 and torch.isfinite(sigma).all() and sigma.abs().sum() == 0


def test_relative_gram_error() -> None:
    reference = torch.eye(3, dtype=torch.float64)[None] * 2.0
    assert torch.isclose(relative_gram_error(reference * 1.1, reference), torch.tensor([0.1]).double()).all()


# ----------------------------------------------------------------------------------------------------------------
# Tests added from the mutation-testing run (docs/mutation-testing.md).


def test_gram_is_exactly_symmetric() -> None:
    """Sigma feeds eigh, which reads one triangle: it must be symmetric bit for bit, not only up to rounding."""
    jacobian = torch.randn(3, 64, 2, 7, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    sigma, _ = gram_matrix(jacobian, torch.ones(3, 64, dtype=torch.bool), torch.ones(3, dtype=torch.float64))
    assert torch.equal(sigma, sigma.transpose(-1, -2))


def test_gram_of_a_single_valid_point() -> None:
    # Point 0 has J = [[1, 2, 0], [0, 3, 4]] pixels; image scale 10 -> J / 10; point 1 is masked out.
    jacobian = torch.tensor(
        [[[[1.0, 2.0, 0.0], [0.0, 3.0, 4.0]], [[50.0, 60.0, 70.0], [80.0, 90.0, 99.0]]]], dtype=torch.float64
    )
    sigma, count = gram_matrix(jacobian, torch.tensor([[True, False]]), torch.tensor([10.0], dtype=torch.float64))
    # J^T J = [[1, 2, 0], [2, 13, 12], [0, 12, 16]], divided by 10^2 and by the one valid point.
    expected = torch.tensor([[[1.0, 2.0, 0.0], [2.0, 13.0, 12.0], [0.0, 12.0, 16.0]]], dtype=torch.float64) / 100.0
    torch.testing.assert_close(sigma, expected, atol=1e-15, rtol=0)
    assert count.tolist() == [1]


def test_relative_gram_error_of_float32_inputs_is_computed_in_float64() -> None:
    generator = torch.Generator().manual_seed(1)
    reference = torch.randn(2, 12, 12, generator=generator).float()
    sigma = (reference + 1e-3 * torch.randn(2, 12, 12, generator=generator)).float()
    ref64, sigma64 = reference.double().numpy(), sigma.double().numpy()
    expected = np.linalg.norm(sigma64 - ref64, axis=(1, 2)) / np.linalg.norm(ref64, axis=(1, 2))
    got = relative_gram_error(sigma, reference)
    assert got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-13)
