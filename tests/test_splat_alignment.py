"""Test-time alignment of held-out views for S2CamP's splat model (s2camp_ns/scripts/splat_alignment.py).

A small S2CampSplatModel (a few hundred Gaussians placed in front of the camera, no training) renders through the
reference rasterizer on the CPU. Target images are rendered through nerfstudio's own view matrix (``get_viewmat``)
and the camera's K, never through the alignment's view matrix.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from conftest import lpips_offline
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.models.splatfacto import SplatfactoModel, get_viewmat

from s2camp_ns.core.camera import Intrinsics, opengl_to_opencv, se3_exp
from s2camp_ns.method.splat_model import S2CampSplatModel, S2CampSplatModelConfig
from s2camp_ns.scripts.alignment_camera import HeldOutView
from s2camp_ns.scripts.splat_alignment import aligned_view_matrix, base_matrix
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig, align_and_evaluate_views, evaluate_held_out_views

F64 = torch.float64


def splat_model(count: int, extent: tuple[float, float, float], seed: int = 0) -> S2CampSplatModel:
    """An S2CampSplatModel (SH degree 0) with ``count`` Gaussians in a box of ``extent`` around the origin: sizes
    0.04-0.08, random orientations, opacities and colours, all from ``seed``; in eval mode."""
    config = S2CampSplatModelConfig(num_random=count, sh_degree=0)
    with lpips_offline():
        model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2,
                             metadata={})  # fmt: skip
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        model.gauss_params["means"].copy_((torch.rand(count, 3, generator=generator) - 0.5) * torch.tensor(extent))
        scales = 0.04 + 0.04 * torch.rand(count, 3, generator=generator)
        model.gauss_params["scales"].copy_(torch.log(scales))
        model.gauss_params["opacities"].copy_(torch.rand(count, 1, generator=generator) * 2.0)
        model.gauss_params["features_dc"].copy_(torch.randn(count, 3, generator=generator) * 1.5)
        model.gauss_params["quats"].copy_(torch.randn(count, 4, generator=generator))
    model.eval()
    return model


def pinhole(focal: float, width: int, height: int) -> Intrinsics:
    return Intrinsics.create(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height)


def c2w_looking_down_z(distance: float) -> torch.Tensor:
    """OpenGL c2w at (0.1, -0.05, distance) looking at -z (towards the Gaussians)."""
    return torch.tensor([[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, -0.05], [0.0, 0.0, 1.0, distance]], dtype=F64)


def render_as_nerfstudio(model, c2w_gl: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    """[H, W, 3] through splatfacto's own view matrix of ``c2w_gl`` and the camera's K (no alignment code)."""
    k = torch.tensor(
        [[float(intrinsics.fx), 0.0, float(intrinsics.cx)], [0.0, float(intrinsics.fy), float(intrinsics.cy)],
         [0.0, 0.0, 1.0]]
    )[None]  # fmt: skip
    width, height = int(intrinsics.width), int(intrinsics.height)
    with torch.no_grad():
        rgb = model.render_view(get_viewmat(c2w_gl.float()[None]), k, width, height)["rgb"]
    return rgb.reshape(height, width, 3).float()


def test_aligned_view_matrix_renders_the_moved_camera_with_the_scaled_focal():
    """A path (base K, view matrix A [R | t]) = the camera c2w exp(twist) rendered with K scaled by exp(log focal),
    the latter built with nerfstudio's view matrix and a scaled K."""
    model = splat_model(120, (2.0, 1.5, 2.0))
    width, height = 40, 30
    intrinsics = pinhole(36.0, width, height)
    c2w = c2w_looking_down_z(3.0)
    twist = torch.tensor([0.02, -0.03, 0.05, 0.01, -0.02, 0.015], dtype=F64)
    log_focal = torch.tensor(0.04, dtype=F64)
    moved_cv = opengl_to_opencv(c2w) @ torch.cat([se3_exp(twist), torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=F64)])
    expected = render_as_nerfstudio(model, opengl_to_opencv(moved_cv), pinhole(36.0 * math.exp(0.04), width, height))
    base_k = base_matrix(intrinsics)
    with torch.no_grad():
        rendered = model.render_view(aligned_view_matrix(c2w, base_k, twist, log_focal), base_k, width, height)
    torch.testing.assert_close(rendered["rgb"].reshape(height, width, 3), expected, atol=1e-5, rtol=0)
    assert float((expected - render_as_nerfstudio(model, c2w, intrinsics)).abs().max()) > 0.1  # the move shows


GRADIENT_POINT = (0.01, -0.02, 0.015, 0.004, -0.006, 0.003, 0.01)
"""Twist (rho, omega) and log focal at which the alignment loss's gradient is checked."""


def alignment_loss_and_gradient_setting():
    """A 40-Gaussian float64 model, a 32 x 24 pinhole view and its target image (nerfstudio's view matrix), and the
    alignment loss MSE(render through (twist, log focal), target) of a model as a function of the 7 variables."""
    model = splat_model(40, (1.2, 1.2, 1.2)).double()
    width, height = 32, 24
    intrinsics = pinhole(30.0, width, height)
    c2w = c2w_looking_down_z(3.0)
    target = render_as_nerfstudio(model, c2w, intrinsics).double()
    base_k = base_matrix(intrinsics)

    def loss(of_model, variables: torch.Tensor) -> torch.Tensor:
        viewmat = aligned_view_matrix(c2w, base_k, variables[:6], variables[6])
        rgb = of_model.render_view(viewmat, base_k, width, height)["rgb"].reshape(height, width, 3)
        return torch.mean((rgb.double().cpu() - target) ** 2)

    return model, loss


def test_alignment_loss_gradients_match_finite_differences():
    """d MSE / d (twist, log focal) by autograd through the reference rasterizer (float64 model) against central
    finite differences (h = 1e-6) of the same loss. 40 Gaussians on 32 x 24 pixels: no alpha / transmittance
    cut-off is crossed within +-h (those steps are invisible to any gradient; a larger scene or step crosses some)."""
    model, loss = alignment_loss_and_gradient_setting()
    at = torch.tensor(GRADIENT_POINT, dtype=F64)
    variables = at.clone().requires_grad_(True)
    (autograd,) = torch.autograd.grad(loss(model, variables), variables)
    step = 1e-6
    with torch.no_grad():
        finite = torch.stack(
            [(loss(model, at + step * e) - loss(model, at - step * e)) / (2 * step) for e in torch.eye(7).double()]
        )
    relative = (autograd - finite).abs() / finite.abs()
    print(f"relative errors of the twist and log-focal gradients: {[f'{float(r):.1e}' for r in relative]}")
    assert bool((finite.abs() > 1e-5).all()), f"every variable must move the loss: {finite.tolist()}"
    assert bool((relative < 1e-6).all()), relative.tolist()  # measured: 4.6e-10 at most


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a real CUDA device (make gpu-check)")
def test_gsplat_cuda_alignment_gradients_match_the_reference():
    """The same loss with the model on CUDA in float32 through gsplat's rasterization (it differentiates the view
    matrix only: the focal scale enters through A): twist and log-focal gradients within 1e-3 of the reference
    rasterizer's float64 ones, themselves checked against finite differences above."""
    model, loss = alignment_loss_and_gradient_setting()
    variables = torch.tensor(GRADIENT_POINT, dtype=F64, requires_grad=True)
    (expected,) = torch.autograd.grad(loss(model, variables), variables)
    model.config.rasterizer = "gsplat"
    on_cuda = model.float().to("cuda")
    (gradient,) = torch.autograd.grad(loss(on_cuda, variables), variables)
    relative = (gradient - expected).abs() / expected.abs()
    print(f"gsplat CUDA float32 vs reference float64 alignment gradients: {[f'{float(r):.1e}' for r in relative]}")
    assert bool((relative < 1e-3).all()), relative.tolist()


def test_splat_alignment_recovers_a_rotated_camera_and_its_focal_length(monkeypatch):
    """Start 0.5 degrees off in rotation and 1% off in focal length; 100 camera-only steps (lr 3e-3) recover both.

    Tolerances: rotation within 0.1 degree, focal scale within 0.3% of 1/1.01, translation within 0.01 (camera 4
    units from the scene centre); with 64 x 48 pixels, rotation against translation and focal against a dolly
    along the axis are only weakly distinguished (the loss is at 1e-6 there already). The model is frozen and
    left as it was, and the model's camera refinement (``view_matrix``) is never used."""
    model = splat_model(400, (3.0, 2.2, 5.0))
    monkeypatch.setattr(model, "view_matrix", lambda camera: pytest.fail("alignment used the camera optimizer"))
    width, height = 64, 48
    focal = 0.9 * width
    truth = c2w_looking_down_z(4.0)
    image = render_as_nerfstudio(model, truth, pinhole(focal, width, height))
    offset = torch.tensor([0.0, 0.0, 0.0, 0.6, 0.8, 0.0], dtype=F64) * math.radians(0.5)
    start_cv = opengl_to_opencv(truth) @ torch.cat([se3_exp(offset), torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=F64)])
    before = [p.detach().clone() for p in model.parameters()]
    start = HeldOutView(image, opengl_to_opencv(start_cv), pinhole(1.01 * focal, width, height), 0)
    view = align_and_evaluate_views(model, [start], AlignmentConfig(steps=100, lr=3e-3))[0]
    twist = torch.tensor(view.twist, dtype=F64)
    rotation_error = math.degrees(float((twist[3:] + offset[3:]).norm()))
    print(f"PSNR {view.psnr_unaligned:.2f} -> {view.psnr:.2f}, rotation error {rotation_error:.4f} deg, focal scale "
          f"{view.focal_scale:.5f} (truth {1 / 1.01:.5f}), translation {float(twist[:3].norm()):.4f}")  # fmt: skip
    assert view.psnr > view.psnr_unaligned + 20.0 and view.psnr > 45.0, (view.psnr_unaligned, view.psnr)
    assert rotation_error < 0.1
    assert view.focal_scale == pytest.approx(1 / 1.01, abs=3e-3)
    assert float(twist[:3].norm()) < 0.01
    assert all(torch.equal(a, b) for a, b in zip(before, model.parameters(), strict=True))
    assert all(p.requires_grad for p in model.gauss_params.values()) and not model.training


def _cameras(c2w: torch.Tensor, focal: list[float], width: int, height: int, distortion=None) -> Cameras:
    return Cameras(
        camera_to_worlds=c2w.float(), fx=torch.tensor(focal)[:, None], fy=torch.tensor(focal)[:, None],
        cx=width / 2, cy=height / 2, width=width, height=height, distortion_params=distortion,
        camera_type=CameraType.PERSPECTIVE,
    )  # fmt: skip


class _EvalDataset:
    def __init__(self, cameras: Cameras, metadata: dict) -> None:
        self.cameras, self.metadata = cameras, metadata

    def __len__(self) -> int:
        return len(self.cameras)


def test_held_out_splat_views_are_splatfactos_images_through_the_reference_cameras():
    """evaluate_held_out_views on an s2camp-splat pipeline (mock data manager, identity frame map): one AlignedView
    per evaluation image, each image the data manager's cached uint8 one, each pose the reference camera's; an image
    the data manager undistorted (given distortion) keeps its undistorted K, any other gets the reference's K. The
    training cameras were undistorted too (fx 36 -> 36.72) and not refined: the focal ratio must be 1, not 1.02."""
    model = splat_model(300, (2.0, 1.5, 2.0))
    width, height = 40, 30
    train_c2w = torch.stack([c2w_looking_down_z(d).float() for d in (3.0, 3.5, 4.0)])
    train = _cameras(train_c2w, [36.0] * 3, width, height)
    undistorted = _cameras(train_c2w, [36.72] * 3, width, height)
    model.refined_train_cameras = lambda: (train_c2w.double(), undistorted.fx.reshape(-1).double())
    model.reference_cameras = lambda: undistorted  # the model's reference in undistorted units (set_undistortion_scale)
    reference_c2w = torch.stack([c2w_looking_down_z(3.0), c2w_looking_down_z(3.4)])
    reference_c2w[1, 0, 3] = -0.2
    given_c2w = reference_c2w.clone()
    given_c2w[:, 2, 3] += 0.3  # SfM's poses: not what the images show
    distortion = torch.tensor([[0.0] * 6, [0.05, 0.0, 0.0, 0.0, 0.0, 0.0]])
    given = _cameras(given_c2w, [35.0, 38.0], width, height, distortion=distortion)  # view 1: K after undistortion
    reference = _cameras(reference_c2w, [37.0, 33.0], width, height)
    shown = [pinhole(37.0, width, height), pinhole(38.0, width, height)]  # the reference K, the undistorted one
    images = [(render_as_nerfstudio(model, reference_c2w[i], shown[i]) * 255).round().to(torch.uint8) for i in range(2)]
    dataset = _EvalDataset(given, {"reference_cameras": reference})
    datamanager = SimpleNamespace(
        cached_eval=[{"image": image} for image in images],
        eval_dataset=dataset,
        train_dataset=SimpleNamespace(cameras=undistorted),
        train_dataparser_outputs=SimpleNamespace(cameras=train),
    )
    views = evaluate_held_out_views(SimpleNamespace(model=model, datamanager=datamanager), AlignmentConfig(steps=0))
    assert [view.index for view in views] == [0, 1]
    for view in views:  # uint8 quantisation only: the start camera is the one that rendered the image
        assert view.psnr == view.psnr_unaligned and view.psnr > 45.0, view


def test_held_out_alignment_refuses_other_splatfacto_models_by_name():
    pipeline = SimpleNamespace(model=object.__new__(SplatfactoModel))
    with pytest.raises(ValueError, match="SplatfactoModel, a splatfacto model it does not support: use ns-eval"):
        evaluate_held_out_views(pipeline)


def test_held_out_splat_camera_must_be_pinhole():
    distorted = Intrinsics.create(fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24, k1=0.1)
    with pytest.raises(ValueError, match="pinhole camera without distortion.*0.1"):
        base_matrix(distorted)
