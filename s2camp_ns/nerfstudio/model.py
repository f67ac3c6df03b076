"""Nerfacto with the S2CamP camera optimizer, offline-safe LPIPS and camera-error logging.

Everything but the camera handling is nerfstudio's nerfacto (proposal sampling, field, losses, renderers).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.utils.rich_utils import CONSOLE

from s2camp_ns.nerfstudio.camera_optimizer import (
    TRAIN_CAMERA_KEY,
    S2CampCameraOptimizer,
    S2CampCameraOptimizerConfig,
)
from s2camp_ns.nerfstudio.viewer_panel import S2CampViewerPanel

_LPIPS_WARNED = False


def _warn_lpips_unavailable(error: BaseException) -> None:
    global _LPIPS_WARNED
    if not _LPIPS_WARNED:
        CONSOLE.print(
            "[bold yellow]LPIPS unavailable: weights not cached and could not be downloaded "
            f"({type(error).__name__}: {error}). PSNR and SSIM are still computed; lpips is omitted from the "
            "metrics. Cache the AlexNet weights (torch hub) to enable it."
        )
        _LPIPS_WARNED = True


@dataclass
class S2CampModelConfig(NerfactoModelConfig):
    """Nerfacto with preconditioned pose + intrinsics refinement (S2CamP)."""

    _target: type = field(default_factory=lambda: S2CampModel)
    camera_optimizer: S2CampCameraOptimizerConfig = field(default_factory=S2CampCameraOptimizerConfig)
    """The S2CamP camera optimizer: which parameters, the preconditioner's proxy points, damping and refresh."""
    camera_error_every: int = 100
    """Compute camera errors against the dataparser's reference cameras every this many steps (0 = never);
    skipped when the dataparser provides no reference cameras."""
    viewer_update_period: float = 1.0
    """Seconds between updates of the viewer's S2CamP panel and training-camera frusta (0 = every step; negative =
    no panel). Costs nothing when training without the viewer."""


class S2CampModel(NerfactoModel):
    """Nerfacto whose training rays go through the refined cameras (pose and intrinsics)."""

    config: S2CampModelConfig
    camera_optimizer: S2CampCameraOptimizer

    def populate_modules(self):
        try:
            super().populate_modules()
        except (OSError, RuntimeError) as error:
            # Nerfacto builds LPIPS last, right after PSNR; anything failing earlier is a real error.
            if not hasattr(self, "psnr") or hasattr(self, "lpips"):
                raise
            _warn_lpips_unavailable(error)
            self.lpips = None
            self.step = 0
        self._camera_errors: dict[str, float] = {}
        # --- S2CamP viewer panel (viewer_panel.py); inert unless nerfstudio's viewer installs it. The attribute name
        # is the panel's folder label in the viewer.
        if self.config.viewer_update_period >= 0:
            self.S2CamP = S2CampViewerPanel(self, update_period=self.config.viewer_update_period)
        # --- end viewer panel

    @property
    def lpips_available(self) -> bool:
        return self.lpips is not None

    # ------------------------------------------------------------------------------------------------- training
    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> list[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        optimizers = training_callback_attributes.optimizers
        camera_optimizer = self.camera_optimizer

        def refresh_preconditioner(step: int) -> None:
            if camera_optimizer.should_refresh(step):
                torch_optimizer = None if optimizers is None else optimizers.optimizers.get("camera_opt")
                camera_optimizer.refresh(step, torch_optimizer)

        if camera_optimizer.enabled and camera_optimizer.config.refresh_every > 0:
            callbacks.append(
                TrainingCallback(
                    where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                    update_every_num_iters=camera_optimizer.config.refresh_every,
                    func=refresh_preconditioner,
                )
            )
        if self.config.camera_error_every > 0 and self.reference_cameras() is not None:
            callbacks.append(
                TrainingCallback(
                    where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                    update_every_num_iters=self.config.camera_error_every,
                    func=lambda step: self.update_camera_errors(),
                )
            )
        # --- S2CamP viewer panel: its callback exists only when the viewer installed the panel
        panel = getattr(self, "S2CamP", None)
        if panel is not None:
            callbacks.extend(panel.training_callbacks(training_callback_attributes))
        # --- end viewer panel
        return callbacks

    # ---------------------------------------------------------------------------------------------- camera errors
    def reference_cameras(self) -> Cameras | None:
        """Unperturbed training cameras from the dataparser (metadata["reference_cameras"]), if any."""
        metadata = self.kwargs.get("metadata") or {}
        reference = metadata.get("reference_cameras")
        if reference is None or reference.shape[0] != self.num_train_data:
            return None
        return reference

    @torch.no_grad()
    def update_camera_errors(self) -> dict[str, float]:
        """Rotation (rad), position (scene units) and focal (px) errors after similarity alignment."""
        reference = self.reference_cameras()
        if reference is None or not self.camera_optimizer.has_cameras:
            return {}
        try:
            from s2camp_ns.core.alignment import camera_errors
        except ImportError:  # the alignment module is optional at this layer
            return {}
        estimated_c2w = self.camera_optimizer.refined_c2w(opengl=True)
        estimated_fx = self.camera_optimizer.refined_intrinsics().fx
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            errors = camera_errors(
                estimated_c2w, reference.camera_to_worlds, estimated_fx, reference.fx.reshape(-1), align=True
            )
        self._camera_errors = {f"camera_errors/{k}": float(v) for k, v in errors.items()}
        return self._camera_errors

    def get_metrics_dict(self, outputs, batch):
        metrics_dict = super().get_metrics_dict(outputs, batch)
        if self.training:
            metrics_dict.update(self._camera_errors)
        return metrics_dict

    # ------------------------------------------------------------------------------------------------ rendering
    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box: OrientedBox | None = None) -> dict[str, torch.Tensor]:
        """Render a camera; a training camera marked with TRAIN_CAMERA_KEY is rendered fully refined.

        Marked training cameras use the refined pose, focal, principal point, skew and distortion (rays are built
        by the camera optimizer because nerfstudio's Cameras cannot hold skew). Other cameras (held-out eval
        cameras, viewer and render-path cameras) have no refined parameters and render as given.
        """
        if camera.metadata is not None and TRAIN_CAMERA_KEY in camera.metadata:
            index = int(camera.metadata[TRAIN_CAMERA_KEY])
            ray_bundle = self.camera_optimizer.train_camera_raybundle(index)
            return self.get_outputs_for_camera_ray_bundle(ray_bundle)
        return super().get_outputs_for_camera(camera, obb_box)

    def get_image_metrics_and_images(
        self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]
    ) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
        if self.lpips_available:
            return super().get_image_metrics_and_images(outputs, batch)
        # Nerfacto always calls self.lpips; give it a stand-in and drop the key (LPIPS is reported unavailable).
        self.lpips = lambda *args: torch.tensor(float("nan"))
        try:
            metrics_dict, images_dict = super().get_image_metrics_and_images(outputs, batch)
        finally:
            self.lpips = None
        metrics_dict.pop("lpips", None)
        return metrics_dict, images_dict
