"""The camera optimizer in a nerfstudio model: its set-up, its training cameras and its training callbacks.

``CameraOptimizerHooks`` (before the nerfstudio model class in the bases) sets up S2CamP's camera optimizer from the
data parser's metadata (physical cameras, camera model), takes the training cameras from the pipeline, and adds the
callbacks of a training step: before it, a checkpoint's stale P recomputed and whether the metrics are due; after
it, the track prior's proximal step and the common rotation removed, then P refreshed when due or requested. The
model's config has ``refresh_request_every``.

With several processes every rank refreshes P at the same steps: scheduled refreshes by step number, a refresh
requested from the viewer (rank 0 only) by an all-reduce every ``refresh_request_every`` steps
(``distributed.any_rank``).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from nerfstudio.cameras.camera_optimizers import CameraOptimizer
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from torch import Tensor

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.validation import check_positive_int
from s2camp_ns.method.distributed import any_rank, world_size


class CameraOptimizerHooks:
    """Camera refinement of an S2CamP model; call ``setup_camera_refinement`` at the end of ``populate_modules``."""

    camera_optimizer: CameraOptimizer

    def setup_camera_refinement(self) -> None:
        """State, and the optimizer's physical cameras and camera model (from the data parser's metadata, before the
        optimizers are built)."""
        check_positive_int("refresh_request_every", self.config.refresh_request_every)
        self._refresh_requested = False
        self._train_cameras: Cameras | None = None
        metadata = self.kwargs.get("metadata") or {}
        camera_ids = metadata.get("camera_ids")
        if self.uses_s2camp_optimizer and camera_ids is not None and len(camera_ids) == self.num_train_data:
            self.camera_optimizer.refiner.set_camera_groups(camera_ids)
        if self.uses_s2camp_optimizer and metadata.get("camera_model") is not None:
            self.camera_optimizer.refiner.set_camera_model(metadata["camera_model"])

    @property
    def uses_s2camp_optimizer(self) -> bool:
        """True for S2CamP's camera optimizer, False for nerfstudio's stock one."""
        return isinstance(self.camera_optimizer, S2CampCameraOptimizer)

    def set_train_cameras(
        self,
        cameras: Cameras,
        points: Tensor | None = None,
        track_rms_px: Tensor | None = None,
        track_evidence: TrackEvidence | None = None,
        track_observations: Tensor | None = None,
    ) -> None:
        """Keep the training cameras (the pipeline calls this before loading a checkpoint) and hand them to S2CamP's
        optimizer with the sparse ``points`` (proxy range) and the SfM tracks (track prior: ``track_evidence``, else
        the reprojection RMS ``track_rms_px`` [n] px and the tracks per image ``track_observations`` [n])."""
        self._train_cameras = cameras.to("cpu")
        if self.uses_s2camp_optimizer:
            self.camera_optimizer.set_train_cameras(cameras, points=points)
            self.camera_optimizer.set_track_prior(track_rms_px, track_evidence, track_observations)

    @torch.no_grad()
    def refined_train_cameras(self) -> tuple[Float[Tensor, "n 3 4"], Float[Tensor, " n"]]:
        """OpenGL c2w [n, 3, 4] and fx [n] of the training cameras as the model sees them (float64, CPU); the stock
        optimizer moves rays in the world frame, c2w' = [R_adj R | t + t_adj], and keeps the intrinsics."""
        if self.uses_s2camp_optimizer:
            refiner = self.camera_optimizer.refiner
            return refiner.refined_c2w(opengl=True).cpu(), refiner.refined_intrinsics().fx.cpu()
        if self._train_cameras is None:
            raise RuntimeError("set_train_cameras must be called before refined_train_cameras (the pipeline does)")
        cameras = self._train_cameras
        c2w = cameras.camera_to_worlds.to(torch.float64)
        if self.camera_optimizer.config.mode != "off":
            indices = torch.arange(c2w.shape[0], device=self.device)
            adjustment = self.camera_optimizer(indices).to(device="cpu", dtype=torch.float64)
            c2w = torch.cat([adjustment[:, :, :3] @ c2w[:, :, :3], c2w[:, :, 3:] + adjustment[:, :, 3:]], dim=-1)
        return c2w, cameras.fx.reshape(-1).to(torch.float64)

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> list[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        camera_optimizer = self.camera_optimizer
        if not (isinstance(camera_optimizer, S2CampCameraOptimizer) and camera_optimizer.enabled):
            return callbacks
        optimizers = training_callback_attributes.optimizers
        trainer = training_callback_attributes.trainer
        steps_per_log = trainer.config.logging.steps_per_log if trainer is not None else 1

        def torch_optimizer() -> torch.optim.Optimizer | None:
            return None if optimizers is None else optimizers.optimizers.get("camera_opt")

        def before_camera_step(step: int) -> None:
            camera_optimizer.metrics_due = step % steps_per_log == 0
            # A checkpoint's P for other base cameras, recomputed once Adam's moments are loaded (else a no-op).
            camera_optimizer.refiner.recompute_stale_preconditioner(step, torch_optimizer())

        def after_camera_step(step: int) -> None:
            # The track prior's proximal step at the camera group's lr, then the common rotation removed.
            adam = torch_optimizer()
            camera_optimizer.after_step(0.0 if adam is None else float(adam.param_groups[0]["lr"]))

        def refresh_preconditioner(step: int) -> None:
            # Scheduled and requested refreshes, in the training thread, decided identically on every rank.
            if self.agreed_refresh_request(step) or camera_optimizer.refresh_due(step):
                camera_optimizer.refiner.refresh(step, torch_optimizer())

        before, after = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION, TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        return callbacks + [
            TrainingCallback(where_to_run=[before], func=before_camera_step),
            TrainingCallback(where_to_run=[after], func=after_camera_step),
            TrainingCallback(where_to_run=[after], func=refresh_preconditioner),
        ]

    def request_refresh(self) -> None:
        """Refresh P at the next agreed step (thread-safe; the viewer calls it from rank 0's websocket thread)."""
        self._refresh_requested = True

    def agreed_refresh_request(self, step: int) -> bool:
        """Whether every rank applies a requested refresh of P after ``step`` (the same answer on all): one process
        at once; several at multiples of ``refresh_request_every``, by an all-reduce (MAX) of the pending flags."""
        if world_size() > 1 and step % self.config.refresh_request_every != 0:
            return False
        requested, self._refresh_requested = self._refresh_requested, False
        return any_rank(requested, self.device)


__all__ = ["CameraOptimizerHooks"]
