"""An S2CamP model as the viewer panel's data source (``panel.CameraRefinementSource``), and the panel's update.

``ViewerSource`` (before the nerfstudio model class in the bases, after ``CameraErrorLog`` and
``CameraOptimizerHooks``, whose camera errors and refresh requests it serves) declares the panel as the model's
attribute ``S2CamP`` (the viewer's folder label). Once nerfstudio's viewer has attached the panel, a training
callback updates it after a step, once per ``viewer_update_period`` seconds or at once after a refresh of P; it reads
host state only, so a step without an update runs nothing of the panel.
"""

from __future__ import annotations

import time

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation

from s2camp_ns.core.camera import opengl_to_opencv, vertical_field_of_view
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
from s2camp_ns.viewer.panel import CameraFrusta, FrustumSet, RefinementStatus, S2CampViewerPanel


class ViewerSource:
    """The viewer panel of an S2CamP model; call ``setup_viewer_panel`` in ``populate_modules``. The model's config
    has ``viewer_update_period`` (negative: no panel)."""

    def setup_viewer_panel(self) -> None:
        """The panel, inert unless the viewer attaches it; none for nerfstudio's stock camera optimizer."""
        if self.config.viewer_update_period >= 0 and self.uses_s2camp_optimizer:
            self.S2CamP = S2CampViewerPanel(self, update_period=self.config.viewer_update_period)

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> list[TrainingCallback]:
        return super().get_training_callbacks(training_callback_attributes) + self.viewer_panel_callbacks()

    def viewer_panel_callbacks(self) -> list[TrainingCallback]:
        """The panel's update after a step (host state only: no tensor read); nothing without the viewer."""
        panel = getattr(self, "S2CamP", None)
        if panel is None or not panel.attached:
            return []
        refiner = self.camera_optimizer.refiner

        def update_viewer_panel(step: int) -> None:
            if not refiner.has_cameras:
                return  # a pipeline that never handed the training cameras to the camera optimizer
            refreshed = refiner.last_refresh != panel.shown_refresh_step
            if refreshed or time.monotonic() - panel.last_update >= panel.update_period:
                panel.update(step)

        return [
            TrainingCallback(where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION], func=update_viewer_panel)
        ]

    def refinement_status(self) -> RefinementStatus | None:
        optimizer = self.camera_optimizer
        if not self.uses_s2camp_optimizer or not optimizer.refiner.has_cameras:
            return None
        refiner = optimizer.refiner
        preconditioned = optimizer.enabled and optimizer.config.precondition
        computed = preconditioned and refiner.gram_known  # host state: the viewer's check reads no tensor
        return RefinementStatus(
            num_cameras=optimizer.num_cameras,
            refinement_enabled=optimizer.enabled,
            preconditioned=preconditioned,
            last_refresh_step=refiner.last_refresh,
            refresh_every=optimizer.config.refresh_every,
            gram=refiner.gram if computed else None,
            precond_inverse=refiner.precond_inv if computed else None,
        )

    def camera_errors(self) -> dict[str, float]:
        return self.update_camera_errors() if self.reference_cameras() is not None else {}

    @torch.no_grad()
    def camera_frusta(self, which: FrustumSet) -> CameraFrusta | None:
        if not self.uses_s2camp_optimizer or not self.camera_optimizer.refiner.has_cameras:
            return None
        refiner = self.camera_optimizer.refiner
        base = refiner.base_intrinsics_struct()
        if which == "refined":
            deltas = refiner.deltas()
            refined = refiner.refined_intrinsics(deltas)
            fov = vertical_field_of_view(refined)
            return CameraFrusta(refiner.refined_c2w(deltas), fov, refined.width, refined.height)
        if which == "initial":
            return CameraFrusta(refiner.base_c2w_cv, vertical_field_of_view(base), base.width, base.height)
        reference = self.reference_cameras()
        if reference is None:
            return None
        c2w = opengl_to_opencv(reference.camera_to_worlds.to(torch.float64)).cpu()
        fov = vertical_field_of_view(intrinsics_from_cameras(reference.to("cpu"))).cpu()
        same_poses = torch.allclose(c2w, refiner.base_c2w_cv.cpu(), atol=1e-6)
        if same_poses and torch.allclose(fov, vertical_field_of_view(base).cpu()):
            return None
        return CameraFrusta(
            c2w, fov, reference.width.reshape(-1).to(torch.float64), reference.height.reshape(-1).to(torch.float64)
        )


__all__ = ["ViewerSource"]
