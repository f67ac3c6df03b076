"""What the S2CamP models share, whatever renders them (nerfacto: ``model.py``, splatfacto: ``splat_model.py``).

``S2CampRefinementMixin`` (before the nerfstudio model class in the bases) adds: the camera optimizer's set-up from
the dataparser's metadata, the training cameras, P's refreshes, camera errors against the reference cameras, the
viewer panel's ``CameraRefinementSource`` and offline-safe LPIPS. The model's config must have ``camera_error_every``,
``viewer_update_period`` and ``refresh_request_every``.

With several processes every rank refreshes P at the same steps: scheduled refreshes by step number, a refresh
requested from the viewer (rank 0 only) by an all-reduce every ``refresh_request_every`` steps. Camera errors are
computed on rank 0 only.
"""

from __future__ import annotations

import time
import warnings

import torch
import torch.distributed as dist
from jaxtyping import Float
from nerfstudio.cameras.camera_optimizers import CameraOptimizer
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer
from s2camp_ns.core.camera import opengl_to_opencv, vertical_field_of_view
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.validation import check_positive_int
from s2camp_ns.nerfstudio.camera_conversion import intrinsics_from_cameras
from s2camp_ns.nerfstudio.viewer_panel import CameraFrusta, FrustumSet, RefinementStatus, S2CampViewerPanel

_LPIPS_WARNED = False


def warn_lpips_unavailable(error: BaseException) -> None:
    global _LPIPS_WARNED
    if not _LPIPS_WARNED:
        CONSOLE.print(
            "[bold yellow]LPIPS unavailable: weights not cached and could not be downloaded "
            f"({type(error).__name__}: {error}). PSNR and SSIM are still computed; lpips is omitted from the "
            "metrics. Cache the AlexNet weights (torch hub) to enable it."
        )
        _LPIPS_WARNED = True


def world_size() -> int:
    """Number of training processes (1 without a process group)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def any_rank(flag: bool, device: torch.device | str) -> bool:
    """True on every rank if ``flag`` is on any rank: one all-reduce (MAX); ``flag`` itself without a process
    group. ``device``: the rank's own device under NCCL, the CPU under gloo."""
    if world_size() == 1:
        return flag
    value = torch.tensor([int(flag)], dtype=torch.int64, device=device)
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item())


class S2CampRefinementMixin:
    """Camera refinement of an S2CamP model; call ``setup_camera_refinement`` at the end of ``populate_modules``."""

    camera_optimizer: CameraOptimizer

    def setup_camera_refinement(self) -> None:
        """State, the optimizer's physical cameras and camera model (from the dataparser's metadata, before the
        optimizers are built), and the viewer panel."""
        check_positive_int("refresh_request_every", self.config.refresh_request_every)
        self._camera_errors: dict[str, float] = {}
        self._refresh_requested = False
        self._train_cameras: Cameras | None = None
        metadata = self.kwargs.get("metadata") or {}
        camera_ids = metadata.get("camera_ids")
        if self.uses_s2camp_optimizer and camera_ids is not None and len(camera_ids) == self.num_train_data:
            self.camera_optimizer.refiner.set_camera_groups(camera_ids)
        if self.uses_s2camp_optimizer and metadata.get("camera_model") is not None:
            self.camera_optimizer.refiner.set_camera_model(metadata["camera_model"])
        # The viewer panel, inert unless the viewer installs it; the attribute name is its folder label.
        if self.config.viewer_update_period >= 0 and self.uses_s2camp_optimizer:
            self.S2CamP = S2CampViewerPanel(self, update_period=self.config.viewer_update_period)

    @property
    def lpips_available(self) -> bool:
        return self.lpips is not None

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
        return callbacks + self.camera_refinement_callbacks(training_callback_attributes)

    def camera_refinement_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> list[TrainingCallback]:
        """Callbacks of the camera optimizer (stale P, refreshes, after-step), camera errors and the viewer panel."""
        callbacks: list[TrainingCallback] = []
        optimizers = training_callback_attributes.optimizers
        camera_optimizer = self.camera_optimizer

        def refresh_preconditioner(step: int) -> None:
            # Scheduled and requested refreshes, in the training thread, decided identically on every rank.
            if self.agreed_refresh_request(step) or camera_optimizer.refresh_due(step):
                torch_optimizer = None if optimizers is None else optimizers.optimizers.get("camera_opt")
                camera_optimizer.refiner.refresh(step, torch_optimizer)

        def recompute_stale_preconditioner(step: int) -> None:
            # A checkpoint's P for other base cameras, recomputed once Adam's moments are loaded (else a no-op).
            torch_optimizer = None if optimizers is None else optimizers.optimizers.get("camera_opt")
            camera_optimizer.refiner.recompute_stale_preconditioner(step, torch_optimizer)

        def after_camera_step(step: int) -> None:
            # The track prior's proximal step at the camera group's lr, then the common rotation removed.
            torch_optimizer = None if optimizers is None else optimizers.optimizers.get("camera_opt")
            lr = 0.0 if torch_optimizer is None else float(torch_optimizer.param_groups[0]["lr"])
            camera_optimizer.after_step(lr)

        trainer = training_callback_attributes.trainer
        steps_per_log = trainer.config.logging.steps_per_log if trainer is not None else 1

        def before_camera_step(step: int) -> None:
            camera_optimizer.metrics_due = step % steps_per_log == 0
            recompute_stale_preconditioner(step)

        before, after = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION, TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        if isinstance(camera_optimizer, S2CampCameraOptimizer) and camera_optimizer.enabled:
            callbacks += [
                TrainingCallback(where_to_run=[before], func=before_camera_step),
                TrainingCallback(where_to_run=[after], func=after_camera_step),
                TrainingCallback(where_to_run=[after], func=refresh_preconditioner),
            ]
        if self.config.camera_error_every > 0 and self.reference_cameras() is not None and comms.is_main_process():
            every = self.config.camera_error_every  # nerfstudio calls func(step=step)
            callbacks.append(
                TrainingCallback([after], func=lambda step: self.update_camera_errors(), update_every_num_iters=every)
            )
        return callbacks + self.viewer_panel_callbacks()

    def viewer_panel_callbacks(self) -> list[TrainingCallback]:
        """The viewer panel's update after a step, once per update period or at once after a refresh of P (host
        state only: no tensor read); nothing without the viewer."""
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

    # CameraRefinementSource (viewer_panel.py)
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

    def request_refresh(self) -> None:
        self._refresh_requested = True

    def agreed_refresh_request(self, step: int) -> bool:
        """Whether every rank applies a requested refresh of P after ``step`` (the same answer on all): one process
        at once; several at multiples of ``refresh_request_every``, by an all-reduce (MAX) of the pending flags."""
        if world_size() > 1 and step % self.config.refresh_request_every != 0:
            return False
        requested, self._refresh_requested = self._refresh_requested, False
        return any_rank(requested, self.device)

    def reference_cameras(self) -> Cameras | None:
        """The dataparser's unperturbed training cameras (``metadata["reference_cameras"]``), if any."""
        metadata = self.kwargs.get("metadata") or {}
        reference = metadata.get("reference_cameras")
        if reference is None or reference.shape[0] != self.num_train_data:
            return None
        return reference

    @torch.no_grad()
    def update_camera_errors(self) -> dict[str, float]:
        """``camera_errors/*``: rotation (rad), position (scene units), focal (px) after a similarity alignment."""
        reference = self.reference_cameras()
        if reference is None:
            return {}
        from s2camp_ns.core.alignment import camera_errors

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

    def get_metrics_dict(self, outputs, batch):
        metrics_dict = super().get_metrics_dict(outputs, batch)
        if self.training:
            metrics_dict.update(self._camera_errors)
        return metrics_dict

    def get_image_metrics_and_images(
        self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]
    ) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
        if self.lpips_available:
            return super().get_image_metrics_and_images(outputs, batch)
        # nerfacto and splatfacto always call self.lpips: a stand-in, its key dropped.
        self.lpips = lambda *args: torch.tensor(float("nan"))
        try:
            metrics_dict, images_dict = super().get_image_metrics_and_images(outputs, batch)
        finally:
            self.lpips = None
        metrics_dict.pop("lpips", None)
        return metrics_dict, images_dict
