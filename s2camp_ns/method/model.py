"""Nerfacto with the S2CamP camera optimizer (``ns-train s2camp``), its training rays cast through the refined cameras.

Everything but the cameras is nerfstudio's nerfacto. What it shares with ``s2camp-splat``, one job per base:
``CameraOptimizerHooks`` (the camera optimizer's set-up and callbacks), ``CameraErrorLog``, ``ViewerSource`` (the
viewer panel) and ``OptionalLpips``. Their training callbacks run in that order after nerfacto's (each base appends
its own after those of the bases after it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig

from s2camp_ns.camera_optimizer import TRAIN_CAMERA_KEY, S2CampCameraOptimizerConfig
from s2camp_ns.method.camera_errors import CameraErrorLog
from s2camp_ns.method.lpips import OptionalLpips, warn_lpips_unavailable
from s2camp_ns.method.model_hooks import CameraOptimizerHooks
from s2camp_ns.method.rays import train_camera_raybundle
from s2camp_ns.viewer.model_source import ViewerSource


@dataclass
class S2CampModelConfig(NerfactoModelConfig):
    """Nerfacto with preconditioned pose + intrinsics refinement (S2CamP)."""

    _target: type = field(default_factory=lambda: S2CampModel)
    camera_optimizer: CameraOptimizerConfig = field(default_factory=S2CampCameraOptimizerConfig)
    """S2CamP's camera optimizer, or nerfstudio's CameraOptimizerConfig (pose only: the ``s2camp-so3xr3`` baseline)."""
    camera_error_every: int = 100
    """Steps between camera errors against the dataparser's reference cameras (0 = never)."""
    viewer_update_period: float = 1.0
    """Seconds between updates of the viewer's S2CamP panel and frusta (0 = every step; negative = no panel)."""
    stratified_samples: bool = True
    """Jitter the samples along each training ray (nerfacto's); False: bin centres, no random numbers in the
    forward pass."""
    refresh_request_every: int = 10
    """With several processes, steps between agreements (an all-reduce) on a refresh of P requested from the
    viewer; one process applies a request at the next step."""


class S2CampModel(ViewerSource, CameraErrorLog, CameraOptimizerHooks, OptionalLpips, NerfactoModel):
    """Nerfacto whose training rays go through the refined cameras (pose and intrinsics)."""

    config: S2CampModelConfig
    camera_optimizer: CameraOptimizer

    def populate_modules(self):
        try:
            super().populate_modules()
        except (OSError, RuntimeError) as error:
            # Nerfacto builds LPIPS last, right after PSNR: anything failing earlier is a real error.
            if not hasattr(self, "psnr") or hasattr(self, "lpips"):
                raise
            warn_lpips_unavailable(error)
            self.lpips = None
            self.step = 0
        if not self.config.stratified_samples:
            self.proposal_sampler.initial_sampler.train_stratified = False
            self.proposal_sampler.pdf_sampler.train_stratified = False
        self.setup_camera_refinement()
        self.setup_viewer_panel()

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box: OrientedBox | None = None) -> dict[str, torch.Tensor]:
        """Render a camera, fully refined if marked with TRAIN_CAMERA_KEY (rays from the refiner), else as given."""
        if self.uses_s2camp_optimizer and camera.metadata is not None and TRAIN_CAMERA_KEY in camera.metadata:
            index = int(camera.metadata[TRAIN_CAMERA_KEY])
            ray_bundle = train_camera_raybundle(self.camera_optimizer.refiner, index)
            return self.get_outputs_for_camera_ray_bundle(ray_bundle)
        return super().get_outputs_for_camera(camera, obb_box)
