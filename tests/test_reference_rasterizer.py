"""The pure-torch reference rasterization against gsplat's formulas and hand-computed cases.

Projection (means, EWA covariance with the field-of-view clamp, 0.3 px blur, compensation, radii) and spherical
harmonics are compared with gsplat 1.4's own pure-torch helpers (``gsplat.cuda._torch_impl``, which run on the CPU);
compositing with a two-Gaussian scene computed by hand (gsplat's torch compositing needs its CUDA tile kernels).
"""

from __future__ import annotations

import math

import pytest
import torch
from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci, _spherical_harmonics

from s2camp_ns.splat.reference_rasterizer import (
    composite_tile,
    covariances_from,
    project_gaussians,
    rasterization,
    spherical_harmonics,
)

F64 = torch.float64


def random_gaussians(n: int, seed: int = 0, spread: float = 2.0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=generator, dtype=F64) * torch.tensor([spread, spread, 0.5], dtype=F64)
    means = means + torch.tensor([0.0, 0.0, 3.0], dtype=F64)
    quats = torch.randn(n, 4, generator=generator, dtype=F64)
    scales = torch.rand(n, 3, generator=generator, dtype=F64) * 0.15 + 0.01
    return {"means": means, "quats": quats, "scales": scales}


def test_covariances_match_gsplat():
    g = random_gaussians(50)
    expected, _ = _quat_scale_to_covar_preci(g["quats"], g["scales"], compute_preci=False, triu=False)
    torch.testing.assert_close(covariances_from(g["quats"], g["scales"]), expected, rtol=1e-12, atol=1e-14)


def test_projection_matches_gsplat_including_the_clamp():
    g = random_gaussians(400)
    covariances = covariances_from(g["quats"], g["scales"])
    angle = torch.tensor(0.3, dtype=F64)
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3] = torch.tensor(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]], dtype=F64
    )
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=F64)
    ks = torch.tensor([[[60.0, 0.0, 30.0], [0.0, 55.0, 26.0], [0.0, 0.0, 1.0]]], dtype=F64)
    radii, means2d, depths, conics, compensations = _fully_fused_projection(
        g["means"], covariances, viewmat[None], ks, 64, 48, calc_compensations=True
    )
    ours = project_gaussians(g["means"], covariances, viewmat[None], ks, 64, 48)
    # The comparison must exercise the clamp: Gaussians rendered (radius > 0) whose means project more than
    # 0.15 image sizes outside the image, where J uses the clamped position.
    u, v = means2d[..., 0], means2d[..., 1]
    clamped = (u < -0.15 * 64) | (u > 1.15 * 64) | (v < -0.15 * 48) | (v > 1.15 * 48)
    assert int((clamped & (radii > 0)).sum()) >= 3
    assert int((radii > 0).sum()) >= 50
    assert torch.equal(ours["radii"], radii)
    torch.testing.assert_close(ours["means2d"], means2d, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(ours["depths"], depths, rtol=1e-12, atol=1e-12)
    visible = radii > 0
    torch.testing.assert_close(ours["conics"][visible], conics[visible], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(ours["compensations"], compensations, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_spherical_harmonics_match_gsplat(degree: int):
    generator = torch.Generator().manual_seed(degree)
    directions = torch.randn(20, 3, generator=generator, dtype=F64) * 3.0
    coefficients = torch.randn(20, 25, 3, generator=generator, dtype=F64)
    expected = _spherical_harmonics(degree, directions, coefficients)
    torch.testing.assert_close(spherical_harmonics(degree, directions, coefficients), expected, rtol=1e-12, atol=1e-13)


def two_gaussians_on_axis(near_opacity: float, far_opacity: float):
    """Two isotropic Gaussians on the optical axis of a 4 x 4 camera, f = 10, c = (2, 2): the near one at depth 2
    with scale 0.2, the far one at depth 4 with scale 0.4. Both project to (2, 2) with Sigma_2d = (f s / z)^2 I = I,
    1.3 I after the 0.3 px blur. The far one is listed first (compositing must sort by depth)."""
    means = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0]], dtype=F64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]], dtype=F64)
    scales = torch.tensor([[0.4] * 3, [0.2] * 3], dtype=F64)
    opacities = torch.tensor([far_opacity, near_opacity], dtype=F64)
    colors = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64)  # far green, near red
    viewmats = torch.eye(4, dtype=F64)[None]
    ks = torch.tensor([[[10.0, 0.0, 2.0], [0.0, 10.0, 2.0], [0.0, 0.0, 1.0]]], dtype=F64)
    return means, quats, scales, opacities, colors, viewmats, ks


def test_two_gaussians_composited_by_hand():
    near_opacity, far_opacity = 0.6, 0.8
    scene = two_gaussians_on_axis(near_opacity, far_opacity)
    background = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    colors, alphas, info = rasterization(*scene, width=4, height=4, backgrounds=background)
    # Pixel (1, 1) has its centre at (1.5, 1.5): d = (0.5, 0.5), q = 0.5 (0.25 + 0.25) / 1.3 for both Gaussians.
    falloff = math.exp(-0.25 / 1.3)
    a_near, a_far = near_opacity * falloff, far_opacity * falloff
    transmittance = (1 - a_near) * (1 - a_far)
    expected = torch.tensor([a_near, (1 - a_near) * a_far, transmittance], dtype=F64)
    torch.testing.assert_close(colors[0, 1, 1], expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(alphas[0, 1, 1, 0], torch.tensor(1 - transmittance, dtype=F64))
    # Pixel (2, 2), centre (2.5, 2.5): the same distance, the same values (symmetry about the means at (2, 2)).
    torch.testing.assert_close(colors[0, 2, 2], expected, rtol=1e-12, atol=1e-12)
    assert info["radii"].tolist() == [[math.ceil(3 * math.sqrt(1.3))] * 2]
    assert info["width"] == 4 and info["height"] == 4 and info["n_cameras"] == 1


def test_alpha_cap_and_transmittance_stop():
    """Near opacity 1 at its centre: alpha capped at 0.999 (T = 1e-3 after it); the far Gaussian (alpha 0.95)
    would take T to 5e-5 <= 1e-4, so the pixel stops before it and it contributes nothing."""
    means2d = torch.tensor([[0.5, 0.5], [0.5, 0.5]], dtype=F64)
    conics = torch.tensor([[1.0, 0.0, 1.0], [1.0, 0.0, 1.0]], dtype=F64)
    colors = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=F64)
    pixel = torch.tensor([[0.5, 0.5]], dtype=F64)
    out, transmittance = composite_tile(means2d, conics, torch.tensor([1.0, 0.95], dtype=F64), colors, pixel)
    torch.testing.assert_close(out[0], torch.tensor([0.999, 0.0], dtype=F64))
    torch.testing.assert_close(transmittance[0], torch.tensor(1e-3, dtype=F64))
    # With the far alpha at 0.5 the stop is not reached (T = 5e-4): it contributes 0.5 * 1e-3.
    out, transmittance = composite_tile(means2d, conics, torch.tensor([1.0, 0.5], dtype=F64), colors, pixel)
    torch.testing.assert_close(out[0], torch.tensor([0.999, 0.5e-3], dtype=F64))
    torch.testing.assert_close(transmittance[0], torch.tensor(5e-4, dtype=F64))


def test_small_alpha_and_negative_exponent_are_skipped():
    means2d = torch.tensor([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]], dtype=F64)
    # A conic that is not positive definite gives q < 0 at this pixel (skipped, as gsplat does).
    conics = torch.tensor([[1.0, 0.0, 1.0], [-1.0, 0.0, -1.0], [1.0, 0.0, 1.0]], dtype=F64)
    colors = torch.eye(3, dtype=F64)
    pixel = torch.tensor([[1.5, 0.5]], dtype=F64)  # d = (1, 0): q = 0.5 for the first and the last
    opacities = torch.tensor([0.006, 0.5, 0.5], dtype=F64)  # 0.006 e^-0.5 = 0.0036 < 1/255: skipped
    out, transmittance = composite_tile(means2d, conics, opacities, colors, pixel)
    a = 0.5 * math.exp(-0.5)
    torch.testing.assert_close(out[0], torch.tensor([0.0, 0.0, a], dtype=F64))
    torch.testing.assert_close(transmittance[0], torch.tensor(1 - a, dtype=F64))


def test_gaussians_reach_only_the_tiles_of_their_radius():
    """gsplat evaluates a Gaussian only in the 16 x 16 tiles its 3-radius box touches; beyond them it contributes
    nothing even where its alpha exceeds 1/255.

    On the axis of a camera with f = 10, c = (1, 8), depth 2: Sigma_2d = (5 s)^2 + 0.3 = 100 px^2 for
    s^2 = 99.7 / 25, radius ceil(3 sqrt(100 + 0.1)) = 31, so the box ends at x = 32, the first column of tile 2.
    """
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=F64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    scales = torch.full((1, 3), math.sqrt(99.7) / 5, dtype=F64)
    ks = torch.tensor([[[10.0, 0.0, 1.0], [0.0, 10.0, 8.0], [0.0, 0.0, 1.0]]], dtype=F64)
    _, alphas, info = rasterization(
        means, quats, scales, torch.ones(1, dtype=F64), torch.ones(1, 3, dtype=F64), torch.eye(4, dtype=F64)[None], ks,
        width=48, height=16,
    )  # fmt: skip
    assert int(info["radii"][0, 0]) == 31
    # Pixel (31, 8), centre (31.5, 8.5), in tile 1: q = (30.5^2 + 0.5^2) / 200.
    torch.testing.assert_close(alphas[0, 8, 31, 0], torch.tensor(math.exp(-(30.5**2 + 0.25) / 200), dtype=F64))
    # Pixel (32, 8) is in tile 2, outside the box: nothing, although exp(-(31.5^2 + 0.5^2) / 200) = 0.007 > 1/255.
    assert math.exp(-(31.5**2 + 0.25) / 200) > 1 / 255
    assert float(alphas[0, 8, 32, 0]) == 0.0


def test_info_contract_for_the_densification_strategy():
    g = random_gaussians(60, spread=0.5)
    means = g["means"].clone().requires_grad_(True)
    ks = torch.tensor([[[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]]], dtype=F64)
    opacities = torch.full((60,), 0.5, dtype=F64)
    colors = torch.rand(60, 4, 3, dtype=F64)
    image, alphas, info = rasterization(
        means, g["quats"], g["scales"], opacities, colors, torch.eye(4, dtype=F64)[None], ks, 32, 24,
        sh_degree=1, absgrad=True, render_mode="RGB+ED",
    )  # fmt: skip
    assert image.shape == (1, 24, 32, 4) and alphas.shape == (1, 24, 32, 1)
    assert info["means2d"].shape == (1, 60, 2) and info["radii"].shape == (1, 60)
    assert info["radii"].dtype == torch.int32
    info["means2d"].retain_grad()
    image[..., :3].sum().backward()
    grad, absgrad = info["means2d"].grad, info["means2d"].absgrad
    visible = info["radii"] > 0
    assert int(visible.sum()) >= 10
    assert bool((grad[visible].abs().sum(-1) > 0).any())
    # absgrad sums |per-pixel gradients|, so it bounds |sum of them| and exceeds it where signs differ.
    assert bool((absgrad >= grad.abs() - 1e-12).all())
    assert bool((absgrad[visible] > grad.abs()[visible] + 1e-9).any())
    assert float(absgrad[~visible].abs().sum()) == 0.0
