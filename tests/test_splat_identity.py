"""K' = K A through the view matrix [[A R, A t], [0, 1]] (docs/SPLAT.md): exact renders, and intrinsics gradients
through the view matrix against central finite differences of renders with the refined K."""

from __future__ import annotations

import math

import pytest
import torch
from gsplat.cuda._torch_impl import _fully_fused_projection

from s2camp_ns.splat.intrinsics_view import (
    corrected_viewmat,
    intrinsics_correction,
    intrinsics_matrix,
)
from s2camp_ns.splat.reference_rasterizer import covariances_from, project_gaussians, rasterization

F64 = torch.float64
WIDTH, HEIGHT = 32, 24
BASE = (30.0, 28.0, 16.0, 12.0, 0.0)  # fx, fy, cx, cy, skew of the base camera (nerfstudio's: no skew)
REFINED = (31.5, 27.2, 16.7, 11.6, 0.4)
PARAMETERS = ("fx", "fy", "cx", "cy", "skew")
GRADIENT_TOLERANCE = 1e-4
"""Issue 20's target: relative error of every refined parameter's gradient against finite differences."""


def k_of(values, dtype=F64) -> torch.Tensor:
    fx, fy, cx, cy, skew = (torch.as_tensor(v, dtype=dtype).reshape(1) for v in values)
    return intrinsics_matrix(fx, fy, cx, cy, skew)


def scene(dtype=F64, n: int = 40, seed: int = 3) -> dict:
    """Gaussians in front of a rotated camera; the spread puts some beyond the field-of-view clamp."""
    generator = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=generator, dtype=F64) * torch.tensor([1.2, 0.9, 0.4], dtype=F64)
    means = means + torch.tensor([0.0, 0.0, 2.5], dtype=F64)
    angle = 0.2
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3] = torch.tensor(
        [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]]
    )
    viewmat[:3, 3] = torch.tensor([0.05, -0.1, 0.2])
    return {
        "means": means.to(dtype),
        "quats": torch.randn(n, 4, generator=generator, dtype=F64).to(dtype),
        "scales": (torch.rand(n, 3, generator=generator, dtype=F64) * 0.12 + 0.03).to(dtype),
        "opacities": (torch.rand(n, generator=generator, dtype=F64) * 0.6 + 0.3).to(dtype),
        "colors": (torch.randn(n, 4, 3, generator=generator, dtype=F64) * 0.4).to(dtype),
        "viewmats": viewmat[None].to(dtype),
        "weights": torch.rand(1, HEIGHT, WIDTH, 4, generator=generator, dtype=F64).to(dtype),
    }


def render(s: dict, viewmats: torch.Tensor, ks: torch.Tensor):
    return rasterization(
        s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], viewmats, ks, WIDTH, HEIGHT,
        sh_degree=1, render_mode="RGB+ED", rasterize_mode="antialiased",
    )  # fmt: skip


def loss(s: dict, viewmats: torch.Tensor, ks: torch.Tensor) -> torch.Tensor:
    colors, alphas, _ = render(s, viewmats, ks)
    return (colors * s["weights"]).sum() + alphas.sum()


def test_correction_solves_k_a_equals_refined_k():
    base = k_of((30.0, 28.0, 16.0, 12.0, 0.7))  # a skewed base too: the closed form handles it
    refined = k_of(REFINED)
    a = intrinsics_correction(base, refined)
    torch.testing.assert_close(base @ a, refined, rtol=1e-14, atol=1e-12)
    torch.testing.assert_close(a, torch.linalg.solve(base, refined), rtol=1e-12, atol=1e-14)
    assert a[0, 1, 0] == 0 and a[0, 2, 0] == 0 and a[0, 2, 1] == 0 and a[0, 2, 2] == 1


def test_correction_rejects_non_pinhole_matrices():
    bad = k_of(BASE).clone()
    bad[0, 2, 0] = 0.5
    with pytest.raises(ValueError, match="refined_k must be a pinhole"):
        intrinsics_correction(k_of(BASE), bad)
    with pytest.raises(ValueError, match="base_k must have positive focal"):
        intrinsics_correction(k_of((-30.0, 28.0, 16.0, 12.0, 0.0)), k_of(REFINED))


def test_camera_centre_and_depths_unchanged():
    s = scene()
    viewmat = corrected_viewmat(s["viewmats"], intrinsics_correction(k_of(BASE), k_of(REFINED)))
    torch.testing.assert_close(
        torch.linalg.inv(viewmat)[:, :3, 3], torch.linalg.inv(s["viewmats"])[:, :3, 3], rtol=1e-12, atol=1e-12
    )
    covariances = covariances_from(s["quats"], s["scales"])
    direct = project_gaussians(s["means"], covariances, s["viewmats"], k_of(REFINED), WIDTH, HEIGHT)
    through_a = project_gaussians(s["means"], covariances, viewmat, k_of(BASE), WIDTH, HEIGHT)
    torch.testing.assert_close(through_a["depths"], direct["depths"], rtol=1e-13, atol=1e-13)


def test_render_through_view_matrix_equals_render_with_refined_k():
    """Everything the rasterizer outputs, including Gaussians beyond the field-of-view clamp and the skew."""
    s = scene()
    covariances = covariances_from(s["quats"], s["scales"])
    viewmat = corrected_viewmat(s["viewmats"], intrinsics_correction(k_of(BASE), k_of(REFINED)))
    direct = project_gaussians(s["means"], covariances, s["viewmats"], k_of(REFINED), WIDTH, HEIGHT)
    u, v = direct["means2d"][..., 0], direct["means2d"][..., 1]
    beyond_clamp = (u < -0.15 * WIDTH) | (u > 1.15 * WIDTH) | (v < -0.15 * HEIGHT) | (v > 1.15 * HEIGHT)
    assert int((beyond_clamp & (direct["radii"] > 0)).sum()) >= 1, "the scene must exercise the clamp"
    through_a = project_gaussians(s["means"], covariances, viewmat, k_of(BASE), WIDTH, HEIGHT)
    assert torch.equal(through_a["radii"], direct["radii"])
    for key in ("means2d", "covars2d", "conics", "compensations"):
        torch.testing.assert_close(through_a[key], direct[key], rtol=1e-11, atol=1e-11, msg=key)
    colors_a, alphas_a, _ = render(s, viewmat, k_of(BASE))
    colors_k, alphas_k, _ = render(s, s["viewmats"], k_of(REFINED))
    assert float(alphas_k.amax()) > 0.5
    torch.testing.assert_close(colors_a, colors_k, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(alphas_a, alphas_k, rtol=1e-10, atol=1e-10)


def test_gsplat_projection_through_view_matrix_equals_refined_k():
    """gsplat's own pure-torch projection (CPU): A path = rendering with K'. Skew-free K' only: gsplat ignores
    K[0, 1] in its Jacobian (docs/SPLAT.md sec. 3), which is why the refined skew must travel in A."""
    s = scene(n=300)
    covariances = covariances_from(s["quats"], s["scales"])
    refined = REFINED[:4] + (0.0,)
    viewmat = corrected_viewmat(s["viewmats"], intrinsics_correction(k_of(BASE), k_of(refined)))
    direct = _fully_fused_projection(s["means"], covariances, s["viewmats"], k_of(refined), WIDTH, HEIGHT, 0.3,
                                     calc_compensations=True)  # fmt: skip
    through_a = _fully_fused_projection(s["means"], covariances, viewmat, k_of(BASE), WIDTH, HEIGHT, 0.3,
                                        calc_compensations=True)  # fmt: skip
    radii = direct[0]
    u, v = direct[1][..., 0], direct[1][..., 1]
    beyond_clamp = (u < -0.15 * WIDTH) | (u > 1.15 * WIDTH) | (v < -0.15 * HEIGHT) | (v > 1.15 * HEIGHT)
    assert int((beyond_clamp & (radii > 0)).sum()) >= 1, "the scene must exercise gsplat's clamp"
    assert torch.equal(through_a[0], radii)
    for name, a, b in zip(("means2d", "depths", "conics", "compensations"), through_a[1:], direct[1:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-11, msg=name)


def intrinsics_gradients() -> tuple[torch.Tensor, torch.Tensor]:
    """d loss / d (fx', fy', cx', cy', skew'): by autograd through the view matrix (base K), and by central finite
    differences of renders with the refined K itself (no A anywhere), float64."""
    s = scene()
    theta = torch.tensor(REFINED, dtype=F64, requires_grad=True)
    refined = intrinsics_matrix(*(theta[i : i + 1] for i in range(5)))
    viewmat = corrected_viewmat(s["viewmats"], intrinsics_correction(k_of(BASE), refined))
    (autograd,) = torch.autograd.grad(loss(s, viewmat, k_of(BASE)), theta)
    step = 1e-5
    finite = torch.zeros(5, dtype=F64)
    with torch.no_grad():
        for i in range(5):
            plus, minus = list(REFINED), list(REFINED)
            plus[i] += step
            minus[i] -= step
            finite[i] = (loss(s, s["viewmats"], k_of(plus)) - loss(s, s["viewmats"], k_of(minus))) / (2 * step)
    return autograd, finite


def test_intrinsics_gradient_through_view_matrix_matches_finite_differences():
    autograd, finite = intrinsics_gradients()
    relative = (autograd - finite).abs() / finite.abs()
    report = ", ".join(f"{name} {float(r):.1e}" for name, r in zip(PARAMETERS, relative, strict=True))
    print(f"relative gradient errors (A path vs finite differences of K'): {report}")
    assert bool((finite.abs() > 1e-2).all()), f"every parameter must move the render: {finite.tolist()}"
    assert bool((relative <= GRADIENT_TOLERANCE).all()), report


def test_float32_path_matches_refined_camera():
    """The only inexactness: V' = A [R | t] is rounded to float32 before rendering (docs/SPLAT.md sec. 3)."""
    s = scene(dtype=torch.float32)
    correction = intrinsics_correction(k_of(BASE, torch.float32), k_of(REFINED, torch.float32))
    viewmat = corrected_viewmat(s["viewmats"], correction)
    colors_a, alphas_a, _ = render(s, viewmat, k_of(BASE, torch.float32))
    colors_k, alphas_k, _ = render(s, s["viewmats"], k_of(REFINED, torch.float32))
    difference = max(float((colors_a - colors_k)[..., :3].abs().max()), float((alphas_a - alphas_k).abs().max()))
    print(f"float32: largest colour / alpha difference A path vs K' = {difference:.1e}")
    assert difference < 1e-5


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a real CUDA device (make gpu-check)")
def test_gsplat_cuda_intrinsics_gradient_through_view_matrix():
    """gsplat's CUDA rasterization through V' = [[A R, A t], [0, 1]] with the base K renders as the reference
    rasterizer with K', and its intrinsics gradient (through the view matrix only: gsplat has none for Ks) matches
    the reference's float64 gradient, itself checked against finite differences above."""
    from gsplat import rasterization as gsplat_rasterization

    s64 = scene()
    theta64 = torch.tensor(REFINED, dtype=F64, requires_grad=True)
    refined64 = intrinsics_matrix(*(theta64[i : i + 1] for i in range(5)))
    viewmat64 = corrected_viewmat(s64["viewmats"], intrinsics_correction(k_of(BASE), refined64))
    colors64, alphas64, _ = render(s64, viewmat64, k_of(BASE))
    (expected,) = torch.autograd.grad((colors64 * s64["weights"]).sum() + alphas64.sum(), theta64)

    device = torch.device("cuda")
    s = {k: v.to(device=device, dtype=torch.float32) for k, v in s64.items()}
    theta = torch.tensor(REFINED, dtype=torch.float32, device=device, requires_grad=True)
    refined = intrinsics_matrix(*(theta[i : i + 1] for i in range(5)))
    base = k_of(BASE, torch.float32).to(device)
    viewmat = corrected_viewmat(s["viewmats"], intrinsics_correction(base, refined))
    colors, alphas, _ = gsplat_rasterization(
        s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], viewmat, base, WIDTH, HEIGHT,
        sh_degree=1, render_mode="RGB+ED", rasterize_mode="antialiased",
    )  # fmt: skip
    torch.testing.assert_close(colors.double().cpu(), colors64.detach(), rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(alphas.double().cpu(), alphas64.detach(), rtol=1e-3, atol=1e-4)
    (gradient,) = torch.autograd.grad((colors * s["weights"]).sum() + alphas.sum(), theta)
    relative = (gradient.double().cpu() - expected).abs() / expected.abs()
    report = ", ".join(f"{name} {float(r):.1e}" for name, r in zip(PARAMETERS, relative, strict=True))
    print(f"gsplat CUDA float32 vs reference float64 intrinsics gradient: {report}")
    assert bool((relative < 1e-3).all()), report
