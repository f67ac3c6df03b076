"""Test-time camera alignment of held-out views, then PSNR / SSIM (/ LPIPS) through the aligned cameras.

Joint refinement leaves the field in its own frame (a similarity, plus what it absorbed of the camera errors), while
held-out cameras are given in the reference frame. CamP's protocol, the same for every model, aligns each test
camera against the frozen field:

1. map it into the field's frame by the similarity (Umeyama) taking the reference training-camera centres onto the
   refined ones, and scale its focal length by the median refined / reference focal ratio of the training cameras;
2. ``steps`` seeded Adam steps on a local se(3) twist (c2w' = c2w exp(xi)) and a log focal scale, minimising the
   photometric MSE of the test image;
3. render the full image through the aligned camera and compute the metrics (PSNR also before step 2).

Only rendering through (twist, log focal) differs per model: ``ray_alignment`` for ray (nerfacto) models, ``rays``
random pixels per step; ``splat_alignment`` for S2CamP's splat models, the whole (undistorted) image per step. Other
splatfacto models are refused (use ns-eval).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.alignment import Similarity, umeyama
from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.validation import check_positive_int, check_range
from s2camp_ns.scripts.alignment_camera import HeldOutView, scale_focal
from s2camp_ns.scripts.ray_alignment import RayRenderer


@dataclass(frozen=True)
class AlignmentConfig:
    """Camera-only optimisation of a held-out view against a frozen radiance field."""

    steps: int = 100
    """Adam steps per test camera; 0 evaluates the similarity-mapped camera as is."""
    rays: int = 256
    """Random pixels of the test image per step (ray models; splat models take every pixel)."""
    lr: float = 1e-3
    """Initial Adam learning rate of the twist (rad, scene units) and of the log focal scale."""
    lr_final: float = 1e-4
    """Learning rate at the last step (exponential decay)."""
    refine_focal: bool = True
    """Also optimise a focal-length scale."""
    seed: int = 0
    """Seed of the pixel sampling."""
    chunk: int = 4096
    """Rays per forward pass when rendering the full image (ray models)."""
    views_per_batch: int = 8
    """Held-out views optimised together (bounds the batch's memory)."""

    def validate(self) -> None:
        check_range("steps", self.steps, low=0)
        check_positive_int("rays", self.rays)
        check_positive_int("chunk", self.chunk)
        check_positive_int("views_per_batch", self.views_per_batch)
        for name in ("lr", "lr_final"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


@dataclass
class AlignedView:
    """One held-out view after alignment: its metrics before and after the camera-only steps."""

    index: int
    psnr: float
    ssim: float
    lpips: float
    psnr_unaligned: float
    """PSNR through the similarity-mapped camera, before the camera-only steps."""
    final_loss: float
    twist: tuple[float, ...] = (0.0,) * 6
    """(rho, omega): the aligned camera is c2w exp(twist) (OpenCV frame) of the mapped one."""
    focal_scale: float = 1.0
    """exp(log focal): the aligned focal lengths over the mapped camera's."""


def frame_similarity(reference_c2w: Float[Tensor, "n 3 4"], refined_c2w: Float[Tensor, "n 3 4"]) -> Similarity:
    """Similarity taking the reference training-camera centres onto the refined ones (reference -> field frame)."""
    return umeyama(reference_c2w[:, :, 3].double(), refined_c2w[:, :, 3].double())


def map_camera(similarity: Similarity, c2w: Float[Tensor, "3 4"]) -> Float[Tensor, "3 4"]:
    """x -> s R x + t applied to a camera: rotation R R_c2w, centre s R c + t."""
    c2w = c2w.double()
    rotation = similarity.rotation.to(c2w) @ c2w[:, :3]
    centre = similarity.scale * similarity.rotation.to(c2w) @ c2w[:, 3] + similarity.translation.to(c2w)
    return torch.cat([rotation, centre[:, None]], dim=-1)


def _image_metrics(model, predicted: Tensor, target: Tensor) -> tuple[float, float, float]:
    """PSNR, SSIM and LPIPS (NaN without LPIPS weights) of [H, W, 3] images in [0, 1]."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    predicted = predicted.clamp(0.0, 1.0)
    mse = torch.mean((predicted - target) ** 2)
    psnr = float(-10.0 * torch.log10(mse.clamp_min(1e-12)))
    pred_nchw, target_nchw = predicted.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
    ssim = float(structural_similarity_index_measure(pred_nchw, target_nchw, data_range=1.0))
    lpips_model = getattr(model, "lpips", None)
    lpips = math.nan
    if lpips_model is not None:
        try:
            lpips = float(lpips_model(target_nchw.to(model.device), pred_nchw.to(model.device)))
        except (OSError, RuntimeError):
            lpips = math.nan
    return psnr, ssim, lpips


Progress = Callable[[int, int], None]
"""``progress(done, total)`` after each unit of work: each view's two renders, each step of a batch."""


def alignment_work(num_views: int, config: AlignmentConfig) -> int:
    """Units of work (``Progress``) of aligning ``num_views`` views."""
    batches = -(-num_views // config.views_per_batch)
    return 2 * num_views + batches * config.steps


class ViewRenderer(Protocol):
    """How a model renders a held-out view through (twist, log focal): ``RayRenderer`` or ``SplatRenderer``."""

    def step_colours(
        self,
        views: list[HeldOutView],
        targets: list[Float[Tensor, "h w 3"]],
        twists: list[Tensor],
        log_focals: list[Tensor],
        generators: list[torch.Generator],
    ) -> list[tuple[Tensor, Tensor]]:
        """(predicted, target) colours [k, 3] of each view for one Adam step, differentiable in the variables."""
        ...

    def image(self, view: HeldOutView, width: int, height: int, twist: Tensor, log_focal: Tensor) -> Tensor:
        """The full image [height, width, 3] (float32, CPU) through the view's camera moved by the variables."""
        ...


def renderer_for(model, config: AlignmentConfig) -> ViewRenderer:
    """``SplatRenderer`` for S2CamP's splat model, ``RayRenderer`` for other (nerfacto) models; ValueError for
    another splatfacto model."""
    from nerfstudio.models.splatfacto import SplatfactoModel

    from s2camp_ns.method.splat_model import S2CampSplatModel

    if isinstance(model, S2CampSplatModel):
        from s2camp_ns.scripts.splat_alignment import SplatRenderer

        return SplatRenderer(model)
    if isinstance(model, SplatfactoModel):
        raise ValueError(
            f"s2camp-eval's test-time camera alignment supports S2CamP's splat model (s2camp-splat, "
            f"s2camp-splat-so3xr3) and nerfacto models; the model of this run is {type(model).__name__}, a "
            "splatfacto model it does not support: use ns-eval"
        )
    return RayRenderer(model, rays=config.rays, chunk=config.chunk)


def align_and_evaluate_views(
    model,
    views: list[HeldOutView],
    config: AlignmentConfig,
    progress: Progress | None = None,
    view_done: Callable[[AlignedView], None] | None = None,
) -> list[AlignedView]:
    """Align held-out views to the frozen ``model`` and evaluate them, ``config.views_per_batch`` at a time (each
    follows exactly the steps it would alone: own variables and pixel stream, elementwise Adam); ``view_done`` is
    called with each view's result as its batch ends."""
    config.validate()
    renderer = renderer_for(model, config)
    total, done = alignment_work(len(views), config), 0

    def advance() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    step, results = config.views_per_batch, []
    for start in range(0, len(views), step):
        for aligned in _align_batch(model, renderer, views[start : start + step], config, advance):
            results.append(aligned)
            if view_done is not None:
                view_done(aligned)
    return results


def _target_image(image: Tensor) -> Float[Tensor, "h w 3"]:
    """RGB in [0, 1] (float32, CPU) of a held-out image (float, or uint8 as splatfacto caches them)."""
    rgb = image[..., :3].cpu()
    return rgb.float() / 255.0 if rgb.dtype == torch.uint8 else rgb.float()


def _align_batch(
    model, renderer: ViewRenderer, views: list[HeldOutView], config: AlignmentConfig, advance: Callable[[], None]
) -> list[AlignedView]:
    """``align_and_evaluate_views`` for one batch; ``advance()`` after each unit of work."""
    targets = [_target_image(view.image) for view in views]
    twists = [torch.zeros(6, dtype=torch.float64, requires_grad=True) for _ in views]
    log_focals = [torch.zeros((), dtype=torch.float64, requires_grad=config.refine_focal) for _ in views]
    generators = [torch.Generator().manual_seed(config.seed + 7919 * view.index) for view in views]

    def render_all() -> list[Tensor]:
        images = []
        for view, target, twist, log_focal in zip(views, targets, twists, log_focals, strict=True):
            images.append(renderer.image(view, target.shape[1], target.shape[0], twist, log_focal))
            advance()
        return images

    was_training = model.training
    model.eval()
    frozen = [p for p in model.parameters() if p.requires_grad]
    for parameter in frozen:
        parameter.requires_grad_(False)
    try:
        unaligned = render_all()
        variables = twists + (log_focals if config.refine_focal else [])
        optimizer = torch.optim.Adam(variables, lr=config.lr)
        decay = (config.lr_final / config.lr) ** (1.0 / max(config.steps - 1, 1))
        schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=decay)
        losses = [math.nan] * len(views)
        for _ in range(config.steps):
            pairs = renderer.step_colours(views, targets, twists, log_focals, generators)
            per_view = [torch.mean((predicted - target) ** 2) for predicted, target in pairs]
            optimizer.zero_grad(set_to_none=True)
            torch.stack(per_view).sum().backward()
            optimizer.step()
            schedule.step()
            losses = [float(loss.detach()) for loss in per_view]
            advance()
        aligned = render_all()
    finally:
        for parameter in frozen:
            parameter.requires_grad_(True)
        model.train(was_training)
    results = []
    for view, target, before, after, loss, twist, log_focal in zip(
        views, targets, unaligned, aligned, losses, twists, log_focals, strict=True
    ):
        psnr_unaligned = _image_metrics(model, before, target)[0]
        psnr, ssim, lpips = _image_metrics(model, after, target)
        found = tuple(float(value) for value in twist.detach())
        scale = float(torch.exp(log_focal.detach()))
        results.append(AlignedView(view.index, psnr, ssim, lpips, psnr_unaligned, loss, found, scale))
    return results


def _ray_held_out_views(dataset) -> list[tuple[Tensor, Float[Tensor, "3 4"], Intrinsics]]:
    """(image, OpenGL c2w, intrinsics) of every evaluation image: the evaluation split's reference cameras where
    the dataparser provides them, else the cameras as given."""
    from s2camp_ns.data.camera_conversion import intrinsics_from_cameras

    cameras = (getattr(dataset, "metadata", None) or {}).get("reference_cameras")
    if cameras is None or cameras.shape[0] != len(dataset):
        cameras = dataset.cameras
    return [
        (dataset[i]["image"], cameras.camera_to_worlds[i].cpu(), intrinsics_from_cameras(cameras[i : i + 1]))
        for i in range(len(dataset))
    ]


def evaluate_held_out_views(
    pipeline,
    config: AlignmentConfig = AlignmentConfig(),
    progress: Progress | None = None,
    view_done: Callable[[AlignedView], None] | None = None,
) -> list[AlignedView]:
    """Align and evaluate every evaluation image of a pipeline with an S2CamP model, in the frame of the reference
    training cameras (else the given ones); ``view_done`` as in ``align_and_evaluate_views``."""
    model = pipeline.model
    renderer = renderer_for(model, config)  # refuses a model it cannot render before any work
    splat = not isinstance(renderer, RayRenderer)
    refined_c2w, refined_fx = model.refined_train_cameras()
    reference = model.reference_cameras()
    base = reference if reference is not None else model._train_cameras
    reference_c2w = base.camera_to_worlds.to(torch.float64).cpu()
    reference_fx = base.fx.reshape(-1).to(torch.float64).cpu()
    # A splat model's reference focal lengths are the undistorted images' (``set_undistortion_scale``).
    similarity = frame_similarity(reference_c2w, refined_c2w)
    focal_ratio = float(torch.median(refined_fx / reference_fx))
    if splat:
        from s2camp_ns.scripts.splat_alignment import splat_held_out_views

        held_out = splat_held_out_views(pipeline.datamanager)
    else:
        held_out = _ray_held_out_views(pipeline.datamanager.eval_dataset)
    views = [
        HeldOutView(image, map_camera(similarity, c2w), scale_focal(intrinsics, focal_ratio), index)
        for index, (image, c2w, intrinsics) in enumerate(held_out)
    ]
    return align_and_evaluate_views(model, views, config, progress, view_done)
