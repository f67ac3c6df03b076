"""Analytic Jacobian (paper eq. 4) against torch.func autodiff and finite differences; Gram matrix (eq. 5)."""

from __future__ import annotations

import pytest
import torch
from torch.func import jacrev

from s2camp_ns.core.camera import Intrinsics, ParameterLayout, project_with_delta, unproject
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
    def stacked_projection(delta: torch.Tensor) -> torch.Tensor:
        return project_with_delta(points, intrinsics, delta)

    jacobian = jacrev(stacked_projection)(torch.zeros(intrinsics.num_cameras, 12, dtype=torch.float64))
    # [n, l, 2, n, 12] -> per-camera block [n, l, 2, 12]
    return torch.stack([jacobian[i, :, :, i, :] for i in range(intrinsics.num_cameras)])


def test_analytic_jacobian_matches_autodiff() -> None:
    intrinsics, points = _camera_and_points(seed=0)
    _, analytic, _ = projection_jacobian(points, intrinsics)
    torch.testing.assert_close(analytic, _autodiff_jacobian(points, intrinsics), rtol=1e-9, atol=1e-9)


def test_analytic_jacobian_matches_finite_differences() -> None:
    intrinsics, points = _camera_and_points(seed=1, count=32)
    _, analytic, _ = projection_jacobian(points, intrinsics)
    step = 1e-6
    for k in range(12):
        delta = torch.zeros(2, 12, dtype=torch.float64)
        delta[:, k] = step
        central = project_with_delta(points, intrinsics, delta) - project_with_delta(points, intrinsics, -delta)
        numeric = central / (2 * step)
        scale = numeric.abs().max().clamp(min=1.0)
        assert (analytic[..., k] - numeric).abs().max() / scale < 1e-6, f"column {k}"


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
    keep = [0, 1, 2, 3, 4, 5, 10, 11]
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
