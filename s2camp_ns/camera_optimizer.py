"""S2CamP camera optimizer for nerfstudio: the adapter between nerfstudio's ``CameraOptimizer`` contract and the core's
``CameraRefiner`` (``s2camp_ns.core.refiner``: preconditioned pose + intrinsics refinement, paper sec. 4). nerfstudio's
cameras map to the core's explicitly (``s2camp_ns.nerfstudio.camera_conversion``); training rays are regenerated
through each ray's pixel (``s2camp_ns.nerfstudio.rays``), so intrinsics really move the rays, differentiably.

The refiner's parameters and buffers are this module's own, under the same names (one registry, shared): checkpoint
keys, ``named_parameters()``, ``.to(device)`` and DDP see the latent, P, P^-1 and the schedule as they always did.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, Union

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from rich.console import Console
from torch import Tensor, nn

from s2camp_ns.core.camera import PARAMETER_NAMES, Intrinsics, ParameterLayout, opengl_to_opencv
from s2camp_ns.core.config_defaults import DefaultsOnLoad
from s2camp_ns.core.preconditioner import DampingConfig, SamplingConfig
from s2camp_ns.core.proxy_range import ProxyRanges
from s2camp_ns.core.refiner import CameraRefiner, describe_proxy_ranges
from s2camp_ns.core.track_fit import TrackEvidence, fit_anchor
from s2camp_ns.core.track_loss import track_term
from s2camp_ns.core.track_prior import checked_evidence, describe_anchor_fit, evidence_from_fit
from s2camp_ns.core.validation import check_range
from s2camp_ns.nerfstudio import camera_conversion, rays

LOG = Console(stderr=True, width=120)
"""Start-up notes (the chosen proxy range), on stderr: a caller's stdout (``s2camp-bench`` JSON) stays clean."""
TRAIN_CAMERA_KEY = "s2camp_train_camera_index"
"""Cameras metadata key marking a camera as training camera i: the model then renders it fully refined."""


@dataclass
class S2CampCameraOptimizerConfig(DefaultsOnLoad, CameraOptimizerConfig):
    """Preconditioned refinement of pose, focal length, principal point, skew and radial distortion (S2CamP).

    Sampling and damping are the core's own configs (``SamplingConfig``, ``DampingConfig``), nested, so the plugin and
    the framework-agnostic core share one definition of each option and its default.
    """

    _target: type = field(default_factory=lambda: S2CampCameraOptimizer)

    mode: Literal["off", "SO3xR3", "SE3"] = "SE3"
    """"off" disables camera refinement. "SE3" and "SO3xR3" both refine the local se(3) twist of the paper
    (sec. 4, screw-axis form); S2CamP does not use nerfstudio's SO3xR3 split, the value only exists for
    compatibility with nerfstudio's config."""
    parameters: Literal["pose", "pose+focal", "pose+intrinsics", "all"] = "all"
    """Refined parameter groups: se(3) pose; + focal length; + principal point and skew; + the distortion
    coefficients of the cameras' model ("all": k1, k2 for pinhole and radial cameras, K = 12 as in the paper; + p1, p2
    for OPENCV; + k3 for FULL_OPENCV; k1..k4 for OPENCV_FISHEYE)."""
    precondition: bool = True
    """Optimize whitened deltas phi_hat = P phi (paper eqs. 15-20). False optimizes the raw deltas (P = I), the
    "no preconditioning" ablation."""
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    """Where the proxy points go (paper sec. 4): point set, frustum transform, radial measure and contracted range
    (``s2camp_ns.core.preconditioner.SamplingConfig``). The range is chosen per physical camera from the scene's
    points unless set, e.g. ``--pipeline.model.camera-optimizer.sampling.t-far 1.8``."""
    damping: DampingConfig = field(default_factory=DampingConfig)
    """Diagonal damping added to Sigma before its square root (``s2camp_ns.core.preconditioner.DampingConfig``)."""
    intrinsics: Literal["per-camera", "per-image"] = "per-camera"
    """"per-camera": one set of intrinsics per physical camera, shared by all its images (the dataparser's
    ``metadata["camera_ids"]``: COLMAP's camera_id, or in transforms.json the global intrinsics / each frame's
    own), the pose per image; the preconditioner is the block-triangular factor of ``core.shared_intrinsics``.
    "per-image": intrinsics refined per image (CamP's way), P the symmetric root per image (paper eq. 20)."""
    refresh_every: int = 1000
    """Recompute P from the current refined intrinsics every this many steps; 0 computes it only at the start."""
    trans_l2_penalty: float = 0.0
    """L2 penalty on the raw translation delta (scene units); 0 = none, as in the paper."""
    rot_l2_penalty: float = 0.0
    """L2 penalty on the raw rotation delta (radians); 0 = none, as in the paper."""
    track_prior: bool = True
    """Start each camera where the scene's keypoint tracks put it (a robust camera-only bundle adjustment against their
    points, ``core.track_fit``) and hold it there by what the tracks know of it (``core.track_prior``); cameras
    without tracks start as given. Tracks: the scene's SfM points, re-adjusted with the same robust loss, or tracks
    built from the images (``image_tracks``). ``s2camp-camp`` switches it off (CamP has no prior)."""
    track_loss: bool = False
    """Benchmark candidate: the tracks' robust reprojection cost as a loss term beside the photometric loss, the two
    weighed as log-likelihoods (``s2camp_ns.core.track_loss``); needs the data parser's ``track_evidence``."""
    track_loss_points_free: bool = False
    """Benchmark candidate: the track loss with the 3D points free (each stepped to its optimum every step, so the
    cameras see the joint adjustment's information, ``core.track_loss.refine_points``)."""
    track_prior_intrinsics_only: bool = False
    """Benchmark candidate: the track prior holds the shared intrinsics only (per-camera intrinsics)."""
    pose_prior_exponent: float = 1.0
    """The track prior's hold on each pose: its radius is r_i / (2 O_i)^(e / 2), r_i the image's reprojection error
    and O_i its observations; 1: the standard error of its tracks' fit (the default), 0: the reprojection error r_i,
    which lets the images move a pose sqrt(2 O_i) times further (``core.track_prior``)."""
    photometric: bool = True
    """Let the photometric loss move the cameras. False (with ``track_prior``): every camera with tracks is placed at
    its track prior's anchor (the camera-only adjustment to the tracks, ``core.track_fit``) and stays there, the
    others where they are given: the "tracks alone" baseline, what bundle adjustment gives a user without
    refinement. The latent keeps its gradient, zeroed (Adam then makes no step), so mixed-precision training with
    its gradient scaler runs as for the other settings."""
    fix_common_rotation: bool = True
    """After every step, remove the rotation all training cameras share (the mean over images of the pose update's
    rotation, each in its own frame; ``remove_common_motion``): a common rotation is the similarity gauge in
    disguise, unseen by the photometric loss (a common pitch of cameras on a ring equals moving them all up, a common
    yaw of forward-facing cameras turning the world; docs/DESIGN-NOTES.md sec. 6). On by default;
    off in the ``s2camp-camp`` baseline (CamP's code has no such step) and the photometric-only benchmark rows."""

    def layout(self, camera_model: str = "RADIAL") -> ParameterLayout:
        return ParameterLayout.from_preset(self.parameters, camera_model)

    def validate(self) -> None:
        self.layout()
        if not self.photometric and not self.track_prior:
            raise ValueError(
                "camera-optimizer.photometric False places the cameras at the track prior's anchor and needs "
                "camera-optimizer.track-prior True, got track_prior False"
            )
        check_range("pose_prior_exponent", self.pose_prior_exponent, low=0.0, high=1.0)
        self.sampling.validate()
        self.damping.validate()
        check_range("refresh_every", self.refresh_every, low=0)


def _delegated(target: str) -> property:
    """An attribute of the refiner, read and written through the adapter (``CameraRefiner.<target>``)."""
    return property(
        lambda self: getattr(self.refiner, target),
        lambda self, value: setattr(self.refiner, target, value),
        doc=f"``s2camp_ns.core.refiner.CameraRefiner.{target}``",
    )


def _on_refiner(function: Callable[..., Any]) -> Callable[..., Any]:
    """A method that calls ``function`` (a ``CameraRefiner`` method or a function of one) on the adapter's refiner."""

    @functools.wraps(function)
    def method(self: S2CampCameraOptimizer, *args, **kwargs):
        return function(self.refiner, *args, **kwargs)

    return method


class S2CampCameraOptimizer(CameraOptimizer):
    """nerfstudio's camera optimizer over a ``CameraRefiner``: whitened deltas, their preconditioner and refresh."""

    config: S2CampCameraOptimizerConfig

    def __init__(
        self,
        config: S2CampCameraOptimizerConfig,
        num_cameras: int,
        device: Union[torch.device, str],
        non_trainable_camera_indices: Int[Tensor, " num_non_trainable_cameras"] | None = None,
        **kwargs,
    ) -> None:
        # Skip CameraOptimizer.__init__: it would create a pose_adjustment parameter that never gets a gradient
        # and would sit in the "camera_opt" group (grad-scaler trouble, docs/DESIGN-NOTES.md sec. 9).
        nn.Module.__init__(self)
        config.validate()
        self.config = config
        self.num_cameras = num_cameras
        self.device = device
        refiner = CameraRefiner(
            num_cameras,
            config.parameters,
            per_camera_intrinsics=config.intrinsics == "per-camera",
            precondition=config.precondition,
            sampling=config.sampling,
            damping=config.damping,
            photometric=config.photometric,
            enabled=config.mode != "off",
            frozen_images=non_trainable_camera_indices,
            device=device,
        )
        refiner.cameras_required = (
            "S2CampCameraOptimizer.set_train_cameras must be called before use (the pipeline does)"
        )
        # Not a submodule (its tensors would be listed twice, under "refiner."): its registries are this module's.
        refiner.prior_intrinsics_only = config.track_prior_intrinsics_only
        refiner.pose_prior_exponent = config.pose_prior_exponent
        object.__setattr__(self, "refiner", refiner)
        for registry in ("_parameters", "_buffers", "_non_persistent_buffers_set"):
            object.__setattr__(self, registry, getattr(refiner, registry))
        self._warned_no_pixels = False
        self.metrics_due = True
        """Whether ``get_metrics_dict`` computes the metrics: the model sets it before each training step to whether
        the trainer logs that step."""

    non_trainable_camera_indices = _delegated("frozen_images")
    layout: ParameterLayout = _delegated("layout")
    enabled: bool = _delegated("enabled")
    shared: bool = _delegated("shared")
    projection: str = _delegated("projection")
    proxy_ranges: ProxyRanges | None = _delegated("proxy_ranges")
    groups_known: bool = _delegated("groups_known")
    has_cameras: bool = _delegated("has_cameras")
    has_track_prior: bool = _delegated("has_track_prior")
    num_physical_cameras: int = _delegated("num_physical_cameras")
    preconditioner_is_stale: bool = _delegated("preconditioner_is_stale")
    set_camera_groups = _on_refiner(CameraRefiner.set_camera_groups)
    set_camera_model = _on_refiner(CameraRefiner.set_camera_model)
    base_intrinsics_struct = _on_refiner(CameraRefiner.base_intrinsics_struct)
    prior_anchor_latents = _on_refiner(CameraRefiner.prior_anchor_latents)
    apply_track_prior = _on_refiner(CameraRefiner.apply_track_prior)
    recompute_stale_preconditioner = _on_refiner(CameraRefiner.recompute_stale_preconditioner)
    camera_deltas = _on_refiner(CameraRefiner.deltas)
    cast_rays = _on_refiner(rays.cast_rays)
    train_camera_raybundle = _on_refiner(rays.train_camera_raybundle)
    refine_cameras = _on_refiner(camera_conversion.refined_cameras)

    # ----------------------------------------------------------------------------------------------------- setup
    def set_train_cameras(self, cameras: Cameras, points: Float[Tensor, "m 3"] | None = None) -> None:
        """The dataparser's training cameras and scene points (``metadata["points3D_xyz"]``; None: the fixed proxy
        range) to the refiner, which chooses the range and computes P (``CameraRefiner.set_cameras``)."""
        if cameras.shape[0] != self.num_cameras:
            raise ValueError(f"cameras must hold {self.num_cameras} training cameras, got {cameras.shape[0]}")
        intrinsics = camera_conversion.intrinsics_from_cameras(cameras)
        c2w = opengl_to_opencv(cameras.camera_to_worlds.to(torch.float64))
        groups = camera_conversion.group_identical_intrinsics(cameras)
        chosen = self.refiner.set_cameras(c2w, intrinsics, points, groups)
        if chosen is not None:
            LOG.print(describe_proxy_ranges(chosen, 0 if points is None else points.shape[0], self.config.sampling))

    def set_track_prior(
        self,
        track_rms_px: Float[Tensor, " n"] | None,
        evidence: TrackEvidence | None = None,
        track_observations: Float[Tensor, " n"] | None = None,
    ) -> None:
        """The track prior's anchor and scale per training image (``track_prior=False`` ignores both;
        ``s2camp_ns.core.track_prior``). With ``evidence`` (the data parser's tracks and given cameras) the anchor
        is where the tracks put each camera (``core.track_fit.fit_anchor``) and the scale the reprojection error
        there; without, the given camera and ``track_rms_px`` (NaN or None: no prior), with ``track_observations``
        (tracks per image) for the shared intrinsics' standard error. Call after ``set_train_cameras``."""
        self.refiner.require_cameras()
        prior = None
        if (self.config.track_prior or self.config.track_loss) and evidence is not None:
            fit = fit_anchor(
                evidence.tracks,
                evidence.c2w,
                self.refiner.base_intrinsics_struct(),
                free=self.layout.indices,
                camera_of_image=self.camera_of_image if self.shared else None,
            )
            prior = evidence_from_fit(fit, evidence.world_scale, self.layout) if self.config.track_prior else None
            if self.config.track_loss:
                self.refiner.set_track_term(
                    track_term(
                        evidence, self.refiner.base_intrinsics_struct(), fit.deltas, self.config.track_loss_points_free
                    )
                )
            if (note := describe_anchor_fit(fit)) is not None:
                LOG.print(note)
        elif track_rms_px is not None and self.config.track_prior:
            prior = checked_evidence(track_rms_px, track_observations, self.num_cameras, self.layout)
        self.refiner.set_track_prior(prior)

    def remove_common_motion(self) -> None:
        """With ``fix_common_rotation``: remove the rotation all training cameras share (the gauge,
        ``CameraRefiner.remove_common_motion``); a no-op otherwise."""
        if self.config.fix_common_rotation:
            self.refiner.remove_common_motion()

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ) -> None:
        self.refiner.check_checkpoint_size(state_dict, prefix)
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        recorded = self.refiner.mark_unrecorded_fingerprint(state_dict, prefix, missing_keys)
        self.refiner.after_load()
        if recorded and self.has_cameras:
            self.refiner.check_fingerprint()  # the warning names this line

    # ------------------------------------------------------------------------------------------- refined cameras
    def refined_intrinsics(self, deltas: Tensor | None = None, cameras: Int[Tensor, " m"] | None = None) -> Intrinsics:
        """Phi' = Phi + dPhi of every training camera or of ``cameras`` (``CameraRefiner.refined_intrinsics``)."""
        return self.refiner.refined_intrinsics(deltas, cameras)

    def refined_c2w(
        self, deltas: Tensor | None = None, opengl: bool = False, cameras: Int[Tensor, " m"] | None = None
    ) -> Float[Tensor, "m 3 4"]:
        """c2w' = c2w exp(xi) of every training camera or of ``cameras`` (``CameraRefiner.refined_c2w``)."""
        return self.refiner.refined_c2w(deltas, opengl, cameras)

    def forward(self, indices: Int[Tensor, " camera_indices"]) -> Float[Tensor, "camera_indices 3 4"]:
        """Pose corrections D with c2w_gl' = c2w_gl D (right-multiplied, nerfstudio's OpenGL camera frame).

        This is what nerfstudio's viewer multiplies onto the training-camera frustums it draws.
        """
        deltas = self.camera_deltas()[indices.to(self.precond.device)]
        return camera_conversion.opengl_pose_correction(deltas).to(torch.float32)

    def apply_to_raybundle(self, raybundle: RayBundle) -> None:
        """Replace training rays by rays through the same pixels of the refined cameras (pose AND intrinsics)."""
        if not self.enabled:
            return
        assert raybundle.camera_indices is not None
        pixels = None if raybundle.metadata is None else raybundle.metadata.get(rays.PIXEL_KEY)
        if pixels is not None:
            rays.apply_pixel_rays(self.refiner, raybundle, pixels)
            return
        self._warn_pose_only()
        rays.apply_pose_only(self.refiner, raybundle)

    def _warn_pose_only(self) -> None:
        """Once: rays without pixel coordinates (a stock data manager) follow the pose only."""
        if not self._warned_no_pixels:
            warnings.warn(
                f"ray bundle carries no '{rays.PIXEL_KEY}' metadata (use S2CampDataManagerConfig): intrinsics "
                "refinement has no effect on these rays, only the pose is refined",
                stacklevel=2,
            )
            self._warned_no_pixels = True

    def apply_to_camera(self, camera: Cameras) -> Tensor:
        """Refined OpenGL c2w [1, 3, 4] of a training camera (nerfstudio's contract: used by its exporter).

        Only cameras whose metadata has "cam_idx" (a training-camera index, as nerfstudio sets it) are changed;
        viewer cameras are returned unchanged. ``refine_cameras`` also returns the refined intrinsics.
        """
        if not self.enabled or camera.metadata is None or "cam_idx" not in camera.metadata:
            return camera.camera_to_worlds
        correction = self(torch.tensor([int(camera.metadata["cam_idx"])], dtype=torch.long))
        c2w = camera.camera_to_worlds.reshape(-1, 3, 4)
        return camera_conversion.compose_poses(c2w, correction.to(c2w))

    # ------------------------------------------------------------------------------------------------- refresh
    def refresh(self, step: int, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Recompute P from the current refined intrinsics without moving the cameras (``CameraRefiner.refresh``)."""
        self.refiner.refresh(step, optimizer, stacklevel=2)

    def should_refresh(self, step: int) -> bool:
        every = self.config.refresh_every
        return every > 0 and step > 0 and step % every == 0 and step != self.refiner.last_refresh

    # ---------------------------------------------------------------------------------------- losses, metrics
    def get_loss_dict(self, loss_dict: dict) -> None:
        """The track term (``track_loss``) and optional L2 penalties on the raw pose deltas (off by default)."""
        # nerfacto's rgb_loss is an MSE (Gaussian pixels, eq. 1); splatfacto's main_loss is mostly L1, whose
        # likelihood (Laplace, scale b = the mean absolute error) gives w = b / (6 N sigma_t^2): half eq. 1's factor.
        key, factor = ("rgb_loss", 1.0) if "rgb_loss" in loss_dict else ("main_loss", 0.5)
        if key in loss_dict and (term := self.refiner.track_loss(loss_dict[key], factor)) is not None:
            loss_dict["track_loss"] = term.to(torch.float32)
        if not self.enabled or (self.config.trans_l2_penalty == 0 and self.config.rot_l2_penalty == 0):
            return
        phi = self.camera_deltas()
        loss_dict["camera_opt_regularizer"] = (
            phi[:, :3].norm(dim=-1).mean() * self.config.trans_l2_penalty
            + phi[:, 3:6].norm(dim=-1).mean() * self.config.rot_l2_penalty
        ).to(torch.float32)

    def get_metrics_dict(self, metrics_dict: dict) -> None:
        """Size of the current deltas (raw units: scene units, degrees, pixels), on the steps that log them
        (``metrics_due``: nerfstudio computes a step's metrics every step and writes them every ``steps_per_log``)."""
        if not self.enabled or not self.has_cameras or not self.metrics_due:
            return
        with torch.no_grad():
            phi = self.camera_deltas()
            trans = phi[:, :3].norm(dim=-1)
            rot = torch.rad2deg(phi[:, 3:6].norm(dim=-1))
            metrics_dict["camera_opt_translation_max"] = trans.max().float()
            metrics_dict["camera_opt_translation_mean"] = trans.mean().float()
            metrics_dict["camera_opt_rotation_mean"] = rot.mean().float()
            metrics_dict["camera_opt_rotation_max"] = rot.max().float()
            for name in self.layout.names[6:]:
                column = PARAMETER_NAMES.index(name)
                metrics_dict[f"camera_opt_{name}_abs_mean"] = phi[:, column].abs().mean().float()

    def get_correction_matrices(self):
        return self(torch.arange(0, self.num_cameras).long())


__all__ = ["LOG", "TRAIN_CAMERA_KEY", "S2CampCameraOptimizer", "S2CampCameraOptimizerConfig"]
