"""S2CamP camera optimizer for nerfstudio: preconditioned pose + intrinsics refinement (paper sec. 4).

The optimizer holds whitened deltas phi_hat [num_cameras, K] (K <= 12, the enabled columns of
``core.camera.ParameterLayout``) and maps them to camera-parameter deltas phi = P^-1 phi_hat (paper eq. 15), with
P = (Sigma + damping)^(1/2) computed from deterministic proxy points in each camera's frustum (paper eq. 20).

Refined camera = base camera from the dataparser plus phi:
- pose: c2w' = c2w exp(xi) with the local twist xi in the OpenCV camera frame (``core.camera`` convention);
  nerfstudio stores OpenGL c2w, c2w_gl = c2w_cv F with F = diag(1, -1, -1);
- intrinsics: additive residual update (paper sec. 4, Phi' = Phi + dPhi) of focal, principal point, skew and the
  distortion coefficients of the cameras' model (``camera_model_of``: RADIAL k1, k2; OPENCV + p1, p2; FULL_OPENCV
  + k3; OPENCV_FISHEYE k1..k4), so K is 12, 14 or 15 with the "all" preset.

nerfstudio cameras map explicitly (``intrinsics_from_cameras``, ``nerfstudio_distortion``): PERSPECTIVE cameras'
distortion_params [k1, k2, k3, k4, p1, p2] are OpenCV's k1, k2, k3, p1, p2 plus a polynomial r^8 term k4 that no
COLMAP model has (nerfstudio issue 3355) and that must be zero; FISHEYE cameras' [k1, k2, k3, k4, 0, 0] are
OPENCV_FISHEYE's k1..k4.

Training rays are regenerated from each ray's pixel coordinates (carried by ``PixelRayGenerator`` in
``ray_bundle.metadata[PIXEL_KEY]``), so intrinsics really move the rays, differentiably.

P is refreshed every ``refresh_every`` steps from the current refined intrinsics; a refresh re-expresses the
latent so the camera does not move (phi_hat_new = P_new P_old^-1 phi_hat_old) and transforms Adam's moments
(see ``refresh``).

The proxy points' radial range [t_near, t_far] is chosen once per physical camera from the scene's sparse points
(``core.proxy_range.proxy_ranges``, given to ``set_train_cameras`` by the pipeline), unless the sampling config sets
it; every refresh uses that stored range.

Checkpoints hold phi_hat, P, P^-1, the refresh schedule and the base intrinsics and proxy range P was computed for.
Resuming on the same cameras and points continues bit-identically; loading onto other base cameras (a warm start
resumed with perturbed cameras) or another range recomputes P and re-expresses the latent and Adam's moments before
the next step instead of using a stale P.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Literal, Union

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.cameras.rays import RayBundle
from rich.console import Console
from torch import Tensor, nn

from s2camp_ns.core.camera import (
    PARAMETER_NAMES,
    TENSOR_FIELDS,
    Intrinsics,
    ParameterLayout,
    opengl_to_opencv,
    pixel_to_ray_direction,
    se3_exp,
)
from s2camp_ns.core.colmap_models import SUPPORTED_COLMAP_MODELS
from s2camp_ns.core.config_defaults import DefaultsOnLoad
from s2camp_ns.core.preconditioner import (
    DampingConfig,
    Preconditioner,
    SamplingConfig,
    compute_preconditioner,
    reexpress_latent,
)
from s2camp_ns.core.proxy_range import ProxyRanges, proxy_ranges
from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS, compute_shared_preconditioner, reexpress_shared_latents
from s2camp_ns.core.track_fit import TrackEvidence, fit_anchor
from s2camp_ns.core.validation import check_range

PIXEL_KEY = "s2camp_pixels"
"""RayBundle metadata key of the continuous pixel coordinates (u, v) = (x + 0.5, y + 0.5) of each training ray."""
LOG = Console(stderr=True, width=120)
"""Start-up notes of the optimizer (the chosen proxy range): on stderr, so a caller's stdout (JSON of
``s2camp-bench``) stays clean."""
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
    track_prior: bool = False
    """Anchor each camera where the scene's SfM tracks put it, with a Gaussian prior in the whitened space whose scale
    is the tracks' reprojection error there (``set_track_prior``, ``apply_track_prior``): a camera moves about that
    far from its anchor at most, however long the field pulls. For cameras straight out of SfM the anchor is the
    given camera and the scale SfM's own error; cameras changed after SfM are anchored where their tracks say they
    are (a camera-only bundle adjustment against the fixed points, ``core.track_fit``), so the prior guides them
    there instead of holding them in place. A camera without tracks has no prior. Needs the data parser's
    ``track_evidence`` (COLMAP scenes with points, ns-process-data transforms.json with their ``colmap/sparse/0``, and
    scenes without either through tracks made from their images, ``image_tracks``). On in the ``s2camp`` and
    ``s2camp-splat`` methods (``method_config``), off in this config (the baselines' setting: CamP's and
    nerfstudio's code have no prior); measured on the real-regime grid (``s2camp-bench robustness --preset regime``,
    docs/benchmarks/regime.md, docs/DESIGN-NOTES.md sec. 12-16)."""

    photometric: bool = True
    """Let the photometric loss move the cameras. False (with ``track_prior``): every camera with tracks is placed at
    its track prior's anchor (the camera-only adjustment to the tracks, ``core.track_fit``) and stays there, the
    others where they are given: the "tracks alone" baseline, what bundle adjustment gives a user without
    refinement. The latent keeps its gradient, zeroed (Adam then makes no step), so mixed-precision training with
    its gradient scaler runs as for the other settings."""

    fix_common_rotation: bool = False
    """After every step, remove the rotation that all training cameras share (the mean over images of the pose
    update's rotation, each in its own camera frame; ``remove_common_motion``). A rotation every camera makes at
    once is the similarity gauge in disguise: with a rotation-translation pair per camera that shifts the image of
    content at the scene's depth by nothing, a common pitch of cameras on a ring equals moving all of them up, and a
    common yaw of forward-facing cameras equals turning the world, neither of which the photometric loss sees
    (docs/DESIGN-NOTES.md sec. 13). On in the ``s2camp`` and ``s2camp-splat`` methods, off in this config (the
    baselines' setting)."""

    def layout(self, camera_model: str = "RADIAL") -> ParameterLayout:
        return ParameterLayout.from_preset(self.parameters, camera_model)

    def validate(self) -> None:
        self.layout()
        if not self.photometric and not self.track_prior:
            raise ValueError(
                "camera-optimizer.photometric False places the cameras at the track prior's anchor and needs "
                "camera-optimizer.track-prior True, got track_prior False"
            )
        self.sampling.validate()
        self.damping.validate()
        check_range("refresh_every", self.refresh_every, low=0)


def group_identical_intrinsics(cameras: Cameras) -> Tensor:
    """Physical-camera id per camera: cameras with identical intrinsics, distortion, size and type share one."""
    n = cameras.shape[0]
    columns = [getattr(cameras, name).reshape(n, -1).to(torch.float64).cpu() for name in ("fx", "fy", "cx", "cy")]
    columns += [cameras.width.reshape(n, -1).double().cpu(), cameras.height.reshape(n, -1).double().cpu()]
    columns.append(cameras.camera_type.reshape(n, -1).double().cpu())
    if cameras.distortion_params is not None:
        columns.append(cameras.distortion_params.reshape(n, -1).to(torch.float64).cpu())
    _, ids = torch.unique(torch.cat(columns, dim=-1), dim=0, return_inverse=True)
    return ids


SUPPORTED_CAMERA_TYPES = {
    CameraType.PERSPECTIVE.value: "perspective",
    CameraType.FISHEYE.value: "fisheye",
}
"""nerfstudio camera types S2CamP refines, and the core projection each one is."""


def _supported_types_message() -> str:
    return (
        "supported are PERSPECTIVE (COLMAP "
        + ", ".join(m for m in SUPPORTED_COLMAP_MODELS if "FISHEYE" not in m)
        + " with k4 = k5 = k6 = 0) and FISHEYE (COLMAP OPENCV_FISHEYE)"
    )


def projection_of(cameras: Cameras) -> str:
    """The core projection ("perspective" or "fisheye") of nerfstudio cameras; ValueError naming any camera type
    S2CamP cannot refine (equirectangular, omnidirectional, orthographic, ...) or a mix of types."""
    types = sorted({int(t) for t in cameras.camera_type.reshape(-1).tolist()})
    unsupported = [CameraType(t).name for t in types if t not in SUPPORTED_CAMERA_TYPES]
    if unsupported:
        raise ValueError(
            f"camera type {', '.join(unsupported)} is not supported by S2CamP's camera refinement; "
            + _supported_types_message()
        )
    if len(types) > 1:
        raise ValueError(
            f"cameras mix the types {[CameraType(t).name for t in types]}; S2CamP refines one camera type per scene"
        )
    return SUPPORTED_CAMERA_TYPES[types[0]]


def intrinsics_from_cameras(cameras: Cameras, dtype: torch.dtype = torch.float64) -> Intrinsics:
    """Base intrinsics of nerfstudio cameras, mapped explicitly; raises ValueError for cameras S2CamP cannot represent.

    nerfstudio's distortion_params are [k1, k2, k3, k4, p1, p2]. PERSPECTIVE: k1, k2, k3, p1, p2 are OpenCV's (the
    radial-tangential model of ``core.camera``); k4 multiplies r^8 in nerfstudio, which no COLMAP model can hold
    (FULL_OPENCV's k4 is a rational coefficient, nerfstudio issue 3355), so it must be zero. FISHEYE: k1..k4 are
    OPENCV_FISHEYE's (theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8), what nerfstudio renders) and p1, p2,
    which OpenCV's fisheye model lacks, must be zero.
    """
    projection = projection_of(cameras)
    n = cameras.shape[0]
    params = torch.zeros(n, 6, dtype=dtype)
    if cameras.distortion_params is not None:
        params = cameras.distortion_params.reshape(n, 6).to(dtype).cpu()
    if projection == "perspective":
        reason = "a polynomial r^8 term in nerfstudio; COLMAP FULL_OPENCV's k4 divides instead (nerfstudio issue 3355)"
        must_be_zero = [(3, "k4", reason)]
    else:
        reason = "OPENCV_FISHEYE has no tangential terms"
        must_be_zero = [(4, "p1", reason), (5, "p2", reason)]
    for column, name, reason in must_be_zero:
        if bool((params[:, column] != 0).any()):
            i = int(torch.nonzero(params[:, column] != 0)[0])
            raise ValueError(
                f"distortion parameter {name} = {params[i, column].item():g} of {projection} camera {i} is not "
                f"supported ({reason}); allowed is {name} = 0"
            )
    k1, k2, k3, k4, p1, p2 = params.unbind(dim=-1)
    return Intrinsics.create(
        fx=cameras.fx.reshape(n).cpu(),
        fy=cameras.fy.reshape(n).cpu(),
        cx=cameras.cx.reshape(n).cpu(),
        cy=cameras.cy.reshape(n).cpu(),
        width=cameras.width.reshape(n).cpu(),
        height=cameras.height.reshape(n).cpu(),
        k1=k1,
        k2=k2,
        k3=k3,
        k4=k4 if projection == "fisheye" else 0.0,
        p1=p1 if projection == "perspective" else 0.0,
        p2=p2 if projection == "perspective" else 0.0,
        model=projection,
        dtype=dtype,
    )


def nerfstudio_distortion(intrinsics: Intrinsics) -> Float[Tensor, "n 6"]:
    """nerfstudio's distortion_params [k1, k2, k3, k4, p1, p2] of ``intrinsics`` (the inverse of
    ``intrinsics_from_cameras``): the same slots for both projections, p1 = p2 = 0 for fisheye cameras."""
    zeros = torch.zeros_like(intrinsics.k1)
    tangential = (zeros, zeros) if intrinsics.is_fisheye else (intrinsics.p1, intrinsics.p2)
    return torch.stack([intrinsics.k1, intrinsics.k2, intrinsics.k3, intrinsics.k4, *tangential], dim=-1)


def camera_model_of(intrinsics: Intrinsics) -> str:
    """The COLMAP camera model whose distortion groups the "all" preset refines: OPENCV_FISHEYE for fisheye
    cameras; FULL_OPENCV when some camera has k3; OPENCV when some camera has p1 or p2; RADIAL otherwise.

    Decided by the values (nerfstudio's cameras do not keep the model's name): an OPENCV camera with
    p1 = p2 = 0 is a RADIAL camera, as COLMAP's models nest.
    """
    if intrinsics.is_fisheye:
        return "OPENCV_FISHEYE"
    if bool((intrinsics.k3 != 0).any()):
        return "FULL_OPENCV"
    if bool((intrinsics.p1 != 0).any() | (intrinsics.p2 != 0).any()):
        return "OPENCV"
    return "RADIAL"


class S2CampCameraOptimizer(CameraOptimizer):
    """Whitened camera-parameter deltas, their preconditioner and its refresh schedule."""

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
        # and would sit in the "camera_opt" group (grad-scaler trouble, docs/DESIGN-NOTES.md sec. 6).
        nn.Module.__init__(self)
        config.validate()
        self.config = config
        self.num_cameras = num_cameras
        self.device = device
        self.non_trainable_camera_indices = non_trainable_camera_indices
        self.layout = config.layout()
        k = self.layout.num_params
        self.enabled = config.mode != "off"
        # Shared intrinsics: the latent splits into a pose part per image and an intrinsics part per physical camera.
        self.shared = self.enabled and config.intrinsics == "per-camera" and k > NUM_POSE_PARAMS
        if self.enabled:
            self.whitened_delta = self._latent(torch.zeros(num_cameras, NUM_POSE_PARAMS if self.shared else k), device)
        if self.shared:  # one physical camera per image until ``set_camera_groups`` says otherwise
            self.whitened_intrinsics = self._latent(torch.zeros(num_cameras, k - NUM_POSE_PARAMS), device)
        eye = torch.eye(k, dtype=torch.float64, device=device).expand(num_cameras, k, k).clone()
        # P and P^-1 (paper eq. 20) and the schedule state are persistent so that a resumed run continues with
        # the identical camera parameters.
        self.register_buffer("precond", eye.clone())
        self.register_buffer("precond_inv", eye.clone())
        self.register_buffer("last_refresh_step", torch.tensor(-1, dtype=torch.long, device=device))
        self.register_buffer("num_refreshes", torch.tensor(0, dtype=torch.long, device=device))
        # Base cameras come from the dataparser on every run, so they are not saved.
        self.register_buffer(
            "base_c2w_cv", torch.zeros(num_cameras, 3, 4, dtype=torch.float64, device=device), persistent=False
        )
        self.register_buffer(
            "base_intrinsics", torch.zeros(num_cameras, 13, dtype=torch.float64, device=device), persistent=False
        )
        self.projection = "perspective"
        # The base intrinsics of the run that computed P, saved with P: a checkpoint loaded onto other base cameras
        # is detected and P recomputed (``_check_base_cameras``) instead of silently reused. P depends on
        # the intrinsics only (the Jacobian is taken in the camera frame), so the base poses need no record.
        self.register_buffer("precond_base_intrinsics", torch.zeros_like(self.base_intrinsics))
        # Undamped Gram Sigma of the last refresh (zero until one computes it; the viewer panel's condition numbers).
        self.register_buffer("gram", torch.zeros_like(eye), persistent=False)
        # Contracted proxy range [t_near, t_far] per image (equal for the images of a physical camera): this run's,
        # chosen from the scene at ``set_train_cameras`` (not saved, like the base cameras), and the one P was
        # computed with (saved with P, so a checkpoint loaded with another range is recomputed like other cameras).
        no_range = torch.zeros(num_cameras, 2, dtype=torch.float64, device=device)
        self.register_buffer("proxy_range", no_range.clone(), persistent=False)
        self.register_buffer("precond_proxy_range", no_range.clone())
        self.proxy_ranges: ProxyRanges | None = None
        # Physical camera of each image (0..C-1); one camera per image until ``set_camera_groups`` says otherwise.
        self.register_buffer("camera_of_image", torch.arange(num_cameras, device=device), persistent=False)
        self.groups_known = False
        self.has_cameras = False
        self._warned_no_pixels = False
        # Why a loaded P does not fit the base cameras (None when it does): it is recomputed before the next training
        # step (``recompute_stale_preconditioner``), once Adam's moments are loaded too.
        self._stale_preconditioner: str | None = None
        # Track prior radius per image in whitened units (RMS px / max(W, H)); NaN = no prior (``set_track_prior``),
        # and per physical camera for the shared intrinsics latent (the standard error of its pooled fit).
        no_prior = torch.full((num_cameras,), float("nan"), dtype=torch.float64, device=device)
        self.register_buffer("prior_radius", no_prior, persistent=False)
        self.register_buffer("prior_radius_intrinsics", no_prior.clone(), persistent=False)
        # Its anchor: the deltas phi (the layout's columns) where the tracks put each camera; zero = the given camera.
        self.register_buffer(
            "prior_anchor",
            torch.zeros(num_cameras, k, dtype=torch.float64, device=device),
            persistent=False,
        )
        self.has_track_prior = False

    # ----------------------------------------------------------------------------------------------------- setup
    def _latent(self, values: Tensor, device: torch.device | str) -> nn.Parameter:
        """A latent parameter on ``device``; with ``photometric`` False its gradient is zeroed (tracks
        alone: the images move no camera, and Adam steps by zero)."""
        latent = nn.Parameter(values.to(device))
        if not self.config.photometric:
            latent.register_hook(torch.zeros_like)
        return latent

    @property
    def num_physical_cameras(self) -> int:
        return int(self.camera_of_image.max()) + 1 if self.num_cameras else 0

    def set_camera_groups(self, camera_ids: Tensor | list[int]) -> None:
        """Which training images share a physical camera (any integer ids, one per image; relabelled 0..C-1 in
        order of first appearance). With shared intrinsics this sizes the intrinsics latent [C, m]; call it before
        the optimizers are built (the model does, from the dataparser's metadata)."""
        ids = torch.as_tensor(camera_ids).reshape(-1)
        if ids.shape[0] != self.num_cameras:
            raise ValueError(f"camera_ids must hold {self.num_cameras} entries (one per image), got {ids.shape[0]}")
        _, first = torch.unique(ids, return_inverse=True)
        order = {}
        labels = [order.setdefault(int(value), len(order)) for value in first.tolist()]
        self.camera_of_image = torch.tensor(labels, dtype=torch.long, device=self.precond.device)
        self.groups_known = True
        if self.shared:
            m = self.layout.num_params - NUM_POSE_PARAMS
            existing = getattr(self, "whitened_intrinsics", None)
            if existing is None or existing.shape != (len(order), m):
                self.whitened_intrinsics = self._latent(torch.zeros(len(order), m), self.precond.device)

    def set_train_cameras(self, cameras: Cameras, points: Float[Tensor, "m 3"] | None = None) -> None:
        """Store the dataparser's training cameras, choose the proxy range from the scene's ``points`` and compute the
        initial P (called by the pipeline).

        ``points``: the scene's sparse points in the cameras' (normalized) world frame, the dataparser's
        ``metadata["points3D_xyz"]``; they set each physical camera's contracted range (``choose_proxy_range``).
        None: the fixed range. A checkpoint loaded afterwards overwrites phi_hat, P and P^-1 with the saved ones; if
        its P was computed for other base cameras or another range, it is recomputed before the next training step
        (see ``_check_base_cameras``).
        """
        if cameras.shape[0] != self.num_cameras:
            raise ValueError(f"cameras must hold {self.num_cameras} training cameras, got {cameras.shape[0]}")
        intrinsics = intrinsics_from_cameras(cameras)
        device = self.precond.device
        self.base_c2w_cv = opengl_to_opencv(cameras.camera_to_worlds.to(torch.float64)).to(device)
        base = intrinsics.tensors().to(device)
        self.projection = intrinsics.model
        self.set_camera_model(camera_model_of(intrinsics))
        if self.shared and not self.groups_known:
            self.set_camera_groups(group_identical_intrinsics(cameras))
        self.base_intrinsics = self._shared_base(base) if self.shared else base
        self.proxy_range = self.choose_proxy_range(cameras, points).to(device)
        self.has_cameras = True
        if int(self.last_refresh_step) < 0:
            self.refresh(step=0)
        else:  # a checkpoint was loaded before the cameras were known
            self._check_base_cameras()

    def set_track_prior(
        self,
        track_rms_px: Float[Tensor, " n"] | None,
        evidence: TrackEvidence | None = None,
        track_observations: Float[Tensor, " n"] | None = None,
    ) -> None:
        """The track prior's anchor and scale per training image (``track_prior=False`` ignores both).

        With ``evidence`` (the scene's tracks and the given cameras in the tracks' world, from the data parser) the
        anchor is where the tracks put each camera (``core.track_fit``: a camera-only bundle adjustment of this
        optimizer's free parameters against the fixed SfM points, which keeps the given intrinsics unless the tracks
        call for others, ``fit_anchor``) and the scale is the reprojection error there, the tracks' own noise; shared
        intrinsics take the standard error of their fit to all their images' observations. Without it the anchor is
        the given camera and the scale ``track_rms_px``, its reprojection error against the tracks (``core.tracks``;
        NaN or None: no prior), with ``track_observations`` (each image's number of tracks) for the shared
        intrinsics' standard error. Scales are stored in whitened units (divided by max(W, H), the Gram matrix's
        pixel unit, docs/EQUATIONS.md eq. 5). Call after ``set_train_cameras``."""
        self._require_cameras()
        device = self.precond.device
        radius = torch.full((self.num_cameras,), float("nan"), dtype=torch.float64, device=device)
        anchor = torch.zeros(self.num_cameras, self.layout.num_params, dtype=torch.float64, device=device)
        rms = None
        observations = None
        if self.config.track_prior and evidence is not None:
            fit = fit_anchor(
                evidence.tracks,
                evidence.c2w,
                self.base_intrinsics_struct(),
                free=self.layout.indices,
                camera_of_image=self.camera_of_image if self.shared else None,
            )
            deltas = fit.deltas.clone()
            deltas[:, :3] = deltas[:, :3] * float(evidence.world_scale)  # tracks' world -> training frame
            anchor = deltas[:, list(self.layout.indices)].to(device)
            rms = fit.rms_px.to(device)
            observations = fit.observations.to(device)
            moved = torch.isfinite(fit.rms_given_px) & torch.isfinite(fit.rms_px)
            if bool(moved.any()):
                held = fit.intrinsics_held
                kept = "" if held is None else f"; given intrinsics kept: {int(held.sum())} of {held.numel()} camera(s)"
                LOG.print(
                    f"[dim]Track prior: the cameras' reprojection error against the tracks is "
                    f"{_span(fit.rms_given_px[moved])} px as given and {_span(fit.rms_px[moved])} px where the tracks "
                    f"put them (the anchor{kept}; {fit.iterations} Levenberg-Marquardt iterations)"
                )
        elif track_rms_px is not None and self.config.track_prior:
            rms = torch.as_tensor(track_rms_px, dtype=torch.float64).reshape(-1).to(device)
            if rms.shape[0] != self.num_cameras:
                raise ValueError(
                    f"track_rms_px must hold {self.num_cameras} values (one per training image), got {rms.shape[0]}"
                )
            if bool((rms < 0).any()):
                raise ValueError(f"track_rms_px must be >= 0 (pixels), got minimum {float(rms.min())}")
            if track_observations is not None:
                observations = torch.as_tensor(track_observations, dtype=torch.float64).reshape(-1).to(device)
                if observations.shape[0] != self.num_cameras or bool((observations < 0).any()):
                    raise ValueError(
                        f"track_observations must hold {self.num_cameras} counts >= 0 (one per training image), got "
                        f"{observations.shape[0]} with minimum {float(observations.min())}"
                    )
        if rms is not None:
            radius = rms / self.base_intrinsics_struct().image_scale()
        self.prior_radius = radius
        keep = torch.isfinite(radius)[:, None].expand_as(anchor).clone()
        if self.shared:  # the intrinsics are the physical camera's: anchored where any of its images is tracked
            tracked = torch.zeros(self.num_physical_cameras, dtype=torch.bool, device=device)
            tracked[self.camera_of_image[torch.isfinite(radius)]] = True
            keep[:, NUM_POSE_PARAMS:] = tracked[self.camera_of_image][:, None]
        self.prior_anchor = torch.where(keep, anchor, torch.zeros_like(anchor))
        self.has_track_prior = bool(torch.isfinite(radius).any())
        if self.shared:  # groups are known by now: set_train_cameras fixed them
            finite = torch.isfinite(radius)
            weight = torch.ones_like(radius) if observations is None else observations.to(radius)
            weight = torch.where(finite, weight, torch.zeros_like(weight))
            squared = torch.zeros(self.num_physical_cameras, dtype=torch.float64, device=radius.device)
            counts = torch.zeros_like(squared)
            squared.index_add_(0, self.camera_of_image, torch.nan_to_num(radius).square() * weight)
            counts.index_add_(0, self.camera_of_image, weight)
            # The shared intrinsics are fitted to every observation of their images at once, so their scale is the
            # standard error of that pooled fit: a unit step of the shared latent moves each image's proxy points by
            # an RMS of one (core.shared_intrinsics), and so each of the O observations by about one; O of them with
            # pixel noise of RMS r (2D: r^2 / 2 per coordinate) determine it to r / sqrt(2 O), r the pooled RMS,
            # i.e. sqrt(sum_i O_i r_i^2) / (sqrt(2) sum_i O_i). The poses keep each image's own noise r_i as theirs
            # (the photometric loss corrects poses within it), but the focal length's photometric evidence in the
            # regime is the biased pull of the dolly zoom (docs/DESIGN-NOTES.md sec. 12-14): with r_i / sqrt(n_c)
            # the shared focal length of 49 SfM images still ended 0.06-0.08 px further from the truth than SfM's.
            # Without observation counts (track_rms_px alone, no track_observations) each image counts once.
            self.prior_radius_intrinsics = torch.where(
                counts > 0, squared.sqrt() / (math.sqrt(2.0) * counts.clamp(min=1e-12)), torch.nan
            )
        if self.enabled and not self.config.photometric:
            self._place_at_anchor()

    @torch.no_grad()
    def _place_at_anchor(self) -> None:
        """``photometric`` False: the latent at the anchor (zero, the given camera, where there is no prior)."""
        pose_anchor, intrinsics_anchor = self.prior_anchor_latents()
        self.whitened_delta.copy_(pose_anchor.to(self.whitened_delta.dtype))
        if self.shared:
            finite = torch.isfinite(self.prior_radius_intrinsics)[:, None]
            anchor = torch.where(finite, intrinsics_anchor, torch.zeros_like(intrinsics_anchor))
            self.whitened_intrinsics.copy_(anchor.to(self.whitened_intrinsics.dtype))

    def prior_anchor_latents(self) -> tuple[Float[Tensor, "n k"], Float[Tensor, "c m"] | None]:
        """The anchor in the whitened latent under the current P (phi_hat = P phi, paper eq. 15): the pose latent per
        image and, with shared intrinsics, the intrinsics latent per physical camera (P is block-triangular, so
        the images of one camera give the same intrinsics latent: their first image's)."""
        latent = (self.precond @ self.prior_anchor[..., None])[..., 0]
        if not self.shared:
            return latent, None
        return latent[:, :NUM_POSE_PARAMS], latent[self._first_image_of_each_camera(), NUM_POSE_PARAMS:]

    @torch.no_grad()
    def apply_track_prior(self, lr: float) -> None:
        """One proximal step of the track prior after the optimizer's step of learning rate ``lr``.

        The prior is a Gaussian on the whitened latent phi_hat about its anchor a (``set_track_prior``), whose
        distance is the RMS displacement of the camera's proxy points in units of max(W, H) (paper eqs. 5 and 20;
        damping only adds to it). Its proximal map with Adam's step size, phi_hat <- a + (phi_hat - a) / (1 + lr / r)
        (decoupled weight decay, as AdamW, towards a), balances Adam's step lr m / sqrt(v) where each coordinate is
        |phi_hat_j - a_j| = r |m_j / sqrt(v_j)| <= r: evidence of constant sign (|m / sqrt(v)| near 1) moves a
        whitened coordinate at most r from the anchor, the tracks' noise; gradient noise (|m / sqrt(v)| near 0.23 for
        Adam's beta1 0.9) about a quarter of that. Once the field stops pulling, the camera relaxes back towards the
        anchor within about r / lr steps instead of staying where early field errors pushed it. Images without
        tracks are untouched. Shared intrinsics take the standard error of their fit to all their images'
        observations, RMS / sqrt(2 O) for O observations of pooled RMS (``set_track_prior``).
        """
        # A Python flag, not a look at the radii: no device synchronisation on the training step's path.
        if not self.enabled or not self.has_track_prior or lr <= 0:
            return
        pose_anchor, intrinsics_anchor = self.prior_anchor_latents()
        self._shrink(self.whitened_delta, pose_anchor, self.prior_radius, lr)
        if self.shared:
            self._shrink(self.whitened_intrinsics, intrinsics_anchor, self.prior_radius_intrinsics, lr)

    @torch.no_grad()
    def remove_common_motion(self) -> None:
        """Subtract the mean over trainable images of the rotation part omega of the pose deltas phi
        (``fix_common_rotation``), each in its own camera frame, from every image's, in the latent:
        phi_hat += P[:, :, c] d for the rotation columns c (paper eq. 15; with shared intrinsics the pose rows of the
        block-triangular P, so no intrinsics change). Everything else stays; a no-op when the option is off, when
        disabled or with fewer than three trainable images. With the track prior the rotation is measured from the
        prior's anchor: the tracks fix the world, so the rotation the anchors share (the mean of the cameras' own
        corrections) is no gauge and stays."""
        if not self.enabled or not self.config.fix_common_rotation:
            return
        columns = [3, 4, 5]  # the twist's rotation: (rho_x, rho_y, rho_z, omega_x, omega_y, omega_z)
        trainable = torch.ones(self.num_cameras, dtype=torch.bool, device=self.precond.device)
        if self.non_trainable_camera_indices is not None:
            trainable[self.non_trainable_camera_indices.to(trainable.device)] = False
        if int(trainable.sum()) < 3:
            return
        motion = self.camera_deltas()[:, columns]
        if self.has_track_prior:
            motion = motion - self.layout.expand(self.prior_anchor)[:, columns]
        correction = torch.zeros_like(motion)
        correction[trainable] = -motion[trainable].mean(dim=0)
        latent = self.whitened_delta
        rows = self.precond[:, : latent.shape[1], columns].to(torch.float64)
        latent.add_((rows @ correction[..., None])[..., 0].to(latent.dtype))

    @staticmethod
    def _shrink(latent: nn.Parameter, anchor: Tensor, radius: Tensor, lr: float) -> None:
        factor = 1.0 / (1.0 + lr / radius.clamp(min=1e-12))
        factor = torch.where(torch.isfinite(radius), factor, torch.ones_like(factor)).to(latent.dtype)[:, None]
        anchor = anchor.to(latent.dtype)
        latent.copy_(anchor + (latent - anchor) * factor)

    def choose_proxy_range(self, cameras: Cameras, points: Tensor | None) -> Float[Tensor, "n 2"]:
        """Contracted [t_near, t_far] per training image: chosen per physical camera from the points it sees
        (``core.proxy_range.proxy_ranges``, its images pooled) where the sampling config leaves an end unset, the
        config's range otherwise. Physical cameras: ``camera_of_image`` when known, else identical intrinsics."""
        sampling = self.config.sampling
        n = self.num_cameras
        if not (sampling.auto and self.enabled and self.config.precondition):  # P = I needs no range
            return torch.tensor(sampling.fixed_range(), dtype=torch.float64).expand(n, 2).clone()
        groups = self.camera_of_image if self.groups_known or self.shared else group_identical_intrinsics(cameras)
        groups = groups.cpu()
        c2w = opengl_to_opencv(cameras.camera_to_worlds.detach().to(torch.float64).cpu())
        points = None if points is None else torch.as_tensor(points).detach().to(torch.float64).cpu()
        intrinsics = intrinsics_from_cameras(cameras)
        ranges = proxy_ranges(
            points, c2w, intrinsics, groups, sampling.auto_range, sampling.t_near, sampling.t_far, sampling.radial
        )
        self.proxy_ranges = ranges
        self._log_proxy_ranges(ranges, 0 if points is None else points.shape[0])
        return ranges.stacked()[groups]

    def _log_proxy_ranges(self, ranges: ProxyRanges, num_points: int) -> None:
        sampling = self.config.sampling
        fixed = sampling.fixed_range()
        count = ranges.t_near.shape[0]
        fell_back = int(ranges.fallback.sum())
        chosen = "t_near " + _span(ranges.t_near) + ", t_far " + _span(ranges.t_far)
        if num_points == 0:
            LOG.print(
                "S2CamP proxy range: the scene has no points (dataparser metadata 'points3D_xyz'), so every camera "
                f"uses the fixed contracted range ({fixed[0]:g}, {fixed[1]:g}) (sampling.t-near / t-far set it)"
            )
            return
        message = f"S2CamP proxy range from {num_points} scene points, {count} physical cameras: {chosen} (contracted)"
        if fell_back:
            message += (
                f"; {fell_back} camera(s) see fewer than {sampling.auto_range.min_points} points and use the fixed "
                f"range ({fixed[0]:g}, {fixed[1]:g})"
            )
        LOG.print(message)

    # ---------------------------------------------------------------------------------------------- checkpoints
    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ) -> None:
        saved = state_dict.get(prefix + "precond")
        if saved is not None and saved.shape[0] != self.num_cameras:
            # torch would list a size mismatch per tensor without saying why; the cause is another scene or split.
            raise ValueError(
                f"the camera optimizer's checkpoint holds {saved.shape[0]} training cameras, but this model has "
                f"{self.num_cameras}: it is a checkpoint of another scene or of another train/eval split"
            )
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        if prefix + "precond" not in state_dict:
            return  # no saved P (e.g. a checkpoint stripped of the camera optimizer): the current one stands
        fingerprint = prefix + "precond_base_intrinsics"
        if fingerprint not in state_dict:  # written before P's cameras were recorded: treat them as unknown
            missing_keys.remove(fingerprint)
            self.precond_base_intrinsics.fill_(float("nan"))
        fingerprint = prefix + "precond_proxy_range"
        if fingerprint not in state_dict:  # written before P's range was recorded: unknown
            missing_keys.remove(fingerprint)
            self.precond_proxy_range.fill_(float("nan"))
        if self.has_cameras:
            self._check_base_cameras()

    def _check_base_cameras(self) -> None:
        """Flag a loaded P that was computed for other base intrinsics; it is never used for a training step.

        Same base intrinsics (a resumed run): the saved P is the right one and is kept, so the run continues with
        bit-identical camera parameters. Other base intrinsics (e.g. a warm start resumed with perturbed cameras):
        the cameras themselves are right (phi = P_old^-1 phi_hat is what was learned), but P does not whiten their
        Jacobian. Before the next training step, ``recompute_stale_preconditioner`` recomputes P at the current
        refined intrinsics and re-expresses the latents and Adam's moments, as a refresh does (nerfstudio loads
        Adam's state after the pipeline, so this cannot happen at load time). P depends on the intrinsics and the proxy
        range only; a checkpoint whose range differs (other scene points, another ``sampling.t-far``) is treated alike.
        """
        self._stale_preconditioner = None
        same_intrinsics = torch.equal(self.precond_base_intrinsics, self.base_intrinsics)
        same_range = torch.equal(self.precond_proxy_range, self.proxy_range)
        if same_intrinsics and same_range:
            return
        if not (self.config.precondition and self.enabled):  # P = I does not depend on the cameras
            self.precond_base_intrinsics.copy_(self.base_intrinsics)
            self.precond_proxy_range.copy_(self.proxy_range)
            return
        if not bool(torch.isfinite(self.precond_base_intrinsics).all()):
            self._stale_preconditioner = "the intrinsics its P was computed for are not recorded (an older checkpoint)"
        elif not same_intrinsics:
            self._stale_preconditioner = (
                f"the training cameras' intrinsics differ from those its P was computed for (largest change "
                f"{self._largest_intrinsics_change()})"
            )
        elif not bool(torch.isfinite(self.precond_proxy_range).all()):
            self._stale_preconditioner = "the proxy range its P was computed for is not recorded (an older checkpoint)"
        else:
            self._stale_preconditioner = (
                f"the proxy range differs from the one its P was computed for ({self._largest_range_change()})"
            )
        warnings.warn(
            f"loaded camera-optimizer state: {self._stale_preconditioner}; P is recomputed for these cameras before "
            "the next training step, the latent and Adam's moments re-expressed (the learned camera deltas are kept)",
            stacklevel=2,
        )

    def _largest_intrinsics_change(self) -> str:
        names = TENSOR_FIELDS  # the columns of base_intrinsics
        difference = (self.base_intrinsics - self.precond_base_intrinsics).abs()
        flat = int(difference.argmax())
        camera, column = divmod(flat, difference.shape[1])
        return (
            f"{names[column]} of camera {camera}: {float(self.precond_base_intrinsics[camera, column]):g} -> "
            f"{float(self.base_intrinsics[camera, column]):g}"
        )

    def _largest_range_change(self) -> str:
        difference = (self.proxy_range - self.precond_proxy_range).abs()
        image, column = divmod(int(difference.argmax()), 2)
        name = ("t_near", "t_far")[column]
        return (
            f"{name} of image {image}: {float(self.precond_proxy_range[image, column]):g} -> "
            f"{float(self.proxy_range[image, column]):g}"
        )

    @property
    def preconditioner_is_stale(self) -> bool:
        """True between loading a checkpoint whose P was computed for other cameras and the next training step."""
        return self._stale_preconditioner is not None

    @torch.no_grad()
    def recompute_stale_preconditioner(self, step: int, optimizer: torch.optim.Optimizer | None) -> None:
        """Before a training step (the model's callback): if the loaded P was computed for other cameras, recompute
        it at the current refined intrinsics and re-express the latents and Adam's (loaded) moments, exactly as a
        refresh does. Raises ValueError, naming why, if no P exists for these cameras: a stale P is never used."""
        if self._stale_preconditioner is None:
            return
        reason, self._stale_preconditioner = self._stale_preconditioner, None
        try:
            self._recompute_preconditioner(optimizer)
        except ValueError as error:
            raise ValueError(
                f"checkpoint cannot be used with these training cameras: {reason}, and P cannot be recomputed for "
                f"them: {error}"
            ) from error
        self.last_refresh_step.fill_(step)
        self.num_refreshes.add_(1)

    def _first_image_of_each_camera(self) -> Tensor:
        index = self.camera_of_image
        first = torch.full((self.num_physical_cameras,), self.num_cameras, dtype=torch.long, device=index.device)
        return first.scatter_reduce_(0, index, torch.arange(self.num_cameras, device=index.device), "amin")

    def _shared_base(self, base: Tensor) -> Tensor:
        """One set of base intrinsics per physical camera: the mean over its images (they agree for SfM cameras;
        a per-image perturbation averages out). Images of one camera must have the same size."""
        count = torch.bincount(self.camera_of_image, minlength=self.num_physical_cameras).to(base)
        mean = torch.zeros(self.num_physical_cameras, base.shape[1], dtype=base.dtype, device=base.device)
        mean = mean.index_add_(0, self.camera_of_image, base) / count[:, None]
        first = self._first_image_of_each_camera()
        size_mismatch = (base[first][self.camera_of_image, 7:9] != base[:, 7:9]).any(dim=-1)
        if bool(size_mismatch.any()):
            i = int(torch.nonzero(size_mismatch)[0])
            j = int(first[self.camera_of_image[i]])
            raise ValueError(
                f"training image {i} is {int(base[i, 7])}x{int(base[i, 8])} but image {j} of the same physical camera "
                f"{int(self.camera_of_image[i])} is {int(base[j, 7])}x{int(base[j, 8])}: shared intrinsics need one "
                "image size per camera (or --pipeline.model.camera-optimizer.intrinsics per-image)"
            )
        return mean[self.camera_of_image]

    def set_camera_model(self, camera_model: str) -> None:
        """Use the layout of the cameras' COLMAP model (``camera_model_of``): the "all" preset refines its distortion
        coefficients. Resizes the latents, P, P^-1 and Sigma to the layout's K; a no-op when the layout is unchanged
        (RADIAL, the default). Call it before the optimizers and DDP see the parameters (the model does, from the
        dataparser's metadata); ``set_train_cameras`` calls it again from the cameras themselves.
        """
        layout = self.config.layout(camera_model)
        if layout == self.layout:
            return
        self.layout = layout
        k = layout.num_params
        device = self.precond.device
        if self.enabled and self.shared:
            m = k - NUM_POSE_PARAMS
            self.whitened_intrinsics = nn.Parameter(torch.zeros(self.num_physical_cameras, m, device=device))
        elif self.enabled:
            self.whitened_delta = nn.Parameter(torch.zeros(self.num_cameras, k, device=device))
        eye = torch.eye(k, dtype=torch.float64, device=device).expand(self.num_cameras, k, k).clone()
        self.precond, self.precond_inv, self.gram = eye.clone(), eye.clone(), torch.zeros_like(eye)

    def _require_cameras(self) -> None:
        if not self.has_cameras:
            raise RuntimeError("S2CampCameraOptimizer.set_train_cameras must be called before use (the pipeline does)")

    def base_intrinsics_struct(self) -> Intrinsics:
        return Intrinsics.from_tensors(self.base_intrinsics, model=self.projection)

    # ------------------------------------------------------------------------------------------- refined cameras
    def camera_deltas(self, cameras: Int[Tensor, " m"] | None = None) -> Float[Tensor, "m 16"]:
        """Camera-parameter deltas phi = P^-1 phi_hat (paper eq. 15), all 16 columns, float64: of every camera, or
        of the training cameras ``cameras`` only (a training step needs those its rays come from)."""
        count = self.num_cameras if cameras is None else cameras.shape[0]
        if not self.enabled:
            return self.precond.new_zeros(count, len(PARAMETER_NAMES))
        precond_inv, latent, camera_of_image = self.precond_inv, self.whitened_delta, self.camera_of_image
        if cameras is not None:
            cameras = cameras.to(self.precond.device)
            precond_inv, latent, camera_of_image = precond_inv[cameras], latent[cameras], camera_of_image[cameras]
        latent = latent.to(torch.float64)
        if self.shared:  # [z_i; w_c]: the pose latent of the image and the intrinsics latent of its camera
            latent = torch.cat([latent, self.whitened_intrinsics.to(torch.float64)[camera_of_image]], dim=-1)
        phi = (precond_inv @ latent[..., None])[..., 0]
        if self.non_trainable_camera_indices is not None:
            keep = torch.ones(self.num_cameras, 1, dtype=phi.dtype, device=phi.device)
            keep[self.non_trainable_camera_indices.to(phi.device)] = 0.0
            phi = phi * (keep if cameras is None else keep[cameras])
        return self.layout.expand(phi)

    def refined_intrinsics(self, deltas: Tensor | None = None, cameras: Int[Tensor, " m"] | None = None) -> Intrinsics:
        """Intrinsics Phi' = Phi + dPhi (paper sec. 4), float64, differentiable: of every camera, or of ``cameras``
        (``deltas`` then holds theirs)."""
        self._require_cameras()
        deltas = self.camera_deltas(cameras) if deltas is None else deltas
        if cameras is None:
            return self.base_intrinsics_struct().with_delta(deltas)
        base = self.base_intrinsics[cameras.to(self.precond.device)]
        return Intrinsics.from_tensors(base, model=self.projection).with_delta(deltas)

    def refined_c2w(
        self, deltas: Tensor | None = None, opengl: bool = False, cameras: Int[Tensor, " m"] | None = None
    ) -> Float[Tensor, "m 3 4"]:
        """Refined c2w' = c2w exp(xi), float64, OpenCV frame unless ``opengl``: of every camera, or of ``cameras``
        (``deltas`` then holds theirs)."""
        self._require_cameras()
        deltas = self.camera_deltas(cameras) if deltas is None else deltas
        base = self.base_c2w_cv if cameras is None else self.base_c2w_cv[cameras.to(self.precond.device)]
        delta = se3_exp(deltas[:, :6])
        rotation = base[:, :, :3] @ delta[:, :, :3]
        translation = base[:, :, 3:] + base[:, :, :3] @ delta[:, :, 3:]
        c2w = torch.cat([rotation, translation], dim=-1)
        return opengl_to_opencv(c2w) if opengl else c2w

    def forward(self, indices: Int[Tensor, " camera_indices"]) -> Float[Tensor, "camera_indices 3 4"]:
        """Pose corrections D with c2w_gl' = c2w_gl D (right-multiplied, nerfstudio's OpenGL camera frame).

        This is what nerfstudio's viewer multiplies onto the training-camera frustums it draws.
        """
        deltas = self.camera_deltas()[indices.to(self.precond.device)]
        # c2w_gl' = c2w_cv E F = c2w_gl (F E F): flip the rows and the columns of E.
        correction = opengl_to_opencv(se3_exp(deltas[:, :6]))
        correction[:, 1:3, :] = -correction[:, 1:3, :]
        return correction.to(torch.float32)

    # ---------------------------------------------------------------------------------------------------- rays
    def regenerate_rays(
        self,
        camera_indices: Int[Tensor, " num_rays"],
        pixels: Float[Tensor, "num_rays 2"],
        dtype: torch.dtype = torch.float32,
    ) -> tuple[Float[Tensor, "num_rays 3"], Float[Tensor, "num_rays 3"], Float[Tensor, "num_rays 1"]]:
        """World origins, unit directions and directions_norm of rays through pixels of refined cameras.

        The per-camera algebra runs in float64 for the cameras the rays come from only (at most one per ray, so a
        step costs O(rays), not O(cameras): docs/SCALING.md); the per-ray part in ``dtype``. Autocast is disabled:
        undistortion and the pose product are not safe in half precision.
        """
        self._require_cameras()
        with torch.autocast(device_type=pixels.device.type, enabled=False):
            cameras, ray_camera = torch.unique(camera_indices.to(self.precond.device), return_inverse=True)
            deltas = self.camera_deltas(cameras)
            intrinsics = self.refined_intrinsics(deltas, cameras).to(dtype=dtype)
            c2w = self.refined_c2w(deltas, cameras=cameras).to(dtype=dtype)
            per_ray = intrinsics[ray_camera]
            directions_cam = pixel_to_ray_direction(pixels.to(dtype)[:, None, :], per_ray)[:, 0]
            c2w_rays = c2w[ray_camera]
            directions = (c2w_rays[:, :, :3] @ directions_cam[:, :, None])[..., 0]
            origins = c2w_rays[:, :, 3]
            # nerfstudio's directions_norm is |(a, b, 1)| of the unnormalized camera direction = 1 / d_z; its fisheye
            # directions are unit vectors already (norm 1).
            if intrinsics.is_fisheye:
                directions_norm = torch.ones_like(directions_cam[:, 2:3])
            else:
                directions_norm = 1.0 / directions_cam[:, 2:3]
        return origins, directions, directions_norm

    def apply_to_raybundle(self, raybundle: RayBundle) -> None:
        """Replace training rays by rays through the same pixels of the refined cameras (pose AND intrinsics)."""
        if not self.enabled:
            return
        assert raybundle.camera_indices is not None
        camera_indices = raybundle.camera_indices.reshape(-1)
        pixels = None if raybundle.metadata is None else raybundle.metadata.get(PIXEL_KEY)
        if pixels is None:
            self._apply_pose_only(raybundle, camera_indices)
            return
        origins, directions, directions_norm = self.regenerate_rays(
            camera_indices, pixels.reshape(-1, 2), dtype=raybundle.origins.dtype
        )
        shape = raybundle.origins.shape
        with torch.no_grad():
            cameras, ray_camera = torch.unique(camera_indices.to(self.precond.device), return_inverse=True)
            refined = self.refined_intrinsics(cameras=cameras)
            base = self.base_intrinsics[cameras]
            focal_ratio = base[:, 0] * base[:, 1] / (refined.fx * refined.fy)
        raybundle.origins = origins.reshape(shape)
        raybundle.directions = directions.reshape(shape)
        # Cone footprints shrink with the focal length; nerfacto ignores them, other fields may not.
        raybundle.pixel_area = raybundle.pixel_area * focal_ratio[ray_camera].to(raybundle.pixel_area).reshape(
            raybundle.pixel_area.shape
        )
        if "directions_norm" in raybundle.metadata:
            raybundle.metadata["directions_norm"] = directions_norm.reshape(raybundle.metadata["directions_norm"].shape)

    def _apply_pose_only(self, raybundle: RayBundle, camera_indices: Tensor) -> None:
        """Rays without pixel coordinates (a stock data manager): only the pose refinement can be applied."""
        if not self._warned_no_pixels:
            warnings.warn(
                f"ray bundle carries no '{PIXEL_KEY}' metadata (use S2CampDataManagerConfig): intrinsics refinement "
                "has no effect on these rays, only the pose is refined",
                stacklevel=2,
            )
            self._warned_no_pixels = True
        dtype = raybundle.origins.dtype
        refined = self.refined_c2w()[camera_indices].to(dtype)
        base = self.base_c2w_cv[camera_indices].to(dtype)
        world_rotation = refined[:, :, :3] @ base[:, :, :3].transpose(-1, -2)
        shape = raybundle.origins.shape
        directions = (world_rotation @ raybundle.directions.reshape(-1, 3)[:, :, None])[..., 0]
        offset = (raybundle.origins.reshape(-1, 3) - base[:, :, 3])[:, :, None]
        raybundle.origins = (refined[:, :, 3] + (world_rotation @ offset)[..., 0]).reshape(shape)
        raybundle.directions = directions.reshape(shape)

    def train_camera_raybundle(self, index: int, downscale: int = 1) -> RayBundle:
        """Full-image rays [H, W] of training camera ``index`` through its refined camera, skew included.

        nerfstudio's Cameras cannot represent skew, so rendering a refined training view goes through here.
        """
        self._require_cameras()
        width = int(self.base_intrinsics[index, 7]) // downscale
        height = int(self.base_intrinsics[index, 8]) // downscale
        device = self.precond.device
        ys, xs = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
        pixels = torch.stack([xs + 0.5, ys + 0.5], dim=-1).reshape(-1, 2).to(torch.float32) * downscale
        camera_indices = torch.full((pixels.shape[0],), index, dtype=torch.long, device=device)
        with torch.no_grad():
            origins, directions, directions_norm = self.regenerate_rays(camera_indices, pixels)
        refined = self.refined_intrinsics().detach()
        pixel_area = torch.full_like(directions_norm, float(downscale**2 / (refined.fx[index] * refined.fy[index])))
        return RayBundle(
            origins=origins.reshape(height, width, 3),
            directions=directions.reshape(height, width, 3),
            pixel_area=pixel_area.reshape(height, width, 1),
            camera_indices=camera_indices.reshape(height, width, 1),
            metadata={"directions_norm": directions_norm.reshape(height, width, 1)},
        )

    # ------------------------------------------------------------------------------------------------- cameras
    def apply_to_camera(self, camera: Cameras) -> Tensor:
        """Refined OpenGL c2w [1, 3, 4] of a training camera (nerfstudio's contract: used by its exporter).

        Only cameras whose metadata has "cam_idx" (a training-camera index, as nerfstudio sets it) are changed;
        viewer cameras are returned unchanged. ``refine_cameras`` also returns the refined intrinsics.
        """
        if not self.enabled or camera.metadata is None or "cam_idx" not in camera.metadata:
            return camera.camera_to_worlds
        correction = self(torch.tensor([int(camera.metadata["cam_idx"])], dtype=torch.long))
        c2w = camera.camera_to_worlds.reshape(-1, 3, 4)
        correction = correction.to(c2w)
        rotation = c2w[:, :, :3] @ correction[:, :, :3]
        translation = c2w[:, :, 3:] + c2w[:, :, :3] @ correction[:, :, 3:]
        return torch.cat([rotation, translation], dim=-1)

    @torch.no_grad()
    def refine_cameras(self, cameras: Cameras, indices: Tensor | None = None) -> Cameras:
        """nerfstudio Cameras of the training cameras ``indices`` with refined pose, fx, fy, cx, cy and distortion
        (``nerfstudio_distortion``: nerfstudio's [k1, k2, k3, k4, p1, p2] meaning).

        Skew is not representable in nerfstudio's Cameras and is dropped here (a warning says so when nonzero);
        ``train_camera_raybundle`` renders with it.
        """
        self._require_cameras()
        indices = torch.arange(self.num_cameras) if indices is None else indices.reshape(-1).cpu()
        deltas = self.camera_deltas()
        intrinsics = self.refined_intrinsics(deltas)[indices.to(self.precond.device)]
        if bool((intrinsics.skew.abs() > 1e-6).any()):
            warnings.warn("refined skew is dropped: nerfstudio Cameras cannot represent skew", stacklevel=2)
        c2w = self.refined_c2w(deltas, opengl=True)[indices.to(self.precond.device)]
        selected = cameras[indices]
        distortion = nerfstudio_distortion(intrinsics).cpu()
        device = selected.device
        return Cameras(
            camera_to_worlds=c2w.to(device=device, dtype=torch.float32),
            fx=intrinsics.fx[:, None].to(device=device, dtype=torch.float32),
            fy=intrinsics.fy[:, None].to(device=device, dtype=torch.float32),
            cx=intrinsics.cx[:, None].to(device=device, dtype=torch.float32),
            cy=intrinsics.cy[:, None].to(device=device, dtype=torch.float32),
            width=selected.width,
            height=selected.height,
            distortion_params=distortion.to(device=device, dtype=torch.float32),
            camera_type=selected.camera_type,
            times=selected.times,
            metadata=selected.metadata,
        )

    # ------------------------------------------------------------------------------------------------- refresh
    @torch.no_grad()
    def refresh(self, step: int, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Recompute P from the current refined intrinsics without moving the cameras (paper sec. 4).

        The latent and Adam's moments are re-expressed in the new basis by ``core.preconditioner.reexpress_latent``
        (phi = P^-1 phi_hat is unchanged; m_new = M^-T m_old exactly, v mapped with the elementwise square of M^-T,
        the step count kept, so no full-size step follows a refresh as it would after a state reset).

        The pose columns of the new P are the local-twist Jacobian at the refined pose; for the accumulated twist
        xi the exact Jacobian differs by SE(3)'s right Jacobian, the identity up to O(|xi|) (small corrections).
        If the refined intrinsics are invalid (e.g. distortion folding inside the image) P is kept and a warning
        says why, so a refresh never stops training.
        """
        self._require_cameras()
        try:
            self._recompute_preconditioner(optimizer)
        except ValueError as error:
            warnings.warn(f"preconditioner refresh at step {step} skipped, P kept: {error}", stacklevel=2)
            return
        self._stale_preconditioner = None
        self.last_refresh_step.fill_(step)
        self.num_refreshes.add_(1)

    @torch.no_grad()
    def _recompute_preconditioner(self, optimizer: torch.optim.Optimizer | None) -> None:
        """P at the current refined intrinsics, the latents and Adam's moments re-expressed so that no camera moves;
        ValueError (nothing changed) if the refined intrinsics admit no P."""
        if self.config.precondition and self.enabled and self.shared:
            self._recompute_shared(optimizer)
        elif self.config.precondition and self.enabled:
            device = self.precond.device
            intrinsics = self.refined_intrinsics().detach()
            result = compute_preconditioner(
                intrinsics, self.layout, self.config.sampling, self.config.damping, ranges=self._sampling_ranges()
            )
            old = Preconditioner(matrix=self.precond, inverse=self.precond_inv, gram=self.gram, num_valid=None)
            new = Preconditioner(
                matrix=result.matrix.to(device), inverse=result.inverse.to(device), gram=result.gram, num_valid=None
            )
            latent = self.whitened_delta
            state = optimizer.state.get(latent) if optimizer is not None else None
            reexpress_latent(latent, old, new, state)
            self.precond.copy_(new.matrix)
            self.precond_inv.copy_(new.inverse)
            self.gram.copy_(result.gram.to(device))
        self.precond_base_intrinsics.copy_(self.base_intrinsics)
        self.precond_proxy_range.copy_(self.proxy_range)

    def _sampling_ranges(self, images: Tensor | None = None) -> Tensor | None:
        """The stored per-image proxy range for ``compute_preconditioner`` (of ``images`` only if given); None when
        the config fixes the range (the sampling's own, so a fixed range computes P exactly as it always did)."""
        if not self.config.sampling.auto:
            return None
        return (self.proxy_range if images is None else self.proxy_range[images]).cpu()

    def _recompute_shared(self, optimizer: torch.optim.Optimizer | None) -> None:
        """The shared-intrinsics recomputation: T per physical camera from its refined intrinsics, latents
        re-expressed without moving any camera (``core.shared_intrinsics``); ValueError if no T exists."""
        device = self.precond.device
        first = self._first_image_of_each_camera()
        intrinsics = self.refined_intrinsics().detach()[first]
        result = compute_shared_preconditioner(
            intrinsics, self.layout, self.config.sampling, self.config.damping, ranges=self._sampling_ranges(first)
        )
        matrix, inverse = result.matrix.to(device), result.inverse.to(device)
        states = [None, None]
        if optimizer is not None:
            states = [optimizer.state.get(self.whitened_delta), optimizer.state.get(self.whitened_intrinsics)]
        reexpress_shared_latents(
            self.whitened_delta, self.whitened_intrinsics, self.camera_of_image, self.precond[first],
            self.precond_inv[first], matrix, inverse, *states,
        )  # fmt: skip
        self.precond.copy_(matrix[self.camera_of_image])
        self.precond_inv.copy_(inverse[self.camera_of_image])
        self.gram.copy_(result.gram.to(device)[self.camera_of_image])

    def should_refresh(self, step: int) -> bool:
        every = self.config.refresh_every
        return every > 0 and step > 0 and step % every == 0 and step != int(self.last_refresh_step)

    # ---------------------------------------------------------------------------------------- losses, metrics
    def get_loss_dict(self, loss_dict: dict) -> None:
        """Optional L2 penalties on the raw pose deltas (off by default)."""
        if not self.enabled or (self.config.trans_l2_penalty == 0 and self.config.rot_l2_penalty == 0):
            return
        phi = self.camera_deltas()
        loss_dict["camera_opt_regularizer"] = (
            phi[:, :3].norm(dim=-1).mean() * self.config.trans_l2_penalty
            + phi[:, 3:6].norm(dim=-1).mean() * self.config.rot_l2_penalty
        ).to(torch.float32)

    def get_metrics_dict(self, metrics_dict: dict) -> None:
        """Size of the current deltas (raw units: scene units, degrees, pixels)."""
        if not self.enabled or not self.has_cameras:
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


def _span(values: Tensor) -> str:
    low, high = float(values.min()), float(values.max())
    return f"{low:.3f}" if low == high else f"{low:.3f}..{high:.3f}"


__all__ = [
    "PIXEL_KEY",
    "TRAIN_CAMERA_KEY",
    "S2CampCameraOptimizer",
    "S2CampCameraOptimizerConfig",
    "camera_model_of",
    "group_identical_intrinsics",
    "intrinsics_from_cameras",
    "nerfstudio_distortion",
    "projection_of",
]
