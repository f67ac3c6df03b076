"""S2CamP's camera optimizer for nerfstudio: nerfstudio's ``CameraOptimizer`` contract over the framework-free
``CameraRefiner`` (``s2camp_ns.core.refiner``), held as the submodule ``refiner``.

It converts nerfstudio's cameras (``data.camera_conversion``), fits the track prior's anchor
(``core.track_fit``), casts the training rays through the refined cameras (``method.rays``), and after each
optimizer step applies the track prior and removes the common rotation.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Literal, Union

import torch
import tyro
from jaxtyping import Float, Int
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from rich.console import Console
from torch import Tensor, nn

from s2camp_ns.compat import DefaultsOnLoad, refiner_keys
from s2camp_ns.core.anchor_tracks import AnchorTracks, fitted_anchor_tracks
from s2camp_ns.core.camera import PARAMETER_NAMES, ParameterLayout, opengl_to_opencv
from s2camp_ns.core.preconditioner import DampingConfig, SamplingConfig
from s2camp_ns.core.proxy_range import describe_proxy_ranges
from s2camp_ns.core.refiner import CameraRefiner
from s2camp_ns.core.track_fit import TrackEvidence, fit_anchor
from s2camp_ns.core.track_prior import checked_evidence, describe_anchor_fit, evidence_from_fit
from s2camp_ns.core.validation import check_range
from s2camp_ns.data import camera_conversion
from s2camp_ns.method import rays

LOG = Console(stderr=True, width=120)
"""Start-up notes (the proxy range, the anchor fit), on stderr: a caller's stdout (JSON) stays clean."""
TRAIN_CAMERA_KEY = "s2camp_train_camera_index"
"""Cameras metadata key marking a camera as training image i: the model then renders it fully refined."""


@dataclass
class S2CampCameraOptimizerConfig(DefaultsOnLoad, CameraOptimizerConfig):
    """Preconditioned refinement of pose, focal length, principal point, skew and lens distortion (S2CamP)."""

    _target: type = field(default_factory=lambda: S2CampCameraOptimizer)
    mode: Literal["off", "SO3xR3", "SE3"] = "SE3"
    """"off" disables camera refinement; "SE3" refines the local se(3) twist ("SO3xR3", nerfstudio's other name, means
    SE3 here, with a warning: nerfstudio's SO3xR3 optimizer is the method s2camp-so3xr3)."""
    parameters: Literal["pose", "pose+focal", "pose+intrinsics", "all"] = "all"
    """Refined groups: pose; + focal length; + principal point and skew; + the distortion of the cameras' model."""
    intrinsics: Literal["per-camera", "per-image"] = "per-camera"
    """"per-camera": one set per physical camera, shared by its images; "per-image": one per image (CamP's way)."""
    precondition: bool = True
    """Optimize the whitened deltas P phi (paper eq. 15); False optimizes the raw deltas (P = I)."""
    refresh_every: int = 1000
    """Recompute P at the refined intrinsics every this many steps; 0 computes it only at the start."""
    track_prior: bool = True
    """Start each camera where its keypoint tracks put it and hold it by what they know of it (no tracks: as given)."""
    pose_prior_exponent: float = 1.0
    """How firmly the tracks hold each pose, in [0, 1]: 1 their standard error r / sqrt(2 O), 0 their reprojection
    error r (O the image's track observations)."""
    photometric: bool = True
    """Let the images move the cameras. False (with the track prior): the tracks alone place them."""
    fix_common_rotation: bool = True
    """After every step remove the rotation all cameras share: the similarity gauge, which the images cannot see."""
    trans_l2_penalty: float = 0.0
    """L2 penalty on the raw translation delta (scene units); 0: none."""
    rot_l2_penalty: float = 0.0
    """L2 penalty on the raw rotation delta (radians); 0: none."""
    sampling: tyro.conf.Suppress[SamplingConfig] = field(default_factory=SamplingConfig)
    """P's proxy points (``core.preconditioner.SamplingConfig``; ``CAMP_SAMPLING`` is CamP's published sampling)."""
    damping: tyro.conf.Suppress[DampingConfig] = field(default_factory=DampingConfig)
    """Damping of Sigma before P is taken (``core.preconditioner.DampingConfig``; CamP's values)."""

    def validate(self) -> None:
        ParameterLayout.from_preset(self.parameters)
        if self.mode == "SO3xR3":
            warnings.warn(
                "camera-optimizer mode SO3xR3 means SE3 in S2CamP's camera optimizer (it refines the local se(3) "
                "twist, preconditioned); for nerfstudio's own SO3xR3 pose optimizer train s2camp-so3xr3 (or "
                "s2camp-splat-so3xr3)",
                stacklevel=2,
            )
        if not self.photometric and not self.track_prior:
            raise ValueError(
                "camera-optimizer.photometric False places the cameras at the track prior's anchor and needs "
                "camera-optimizer.track-prior True, got track_prior False"
            )
        check_range("pose_prior_exponent", self.pose_prior_exponent, low=0.0, high=1.0)
        check_range("refresh_every", self.refresh_every, low=0)
        self.sampling.validate()
        self.damping.validate()


class S2CampCameraOptimizer(CameraOptimizer):
    """nerfstudio's camera optimizer over a ``CameraRefiner`` (``refiner``): rays, metrics, losses, the after-step
    work and the refresh schedule."""

    config: S2CampCameraOptimizerConfig

    def __init__(
        self,
        config: S2CampCameraOptimizerConfig,
        num_cameras: int,
        device: Union[torch.device, str],
        non_trainable_camera_indices: Int[Tensor, " num_non_trainable_cameras"] | None = None,
        **kwargs,
    ) -> None:
        # Not CameraOptimizer.__init__: its pose_adjustment parameter would never get a gradient and would sit in the
        # "camera_opt" group beside the latents (the gradient scaler then finds no inf checks for it).
        nn.Module.__init__(self)
        config.validate()
        self.config, self.num_cameras, self.device = config, num_cameras, device
        self.refiner = CameraRefiner(
            num_cameras, config.parameters, per_camera_intrinsics=config.intrinsics == "per-camera",
            precondition=config.precondition, sampling=config.sampling, damping=config.damping,
            photometric=config.photometric, enabled=config.mode != "off",
            pose_prior_exponent=config.pose_prior_exponent, frozen_images=non_trainable_camera_indices, device=device,
        )  # fmt: skip
        self.refiner.cameras_required = (
            "S2CampCameraOptimizer.set_train_cameras must be called before use (the pipeline does)"
        )
        self.anchor_tracks: AnchorTracks | None = None
        """The tracks the anchor was fitted to (``set_track_prior``; None: no fit), for the export."""
        self.metrics_due = True
        """Whether ``get_metrics_dict`` computes the metrics: the model sets it before each step to whether the
        trainer logs that step."""
        self._warned_no_pixels = False
        self._register_load_state_dict_pre_hook(refiner_keys, with_module=True)

    @property
    def enabled(self) -> bool:
        return self.refiner.enabled

    # ----------------------------------------------------------------------------------------------------- setup
    def set_train_cameras(self, cameras: Cameras, points: Float[Tensor, "m 3"] | None = None) -> None:
        """The data parser's training cameras and scene points (``metadata["points3D_xyz"]``; None: the fixed proxy
        range): the refiner chooses the range and computes P (``CameraRefiner.set_cameras``)."""
        if cameras.shape[0] != self.num_cameras:
            raise ValueError(f"cameras must hold {self.num_cameras} training cameras, got {cameras.shape[0]}")
        intrinsics = camera_conversion.intrinsics_from_cameras(cameras)
        c2w = opengl_to_opencv(cameras.camera_to_worlds.to(torch.float64))
        groups = camera_conversion.group_identical_intrinsics(cameras)
        chosen = self.refiner.set_cameras(c2w, intrinsics, points, groups)
        if chosen is not None:
            fixed, count = self.config.sampling.fixed_range(), 0 if points is None else points.shape[0]
            LOG.print(describe_proxy_ranges(chosen, count, fixed, self.config.sampling.auto_range.min_points))

    def set_track_prior(
        self,
        track_rms_px: Float[Tensor, " n"] | None,
        evidence: TrackEvidence | None = None,
        track_observations: Float[Tensor, " n"] | None = None,
    ) -> None:
        """The track prior per training image (``core.track_prior``; nothing with ``track_prior`` False). With the data
        parser's ``evidence`` the anchor is where the tracks put each camera (``core.track_fit.fit_anchor``);
        without, the given camera with its reprojection error ``track_rms_px`` (NaN or None: no prior) and its
        ``track_observations``. Call after ``set_train_cameras``."""
        refiner = self.refiner
        refiner.require_cameras()
        prior, self.anchor_tracks = None, None
        if self.config.track_prior and evidence is not None:
            shared = refiner.factorisation == "block"
            fit = fit_anchor(
                evidence.tracks, evidence.c2w, refiner.base_intrinsics_struct(), free=refiner.layout.indices,
                camera_of_image=refiner.camera_of_image if shared else None,
            )  # fmt: skip
            prior = evidence_from_fit(fit, evidence.world_scale, refiner.layout)
            self.anchor_tracks = fitted_anchor_tracks(evidence, fit, refiner.base_intrinsics_struct())
            if (note := describe_anchor_fit(fit)) is not None:
                LOG.print(note)
        elif self.config.track_prior and track_rms_px is not None:
            prior = checked_evidence(track_rms_px, track_observations, self.num_cameras, refiner.layout)
        refiner.set_track_prior(prior)

    # ------------------------------------------------------------------------------------------------ contract
    def forward(self, indices: Int[Tensor, " camera_indices"]) -> Float[Tensor, "camera_indices 3 4"]:
        """Pose corrections D with c2w_gl' = c2w_gl D (nerfstudio's OpenGL camera frame): what nerfstudio's viewer
        multiplies onto the training-camera frusta it draws."""
        deltas = self.refiner.deltas()[indices.to(self.refiner.precond.device)]
        return camera_conversion.opengl_pose_correction(deltas).to(torch.float32)

    def apply_to_raybundle(self, raybundle: RayBundle) -> None:
        """Cast the training rays through their pixels of the refined cameras (pose and intrinsics,
        ``rays.apply_pixel_rays``); rays without pixels (a stock data manager) follow the pose only."""
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
        """Once: rays without pixel coordinates follow the pose only (the warning names the caller's line)."""
        if not self._warned_no_pixels:
            warnings.warn(
                f"ray bundle carries no '{rays.PIXEL_KEY}' metadata (use S2CampDataManagerConfig): intrinsics "
                "refinement has no effect on these rays, only the pose is refined",
                stacklevel=2,
            )
            self._warned_no_pixels = True

    def apply_to_camera(self, camera: Cameras) -> Tensor:
        """Refined OpenGL c2w [1, 3, 4] of a training camera (metadata "cam_idx", as nerfstudio sets it; used by its
        exporter); other cameras unchanged. ``camera_conversion.refined_nerfstudio_cameras`` also gives the
        intrinsics."""
        if not self.enabled or camera.metadata is None or "cam_idx" not in camera.metadata:
            return camera.camera_to_worlds
        correction = self(torch.tensor([int(camera.metadata["cam_idx"])], dtype=torch.long))
        c2w = camera.camera_to_worlds.reshape(-1, 3, 4)
        return camera_conversion.compose_poses(c2w, correction.to(c2w))

    def get_correction_matrices(self) -> Float[Tensor, "n 3 4"]:
        return self(torch.arange(0, self.num_cameras).long())

    # ------------------------------------------------------------------------------------ after a step, refresh
    def after_step(self, lr: float) -> None:
        """After the optimizers' step of learning rate ``lr``: the track prior's proximal step, then the common
        rotation removed (``fix_common_rotation``). No host read."""
        self.refiner.apply_track_prior(lr)
        if self.config.fix_common_rotation:
            self.refiner.remove_common_motion()

    def refresh_due(self, step: int) -> bool:
        """Whether P is refreshed after ``step`` (every ``refresh_every`` steps, once per step)."""
        every = self.config.refresh_every
        return every > 0 and step > 0 and step % every == 0 and step != self.refiner.last_refresh

    # ---------------------------------------------------------------------------------------- losses, metrics
    def get_loss_dict(self, loss_dict: dict) -> None:
        """Optional L2 penalties on the raw pose deltas (off by default)."""
        if not self.enabled or (self.config.trans_l2_penalty == 0 and self.config.rot_l2_penalty == 0):
            return
        phi = self.refiner.deltas()
        loss_dict["camera_opt_regularizer"] = (
            phi[:, :3].norm(dim=-1).mean() * self.config.trans_l2_penalty
            + phi[:, 3:6].norm(dim=-1).mean() * self.config.rot_l2_penalty
        ).to(torch.float32)

    def get_metrics_dict(self, metrics_dict: dict) -> None:
        """Size of the current deltas (scene units, degrees, pixels), on the steps that log them (``metrics_due``)."""
        if not self.enabled or not self.refiner.has_cameras or not self.metrics_due:
            return
        with torch.no_grad():
            phi = self.refiner.deltas()
            sizes = {"translation": phi[:, :3].norm(dim=-1), "rotation": phi[:, 3:6].norm(dim=-1).rad2deg()}
            for name, size in sizes.items():
                metrics_dict[f"camera_opt_{name}_max"] = size.max().float()
                metrics_dict[f"camera_opt_{name}_mean"] = size.mean().float()
            for name in self.refiner.layout.names[6:]:
                column = PARAMETER_NAMES.index(name)
                metrics_dict[f"camera_opt_{name}_abs_mean"] = phi[:, column].abs().mean().float()


__all__ = ["LOG", "TRAIN_CAMERA_KEY", "S2CampCameraOptimizer", "S2CampCameraOptimizerConfig"]
