"""Camera errors of the training cameras against the data parser's reference cameras, logged while training.

``camera_errors/*`` (rotation in radians, position in scene units, focal length in px, after a similarity alignment,
``core.alignment.camera_errors``) every ``camera_error_every`` steps on rank 0, and in the metrics of the steps the
trainer logs. The reference cameras are ``metadata["reference_cameras"]``: the unperturbed ones under CamP's
perturbation, else the cameras as given.
"""

from __future__ import annotations

import warnings

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils import comms

from s2camp_ns.core.alignment import camera_errors


class CameraErrorLog:
    """Camera errors of an S2CamP model (before ``CameraOptimizerHooks`` in the bases, whose
    ``refined_train_cameras`` it reads); the model's config has ``camera_error_every``."""

    _camera_errors: dict[str, float] = {}
    """The last ``update_camera_errors`` (replaced, never changed in place)."""

    def reference_cameras(self) -> Cameras | None:
        """The data parser's reference training cameras (``metadata["reference_cameras"]``), if any."""
        metadata = self.kwargs.get("metadata") or {}
        reference = metadata.get("reference_cameras")
        if reference is None or reference.shape[0] != self.num_train_data:
            return None
        return reference

    @torch.no_grad()
    def update_camera_errors(self) -> dict[str, float]:
        """``camera_errors/*``: rotation (rad), position (scene units), focal (px) after a similarity alignment;
        empty without reference cameras or before the pipeline handed over the training cameras."""
        reference = self.reference_cameras()
        if reference is None:
            return {}
        try:
            estimated_c2w, estimated_fx = self.refined_train_cameras()
        except RuntimeError:  # no training cameras handed over yet
            return {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            errors = camera_errors(
                estimated_c2w,
                reference.camera_to_worlds.to(torch.float64).cpu(),
                estimated_fx,
                reference.fx.reshape(-1).to(torch.float64).cpu(),
                align=True,
            )
        self._camera_errors = {f"camera_errors/{k}": float(v) for k, v in errors.items()}
        return self._camera_errors

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> list[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        every = self.config.camera_error_every
        if every > 0 and self.reference_cameras() is not None and comms.is_main_process():
            after = TrainingCallbackLocation.AFTER_TRAIN_ITERATION  # nerfstudio calls func(step=step)
            callbacks.append(
                TrainingCallback([after], func=lambda step: self.update_camera_errors(), update_every_num_iters=every)
            )
        return callbacks

    def get_metrics_dict(self, outputs, batch):
        metrics_dict = super().get_metrics_dict(outputs, batch)
        if self.training:
            metrics_dict.update(self._camera_errors)
        return metrics_dict


__all__ = ["CameraErrorLog"]
