"""splatfacto with the S2CamP camera optimizer (``ns-train s2camp-splat``): pose, focal, principal point and skew.

nerfstudio 1.1.5's splatfacto, its training views rendered through the refined cameras. gsplat has no gradient for
the intrinsics, so the refined K' enters as the view matrix [[A R, A t], [0, 1]], A = K^-1 K', rendered with the
camera's own K (exact: ``s2camp_ns.splat.intrinsics_view``). Distortion stays fixed: splatfacto trains on
undistorted images, so the cameras are pinhole and ``parameters all`` is refused. Rasterizer: gsplat on CUDA, the
pure-torch ``reference_rasterizer`` elsewhere. What it shares with ``s2camp`` are the bases of ``model.S2CampModel``;
nerfstudio's stock optimizer (``s2camp-splat-so3xr3``) also works.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from gsplat.strategy import DefaultStrategy
from jaxtyping import Float, Int
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.model_components.lib_bilagrid import BilateralGrid
from nerfstudio.models.splatfacto import RGB2SH, SplatfactoModel, SplatfactoModelConfig, get_viewmat
from nerfstudio.utils.colors import get_color
from torch import Tensor

from s2camp_ns.camera_optimizer import TRAIN_CAMERA_KEY, S2CampCameraOptimizerConfig
from s2camp_ns.core.refiner import CameraRefiner
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.data.camera_fields import has_distortion, replace_cameras
from s2camp_ns.method.camera_errors import CameraErrorLog
from s2camp_ns.method.lpips import OptionalLpips, warn_lpips_unavailable
from s2camp_ns.method.model_hooks import CameraOptimizerHooks
from s2camp_ns.splat.intrinsics_view import corrected_viewmat, intrinsics_correction, intrinsics_matrix
from s2camp_ns.splat.reference_rasterizer import rasterization as reference_rasterization
from s2camp_ns.viewer.model_source import ViewerSource

REFUSED_PRESETS = {
    "all": "splatfacto trains on undistorted images, so the distortion stays fixed; use parameters pose+intrinsics"
}
"""Camera-optimizer presets s2camp-splat refuses, and why."""


@dataclass
class S2CampSplatModelConfig(SplatfactoModelConfig):
    """splatfacto with preconditioned pose + intrinsics refinement (S2CamP)."""

    _target: type = field(default_factory=lambda: S2CampSplatModel)
    camera_optimizer: CameraOptimizerConfig = field(
        default_factory=lambda: S2CampCameraOptimizerConfig(parameters="pose+intrinsics")
    )
    """S2CamP's optimizer (``parameters`` pose, pose+focal or pose+intrinsics), or nerfstudio's (pose only)."""
    camera_error_every: int = 100
    """Steps between camera errors against the dataparser's reference cameras (0 = never)."""
    viewer_update_period: float = 1.0
    """Seconds between updates of the viewer's S2CamP panel (0 = every step; negative = no panel)."""
    refresh_request_every: int = 10
    """With several processes, steps between agreements on a refresh of P requested from the viewer."""
    rasterizer: Literal["auto", "gsplat", "reference"] = "auto"
    """"auto": gsplat on CUDA, the pure-torch reference rasterization elsewhere."""


VISER_BACKGROUND = (0.1490, 0.1647, 0.2157)
"""splatfacto's background colour for renders when it trains on random backgrounds (viser's background)."""


def finish_without_lpips(model: SplatfactoModel) -> None:
    """What nerfstudio 1.1.5's ``SplatfactoModel.populate_modules`` builds after LPIPS, built from the model's config
    where LPIPS could not be built (``S2CampSplatModel.populate_modules``): the step, crop box, background colour,
    bilateral grids and gsplat's densification strategy."""
    config = model.config
    model.lpips = None
    model.step = 0
    model.crop_box = None
    random_background = config.background_color == "random"
    model.background_color = torch.tensor(VISER_BACKGROUND) if random_background else get_color(config.background_color)
    if config.use_bilateral_grid:
        shape = config.grid_shape
        model.bil_grids = BilateralGrid(num=model.num_train_data, grid_X=shape[0], grid_Y=shape[1], grid_W=shape[2])
    model.strategy = DefaultStrategy(
        prune_opa=config.cull_alpha_thresh,
        grow_grad2d=config.densify_grad_thresh,
        grow_scale3d=config.densify_size_thresh,
        grow_scale2d=config.split_screen_size,
        prune_scale3d=config.cull_scale_thresh,
        prune_scale2d=config.cull_screen_size,
        refine_scale2d_stop_iter=config.stop_screen_size_at,
        refine_start_iter=config.warmup_length,
        refine_stop_iter=config.stop_split_at,
        reset_every=config.reset_alpha_every * config.refine_every,
        refine_every=config.refine_every,
        pause_refine_after_reset=model.num_train_data + config.refine_every,
        absgrad=config.use_absgrad,
        revised_opacity=False,
        verbose=True,
    )
    model.strategy_state = model.strategy.initialize_state(scene_scale=1.0)


def pinhole_cameras(cameras: Cameras) -> Cameras:
    """The cameras without distortion parameters (splatfacto's data manager keeps them after undistorting)."""
    if cameras.distortion_params is None:
        return cameras
    return replace_cameras(cameras, distortion_params=None)


def world_to_camera(c2w: Float[Tensor, "n 3 4"]) -> Float[Tensor, "n 4 4"]:
    """World-to-camera [n, 4, 4] (the rasterizer's view matrix) of OpenCV camera-to-world matrices."""
    rotation = c2w[:, :, :3].transpose(-1, -2)
    translation = -(rotation @ c2w[:, :, 3:])
    bottom = torch.zeros_like(c2w[:, :1, :])
    bottom[:, 0, 3] = 1.0
    return torch.cat([torch.cat([rotation, translation], dim=-1), bottom], dim=-2)


def refined_view_matrix(
    refiner: CameraRefiner, image: Int[Tensor, " 1"], base_k: Float[Tensor, "1 3 3"]
) -> Float[Tensor, "1 4 4"]:
    """View matrix [[A R', A t'], [0, 1]] (float64) that renders training image ``image``
    with its given ``base_k`` as its refined camera; no host read (``image`` is on the refiner's device)."""
    deltas = refiner.deltas()[image]  # [1, 16]
    c2w = refiner.refined_c2w(deltas, images=image)
    refined = refiner.refined_intrinsics(deltas, images=image)
    refined_k = intrinsics_matrix(refined.fx, refined.fy, refined.cx, refined.cy, refined.skew)
    # Both are pinhole matrices built here: no value check (it would synchronize with the GPU every step).
    correction = intrinsics_correction(base_k.to(refined_k), refined_k, check=False)
    return corrected_viewmat(world_to_camera(c2w), correction)


class S2CampSplatModel(ViewerSource, CameraErrorLog, CameraOptimizerHooks, OptionalLpips, SplatfactoModel):
    """splatfacto whose training views are rendered through the refined cameras (pose and intrinsics)."""

    config: S2CampSplatModelConfig
    camera_optimizer: CameraOptimizer

    def populate_modules(self):
        optimizer_config = self.config.camera_optimizer
        if isinstance(optimizer_config, S2CampCameraOptimizerConfig) and optimizer_config.parameters in REFUSED_PRESETS:
            raise ValueError(
                f"camera-optimizer parameters {optimizer_config.parameters!r} is not supported by s2camp-splat: "
                f"{REFUSED_PRESETS[optimizer_config.parameters]} (allowed: pose, pose+focal, pose+intrinsics)"
            )
        seed_colours = None
        if self.seed_points is not None and not self.config.random_init and not torch.cuda.is_available():
            # splatfacto moves the seed colours to CUDA: hand it the points alone, set the colours below as it would.
            points, seed_colours = self.seed_points
            self.seed_points = (points, seed_colours[:0])
        try:
            super().populate_modules()
        except (OSError, RuntimeError) as error:
            # splatfacto builds LPIPS right after SSIM: anything failing elsewhere is a real error.
            if not hasattr(self, "ssim") or hasattr(self, "lpips"):
                raise
            warn_lpips_unavailable(error)
            finish_without_lpips(self)
        if seed_colours is not None and seed_colours.shape[0] > 0:
            colours = seed_colours.to(torch.float32) / 255
            with torch.no_grad():
                if self.config.sh_degree > 0:
                    self.gauss_params["features_dc"].copy_(RGB2SH(colours))
                else:
                    self.gauss_params["features_dc"].copy_(torch.logit(colours, eps=1e-10))
                self.gauss_params["features_rest"].zero_()
        self.setup_camera_refinement()
        self.setup_viewer_panel()

    def set_train_cameras(
        self,
        cameras: Cameras,
        points: Tensor | None = None,
        track_rms_px: Tensor | None = None,
        track_evidence: TrackEvidence | None = None,
    ) -> None:
        pinhole = pinhole_cameras(cameras)
        # Tracks in distorted images do not fit the undistorted pinhole camera refined here (the pipeline moves them,
        # ``undistorted_tracks``): the prior then keeps its given-camera anchor, with each image's number of tracks.
        evidence, observations = track_evidence, None
        if has_distortion(cameras) and track_evidence is not None:
            image = track_evidence.tracks.image
            evidence, observations = None, torch.bincount(image, minlength=cameras.shape[0]).to(torch.float64)
        super().set_train_cameras(
            pinhole, points=points, track_rms_px=track_rms_px, track_evidence=evidence, track_observations=observations
        )

    def set_undistortion_scale(self, fx_scale: Tensor, fy_scale: Tensor) -> None:
        """Per training image, undistorted over given focal lengths [n]: how ``reference_cameras`` scales the
        reference focal lengths into the refined (undistorted) cameras' units."""
        self._undistortion_scale = (fx_scale.reshape(-1).to(torch.float64), fy_scale.reshape(-1).to(torch.float64))

    def reference_cameras(self) -> Cameras | None:
        """The dataparser's reference training cameras as this model sees them: pinhole, with the undistorted
        images' focal lengths (``set_undistortion_scale``)."""
        reference = super().reference_cameras()
        scale = getattr(self, "_undistortion_scale", None)
        if reference is None or scale is None:
            return reference
        fx_scale, fy_scale = (value.to(reference.fx)[:, None] for value in scale)
        fx, fy = reference.fx * fx_scale, reference.fy * fy_scale
        return replace_cameras(reference, fx=fx, fy=fy, distortion_params=None)

    @torch.no_grad()
    def refined_train_cameras(self) -> tuple[Float[Tensor, "n 3 4"], Float[Tensor, " n"]]:
        """OpenGL c2w and fx of the training cameras as rendered (the stock optimizer: c2w' = c2w [D; 0 0 0 1])."""
        if self.uses_s2camp_optimizer or self.camera_optimizer.config.mode == "off":
            return super().refined_train_cameras()
        if self._train_cameras is None:
            raise RuntimeError("set_train_cameras must be called before refined_train_cameras (the pipeline does)")
        cameras = self._train_cameras
        c2w = cameras.camera_to_worlds.to(torch.float64)
        indices = torch.arange(c2w.shape[0], device=self.device)
        correction = self.camera_optimizer(indices).to(device="cpu", dtype=torch.float64)
        rotation = c2w[:, :, :3] @ correction[:, :, :3]
        translation = c2w[:, :, 3:] + c2w[:, :, :3] @ correction[:, :, 3:]
        return torch.cat([rotation, translation], dim=-1), cameras.fx.reshape(-1).to(torch.float64)

    def view_matrix(self, camera: Cameras) -> Float[Tensor, "1 4 4"]:
        """The view matrix [1, 4, 4] for ``camera``, to be rendered with its own K: refined (``refined_view_matrix``,
        or the stock optimizer's pose) for a training camera (``cam_idx`` while training, or TRAIN_CAMERA_KEY)."""
        metadata = camera.metadata or {}
        index = metadata.get(TRAIN_CAMERA_KEY, metadata.get("cam_idx") if self.training else None)
        if index is None:
            return get_viewmat(camera.camera_to_worlds)
        if not self.uses_s2camp_optimizer:
            return get_viewmat(self.camera_optimizer.apply_to_camera(camera))
        refiner = self.camera_optimizer.refiner
        image = torch.full((1,), int(index), dtype=torch.long, device=refiner.precond.device)
        viewmat = refined_view_matrix(refiner, image, camera.get_intrinsics_matrices().reshape(1, 3, 3))
        return viewmat.to(device=camera.camera_to_worlds.device, dtype=camera.camera_to_worlds.dtype)

    def rasterize(self, means: Tensor, **kwargs):
        """gsplat's rasterization on CUDA, the reference rasterization elsewhere (``rasterizer`` overrides)."""
        choice = self.config.rasterizer
        if choice == "gsplat" or (choice == "auto" and means.is_cuda):
            from gsplat.rendering import rasterization

            return rasterization(means=means, **kwargs)
        return reference_rasterization(means=means, **kwargs)

    def get_outputs(self, camera: Cameras) -> dict[str, Tensor | list]:
        """splatfacto's outputs (rgb, depth, accumulation, background) of one camera through ``view_matrix``."""
        if not isinstance(camera, Cameras):
            raise TypeError(f"get_outputs takes a Cameras object, got {type(camera).__name__}")
        if self.training and camera.shape[0] != 1:
            raise ValueError(f"training renders one camera at a time, got {camera.shape[0]}")
        viewmat = self.view_matrix(camera)
        scale = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / scale)
        ks = camera.get_intrinsics_matrices()
        width, height = int(camera.width.item()), int(camera.height.item())
        camera.rescale_output_resolution(scale)
        return self.render_view(viewmat, ks, width, height, cam_idx=(camera.metadata or {}).get("cam_idx"))

    def render_view(
        self,
        viewmat: Float[Tensor, "1 4 4"],
        ks: Float[Tensor, "1 3 3"],
        width: int,
        height: int,
        cam_idx: int | None = None,
    ) -> dict[str, Tensor | list]:
        """``get_outputs`` for an explicit view matrix and pinhole K, no camera optimizer involved; ``cam_idx``
        selects the bilateral grid while training."""
        params = {name: self.gauss_params[name] for name in self.gauss_params}
        if self.crop_box is not None and not self.training:
            crop = self.crop_box.within(params["means"]).squeeze()
            if int(crop.sum()) == 0:
                return self.get_empty_outputs(width, height, self.background_color)
            params = {name: value[crop] for name, value in params.items()}
        colors = torch.cat([params["features_dc"][:, None, :], params["features_rest"]], dim=1)
        self.last_size = (height, width)
        if self.config.rasterize_mode not in ("antialiased", "classic"):
            raise ValueError(f"rasterize_mode must be 'antialiased' or 'classic', got {self.config.rasterize_mode!r}")
        render_mode = "RGB+ED" if self.config.output_depth_during_training or not self.training else "RGB"
        if self.config.sh_degree > 0:
            sh_degree = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)
        else:
            colors = torch.sigmoid(colors).squeeze(1)
            sh_degree = None
        means = params["means"]
        render, alpha, self.info = self.rasterize(
            means=means,
            quats=params["quats"],
            scales=torch.exp(params["scales"]),
            opacities=torch.sigmoid(params["opacities"]).squeeze(-1),
            colors=colors,
            viewmats=viewmat.to(device=self.device, dtype=means.dtype),
            Ks=ks.to(device=self.device, dtype=means.dtype),
            width=width,
            height=height,
            packed=False,
            near_plane=0.01,
            far_plane=1e10,
            render_mode=render_mode,
            sh_degree=sh_degree,
            sparse_grad=False,
            absgrad=self.strategy.absgrad,
            rasterize_mode=self.config.rasterize_mode,
        )
        if self.training:
            strategy_args = (self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info)
            self.strategy.step_pre_backward(*strategy_args)
        background = self._get_background_color()
        rgb = torch.clamp(render[..., :3] + (1 - alpha) * background, 0.0, 1.0)
        if self.config.use_bilateral_grid and self.training and cam_idx is not None:
            rgb = self._apply_bilateral_grid(rgb, cam_idx, height, width)
        depth = None
        if render_mode == "RGB+ED":
            depth = render[..., 3:4]
            depth = torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
        if background.shape[0] == 3 and not self.training:
            background = background.expand(height, width, 3)
        return {"rgb": rgb.squeeze(0), "depth": depth, "accumulation": alpha.squeeze(0), "background": background}
