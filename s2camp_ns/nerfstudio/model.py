"""Nerfacto with the S2CamP camera optimizer, offline-safe LPIPS and camera-error logging.

Everything but the camera handling is nerfstudio's nerfacto (proposal sampling, field, losses, renderers); the
camera refinement shared with ``s2camp-splat`` (refresh of P, camera errors, viewer panel, several processes) is
``s2camp_ns.nerfstudio.refinement.S2CampRefinementMixin``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig

from s2camp_ns.camera_optimizer import TRAIN_CAMERA_KEY, S2CampCameraOptimizerConfig
from s2camp_ns.nerfstudio.rays import train_camera_raybundle
from s2camp_ns.nerfstudio.refinement import S2CampRefinementMixin, warn_lpips_unavailable


@dataclass
class S2CampModelConfig(NerfactoModelConfig):
    """Nerfacto with preconditioned pose + intrinsics refinement (S2CamP)."""

    _target: type = field(default_factory=lambda: S2CampModel)
    camera_optimizer: CameraOptimizerConfig = field(default_factory=S2CampCameraOptimizerConfig)
    """The S2CamP camera optimizer: which parameters, the preconditioner's proxy points, damping and refresh.
    nerfstudio's own CameraOptimizerConfig (pose only, SO3xR3/SE3) also works: the ``s2camp-so3xr3`` baseline."""
    camera_error_every: int = 100
    """Compute camera errors against the dataparser's reference cameras every this many steps (0 = never);
    skipped when the dataparser provides no reference cameras."""
    viewer_update_period: float = 1.0
    """Seconds between updates of the viewer's S2CamP panel and training-camera frusta (0 = every step; negative =
    no panel). Costs nothing when training without the viewer."""
    stratified_samples: bool = True
    """Jitter the samples along each training ray (nerfacto's stratified sampling). False places them at the bin
    centres: no random numbers in the forward pass, so runs with the same rays agree up to rounding (with
    the data manager's global-batch-sampling, N processes against one, tests/test_distributed.py)."""
    refresh_request_every: int = 10
    """With several processes, the steps at which a refresh of P requested from the viewer is agreed on (an 8-byte
    all-reduce at every multiple of this) and applied by all ranks together. One process applies a request at the
    next step and communicates nothing."""


class S2CampModel(S2CampRefinementMixin, NerfactoModel):
    """Nerfacto whose training rays go through the refined cameras (pose and intrinsics)."""

    config: S2CampModelConfig
    camera_optimizer: CameraOptimizer

    def populate_modules(self):
        try:
            super().populate_modules()
        except (OSError, RuntimeError) as error:
            # Nerfacto builds LPIPS last, right after PSNR; anything failing earlier is a real error.
            if not hasattr(self, "psnr") or hasattr(self, "lpips"):
                raise
            warn_lpips_unavailable(error)
            self.lpips = None
            self.step = 0
        if not self.config.stratified_samples:
            self.proposal_sampler.initial_sampler.train_stratified = False
            self.proposal_sampler.pdf_sampler.train_stratified = False
        self.setup_camera_refinement()

    # ------------------------------------------------------------------------------------------------ rendering
    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box: OrientedBox | None = None) -> dict[str, torch.Tensor]:
        """Render a camera; a training camera marked with TRAIN_CAMERA_KEY is rendered fully refined.

        Marked training cameras use the refined pose, focal, principal point, skew and distortion (rays are built
        by the camera optimizer because nerfstudio's Cameras cannot hold skew). Other cameras (held-out eval
        cameras, viewer and render-path cameras) have no refined parameters and render as given.
        """
        if self.uses_s2camp_optimizer and camera.metadata is not None and TRAIN_CAMERA_KEY in camera.metadata:
            index = int(camera.metadata[TRAIN_CAMERA_KEY])
            ray_bundle = train_camera_raybundle(self.camera_optimizer.refiner, index)
            return self.get_outputs_for_camera_ray_bundle(ray_bundle)
        return super().get_outputs_for_camera(camera, obb_box)
