"""Preconditioned camera refinement in plain PyTorch (paper sec. 4): ``CameraRefiner``, free of any framework.

The refiner holds whitened deltas phi_hat and maps them to camera-parameter deltas phi = P^-1 phi_hat (paper eq. 15),
with P = (Sigma + damping)^(1/2) computed from deterministic proxy points in each camera's frustum (paper eq. 20).
Cameras are the core's: ``Intrinsics``, OpenCV camera-to-world poses [n, 3, 4] and the physical camera of each image.
Refined camera = base camera plus phi: the pose c2w' = c2w exp(xi) with the local twist xi in the OpenCV camera frame
(``core.camera``), the intrinsics the additive residual update Phi' = Phi + dPhi (paper sec. 4) of the columns the
``ParameterLayout`` enables (K = 12, 14 or 15 with the "all" preset, by the cameras' model, ``camera_model_of``).

Two latent layouts share one interface (``core.latent_layout``: ``PerImageIntrinsics``, ``PerCameraIntrinsics``):
intrinsics refined per image (CamP's way, P the symmetric root per image, paper eq. 20), or shared by the images of one
physical camera (a pose latent per image, an intrinsics latent per camera, P the block-triangular factor of
``core.shared_intrinsics``).

P is recomputed (``refresh``) from the current refined intrinsics; the latent is re-expressed so the cameras do not
move, phi_hat_new = P_new P_old^-1 phi_hat_old, and Adam's moments follow (``core.preconditioner.reexpress_latent``).
The proxy points' radial range [t_near, t_far] is chosen once per physical camera from the scene's points
(``core.proxy_range``) unless the sampling config sets it; every refresh uses that stored range.

Checkpoints (``state_dict``) hold phi_hat, P, P^-1, the refresh schedule and the fingerprint of P: the base intrinsics
and proxy range it was computed for. Loading onto the same cameras continues bit-identically; loading onto other
cameras or another range flags P as stale (``check_fingerprint``), and ``recompute_stale_preconditioner`` recomputes it
and re-expresses the latent and Adam's moments before the next step instead of using a stale P.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from s2camp_ns.core.camera import (
    PARAMETER_NAMES,
    TENSOR_FIELDS,
    Intrinsics,
    ParameterLayout,
    camera_model_of,
    delta_field_map,
    distortion_form,
    full_delta,
    opengl_to_opencv,
    se3_exp,
)
from s2camp_ns.core.distortion import undistortion_iterations
from s2camp_ns.core.latent_layout import LatentLayout, PerCameraIntrinsics, PerImageIntrinsics, PriorBlock
from s2camp_ns.core.preconditioner import DampingConfig, SamplingConfig
from s2camp_ns.core.proxy_range import ProxyRanges, proxy_ranges
from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS
from s2camp_ns.core.track_loss import TrackTerm, photometric_weight, refine_points, track_cost
from s2camp_ns.core.track_prior import (
    TrackPriorEvidence,
    apply_track_prior,
    inverse_radius,
    place_at_anchor,
    pose_radius,
    span,
)

ROTATION_COLUMNS = [3, 4, 5]
"""The twist's rotation columns: (rho_x, rho_y, rho_z, omega_x, omega_y, omega_z)."""


class CameraRefiner(nn.Module):
    """Whitened camera-parameter deltas, their preconditioner P and its refresh, the track prior and the gauge fix.

    ``parameters``: the refined groups (``ParameterLayout.from_preset``); ``per_camera_intrinsics``: share the
    intrinsics among the images of a physical camera (``set_camera_groups``) when the layout refines any;
    ``precondition`` False: P = I (the "no preconditioning" ablation); ``photometric`` False: the latent's gradient is
    zeroed (the cameras stay at the track prior's anchor); ``enabled`` False: no latent, every delta zero;
    ``frozen_images``: images whose deltas are held at zero. Call ``set_cameras`` before use.
    """

    def __init__(
        self,
        num_images: int,
        parameters: str = "all",
        *,
        per_camera_intrinsics: bool = True,
        precondition: bool = True,
        sampling: SamplingConfig | None = None,
        damping: DampingConfig | None = None,
        photometric: bool = True,
        enabled: bool = True,
        frozen_images: Int[Tensor, " f"] | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__()
        self._caches: dict[str, tuple[tuple, object]] = {}
        self.num_images = num_images
        self.preset = parameters
        self.layout = ParameterLayout.from_preset(parameters)
        self.sampling = sampling or SamplingConfig()
        self.damping = damping or DampingConfig()
        self.precondition = precondition
        self.photometric = photometric
        self.enabled = enabled
        k = self.layout.num_params
        self.shared = enabled and per_camera_intrinsics and k > NUM_POSE_PARAMS
        self.latent_layout: LatentLayout = PerCameraIntrinsics() if self.shared else PerImageIntrinsics()
        if enabled:
            self.whitened_delta = self._latent(torch.zeros(num_images, self.latent_layout.pose_columns(k)), device)
        if self.shared:  # one physical camera per image until ``set_camera_groups`` says otherwise
            self.whitened_intrinsics = self._latent(torch.zeros(num_images, k - NUM_POSE_PARAMS), device)
        self._register_state(k, device)
        self.frozen_images = frozen_images
        self.projection = "perspective"
        self.distortion_terms: tuple[str, ...] = ()
        """The refined cameras' distortion form (``core.camera.distortion_form``), decided in ``set_cameras``."""
        self.newton_iterations = 0
        """Newton steps that undistort them (``core.distortion.undistortion_iterations``), taken at every refresh."""
        self.last_refresh = -1
        """``last_refresh_step`` on the host: the refresh schedule reads it without a device synchronisation."""
        self.gram_known = False
        """Whether ``gram`` holds a computed Gram matrix (a refresh with preconditioning wrote it)."""
        self.num_physical_cameras = num_images
        """Physical cameras C (``camera_of_image`` holds 0..C-1), on the host."""
        self.proxy_ranges: ProxyRanges | None = None
        self.groups_known = False
        self.has_cameras = False
        self.has_track_prior = False
        self.track_term: TrackTerm | None = None
        self._photometric_mse: Tensor | None = None  # the track loss's running photometric loss (not saved)
        self._track_points: Tensor | None = None  # the track loss's free points (candidate; not saved)
        self.prior_intrinsics_only = False
        """Benchmark candidate: the prior's proximal step on the shared intrinsics' latent only."""
        self.pose_prior_exponent = 1.0
        """The pose prior's radius r_i / (2 O_i)^(e / 2) (``core.track_prior.pose_radius``): 1 the standard error."""
        self.cameras_required = "CameraRefiner.set_cameras must be called before use"
        """The RuntimeError's message when the cameras are needed and not set (a framework names its own call)."""
        # Why a loaded P does not fit the base cameras (None when it does): it is recomputed before the next training
        # step (``recompute_stale_preconditioner``), once Adam's moments are loaded too.
        self._stale_preconditioner: str | None = None

    def _register_state(self, k: int, device: torch.device | str) -> None:
        """The buffers: P, P^-1 and the schedule (saved: a resumed run continues identically); the base cameras, the
        Gram, the proxy range and the track prior (from the scene on every run, not saved); P's fingerprint (saved)."""
        n = self.num_images
        eye = torch.eye(k, dtype=torch.float64, device=device).expand(n, k, k).clone()
        self.register_buffer("precond", eye.clone())
        self.register_buffer("precond_inv", eye.clone())
        self.register_buffer("last_refresh_step", torch.tensor(-1, dtype=torch.long, device=device))
        self.register_buffer("num_refreshes", torch.tensor(0, dtype=torch.long, device=device))
        # The undistortion's Newton steps (``newton_iterations``), saved: a resumed run undistorts as it did (-1: not
        # taken yet).
        self.register_buffer("undistortion_steps", torch.tensor(-1, dtype=torch.long, device=device))
        base_c2w = torch.zeros(n, 3, 4, dtype=torch.float64, device=device)
        self.register_buffer("base_c2w_cv", base_c2w, persistent=False)
        base = torch.zeros(n, len(TENSOR_FIELDS), dtype=torch.float64, device=device)
        self.register_buffer("base_intrinsics", base, persistent=False)
        # The base intrinsics P was computed for: P depends on the intrinsics only (the Jacobian is taken in the
        # camera frame), so the base poses need no record.
        self.register_buffer("precond_base_intrinsics", torch.zeros_like(self.base_intrinsics))
        # Undamped Gram Sigma of the last refresh (zero until one computes it).
        self.register_buffer("gram", torch.zeros_like(eye), persistent=False)
        # Contracted proxy range [t_near, t_far] per image (equal for the images of a physical camera): this run's,
        # and the one P was computed with (saved with P).
        no_range = torch.zeros(n, 2, dtype=torch.float64, device=device)
        self.register_buffer("proxy_range", no_range.clone(), persistent=False)
        self.register_buffer("precond_proxy_range", no_range.clone())
        # Physical camera of each image (0..C-1); one camera per image until ``set_camera_groups`` says otherwise.
        self.register_buffer("camera_of_image", torch.arange(n, device=device), persistent=False)
        # Track prior radius per image in whitened units and per physical camera (NaN = no prior), and its anchor:
        # the deltas phi (the layout's columns) where the tracks put each camera; zero = the given camera.
        no_prior = torch.full((n,), float("nan"), dtype=torch.float64, device=device)
        self.register_buffer("prior_radius", no_prior, persistent=False)
        self.register_buffer("prior_radius_intrinsics", no_prior.clone(), persistent=False)
        anchor = torch.zeros(n, k, dtype=torch.float64, device=device)
        self.register_buffer("prior_anchor", anchor, persistent=False)

    # ----------------------------------------------------------------------------------------------------- setup
    def _latent(self, values: Tensor, device: torch.device | str) -> nn.Parameter:
        """A latent parameter on ``device``; with ``photometric`` False its gradient is zeroed (Adam steps by zero)."""
        latent = nn.Parameter(values.to(device))
        if not self.photometric:
            latent.register_hook(torch.zeros_like)
        return latent

    def first_image_of_each_camera(self) -> Int[Tensor, " c"]:
        index = self.camera_of_image
        first = torch.full((self.num_physical_cameras,), self.num_images, dtype=torch.long, device=index.device)
        return first.scatter_reduce_(0, index, torch.arange(self.num_images, device=index.device), "amin")

    def set_camera_groups(self, camera_ids: Tensor | list[int]) -> None:
        """Which images share a physical camera (any integer ids, one per image; relabelled 0..C-1 in order of first
        appearance). With shared intrinsics this sizes the intrinsics latent [C, m]; call it before the optimizers
        are built."""
        ids = torch.as_tensor(camera_ids).reshape(-1)
        if ids.shape[0] != self.num_images:
            raise ValueError(f"camera_ids must hold {self.num_images} entries (one per image), got {ids.shape[0]}")
        _, first = torch.unique(ids, return_inverse=True)
        order = {}
        labels = [order.setdefault(int(value), len(order)) for value in first.tolist()]
        self.camera_of_image = torch.tensor(labels, dtype=torch.long, device=self.precond.device)
        self.num_physical_cameras = len(order)
        self.groups_known = True
        if self.shared:
            m = self.layout.num_params - NUM_POSE_PARAMS
            existing = getattr(self, "whitened_intrinsics", None)
            if existing is None or existing.shape != (len(order), m):
                self.whitened_intrinsics = self._latent(torch.zeros(len(order), m), self.precond.device)

    def set_camera_model(self, camera_model: str) -> None:
        """Use the layout of the cameras' COLMAP model (``camera_model_of``): the "all" preset refines its distortion
        coefficients. Resizes the latents, P, P^-1 and Sigma to the layout's K; a no-op when the layout is unchanged
        (RADIAL, the default). Call it before an optimizer sees the parameters; ``set_cameras`` calls it again."""
        layout = ParameterLayout.from_preset(self.preset, camera_model)
        if layout == self.layout:
            return
        self.layout = layout
        k = layout.num_params
        device = self.precond.device
        if self.enabled and self.shared:
            m = k - NUM_POSE_PARAMS
            self.whitened_intrinsics = self._latent(torch.zeros(self.num_physical_cameras, m), device)
        elif self.enabled:
            self.whitened_delta = self._latent(torch.zeros(self.num_images, k), device)
        eye = torch.eye(k, dtype=torch.float64, device=device).expand(self.num_images, k, k).clone()
        self.precond, self.precond_inv, self.gram = eye.clone(), eye.clone(), torch.zeros_like(eye)

    def set_cameras(
        self,
        c2w: Float[Tensor, "n 3 4"],
        intrinsics: Intrinsics,
        points: Float[Tensor, "m 3"] | None = None,
        groups: Int[Tensor, " n"] | None = None,
        stacklevel: int = 1,
    ) -> ProxyRanges | None:
        """Store the base cameras (OpenCV c2w, float64), choose the proxy range from the scene's ``points`` and
        compute the initial P, or check a P loaded before (``check_fingerprint``).

        ``groups``: physical-camera ids to use where ``set_camera_groups`` was not called (default: images with
        identical intrinsics share one). Returns the proxy ranges chosen from the points (None: the fixed range).
        A warning names the caller ``stacklevel`` frames up (1: the caller of ``set_cameras``).
        """
        if c2w.shape[0] != self.num_images:
            raise ValueError(f"cameras must hold {self.num_images} training cameras, got {c2w.shape[0]}")
        if groups is None:
            groups = torch.unique(intrinsics.tensors().to(torch.float64), dim=0, return_inverse=True)[1]
        device = self.precond.device
        self.base_c2w_cv = c2w.to(torch.float64).to(device)
        base = intrinsics.tensors().to(device)
        self.projection = intrinsics.model
        self.set_camera_model(camera_model_of(intrinsics))
        if self.shared and not self.groups_known:
            self.set_camera_groups(groups)
        self.base_intrinsics = self.latent_layout.base(self, base)
        self.distortion_terms = distortion_form(intrinsics, self.layout if self.enabled else None)
        chosen, per_image = self.choose_proxy_range(c2w, intrinsics, points, groups)
        self.proxy_range = per_image.to(device)
        self.has_cameras = True
        if int(self.last_refresh_step) < 0:
            self.refresh(step=0, stacklevel=stacklevel + 1)
        else:  # a checkpoint was loaded before the cameras were known
            self.after_load()
            self.check_fingerprint(stacklevel=stacklevel + 1)
        return chosen

    def choose_proxy_range(
        self, c2w: Tensor, intrinsics: Intrinsics, points: Tensor | None, groups: Tensor
    ) -> tuple[ProxyRanges | None, Float[Tensor, "n 2"]]:
        """Contracted [t_near, t_far] per image: chosen per physical camera from the points it sees
        (``core.proxy_range.proxy_ranges``, its images pooled) where the sampling config leaves an end unset, the
        config's range otherwise. Physical cameras: ``camera_of_image`` when known, else ``groups``. Returns the
        chosen per-camera ranges (None when fixed) and the range per image."""
        sampling = self.sampling
        n = self.num_images
        if not (sampling.auto and self.enabled and self.precondition):  # P = I needs no range
            return None, torch.tensor(sampling.fixed_range(), dtype=torch.float64).expand(n, 2).clone()
        groups = (self.camera_of_image if self.groups_known or self.shared else groups).cpu()
        c2w = c2w.detach().to(torch.float64).cpu()
        points = None if points is None else torch.as_tensor(points).detach().to(torch.float64).cpu()
        intrinsics = intrinsics.detach().to(device="cpu", dtype=torch.float64)
        ranges = proxy_ranges(
            points, c2w, intrinsics, groups, sampling.auto_range, sampling.t_near, sampling.t_far, sampling.radial
        )
        self.proxy_ranges = ranges
        return ranges, ranges.stacked()[groups]

    def _take_newton_iterations(self) -> None:
        """The undistortion's Newton steps for the current refined cameras (``undistortion_iterations``, with room
        for the refinement until the next refresh): taken when the cameras are set and at every refresh."""
        self.newton_iterations = 0
        if self.distortion_terms:
            with torch.no_grad():
                refined = self.refined_intrinsics().detach()
            # Images of one physical camera share their refined intrinsics: one of each is enough.
            self.newton_iterations = undistortion_iterations(refined[self.first_image_of_each_camera()])
        self.undistortion_steps.fill_(self.newton_iterations)

    def require_cameras(self) -> None:
        if not self.has_cameras:
            raise RuntimeError(self.cameras_required)

    def base_intrinsics_struct(self) -> Intrinsics:
        return Intrinsics.from_tensors(self.base_intrinsics, model=self.projection)

    # ------------------------------------------------------------------------------------------- refined cameras
    def _cached(self, name: str, key: tuple, build):
        """``build()``, kept under ``name`` until ``key`` changes: keys name the tensors a value is derived from by
        identity and in-place version (``Tensor._version``), so a refresh, a load or a reassignment rebuilds it and a
        training step reads it without recomputing or synchronising."""
        entry = self._caches.get(name)
        if entry is None or entry[0] != key:
            entry = (key, build())
            self._caches[name] = entry
        return entry[1]

    @staticmethod
    def _key(*tensors: Tensor | None) -> tuple:
        return tuple((id(t), t._version, t.device) if t is not None else None for t in tensors)

    def _expansion(self) -> Float[Tensor, "k 16"]:
        """[K, 16] selection matrix: phi @ E scatters the layout's K columns into ``PARAMETER_NAMES``' 16 (exactly)."""
        layout, device = self.layout, self.precond.device

        def build() -> Tensor:
            return layout.expand(torch.eye(layout.num_params, dtype=torch.float64, device=device))

        return self._cached("expansion", (layout, device), build)

    @property
    def frozen_images(self) -> Int[Tensor, " f"] | None:
        """Images whose deltas are held at zero (None: none)."""
        return self._frozen_images

    @frozen_images.setter
    def frozen_images(self, images: Int[Tensor, " f"] | None) -> None:
        self._frozen_images = images
        self._caches.pop("trainable", None)
        mask = self._trainable_mask()
        self.num_trainable = self.num_images if images is None else int(mask.sum())

    def _trainable_mask(self) -> Float[Tensor, "n 1"]:
        """1 for trainable images, 0 for frozen ones, float64 (cached per device)."""

        def build() -> Tensor:
            keep = torch.ones(self.num_images, 1, dtype=torch.float64, device=self.precond.device)
            if self.frozen_images is not None:
                keep[self.frozen_images.to(keep.device)] = 0.0
            return keep

        return self._cached("trainable", (self.precond.device,), build)

    def deltas(self, images: Int[Tensor, " m"] | slice | None = None) -> Float[Tensor, "m 16"]:
        """Camera-parameter deltas phi = P^-1 phi_hat (paper eq. 15), all 16 columns, float64, differentiable: of
        every image, or of ``images`` (an index tensor or a slice). One batched product for every image: a training
        step computes them once and gathers what its rays need."""
        if not self.enabled:
            count = self.num_images if images is None else self.precond[images].shape[0]
            return self.precond.new_zeros(count, len(PARAMETER_NAMES))
        precond_inv = self.precond_inv
        if isinstance(images, Tensor):
            images = images.to(self.precond.device)
        if images is not None:
            precond_inv = precond_inv[images]
        latent = self.latent_layout.latent(self, images)  # [m, K]
        phi = (precond_inv @ latent[..., None])[..., 0] @ self._expansion()  # [m, 16]
        if self.frozen_images is not None:
            mask = self._trainable_mask()
            phi = phi * (mask if images is None else mask[images])
        return phi

    @property
    def intrinsics_form(self) -> dict:
        """The refined cameras' declared form, ``Intrinsics`` keywords (``distortion_terms``, ``newton_iterations``)."""
        return {"distortion_terms": self.distortion_terms, "newton_iterations": self.newton_iterations}

    def refined_fields(
        self, deltas: Tensor | None = None, images: Int[Tensor, " m"] | slice | None = None
    ) -> Float[Tensor, "m 13"]:
        """The refined intrinsics as ``Intrinsics.tensors`` columns, Phi' = Phi + dPhi (paper sec. 4) in one product
        (``core.camera.delta_field_map``), float64, differentiable: of every image, or of ``images`` (``deltas`` then
        holds theirs)."""
        self.require_cameras()
        deltas = self.deltas(images) if deltas is None else full_delta(deltas)
        base = self.base_intrinsics
        if images is not None:
            base = base[images.to(base.device) if isinstance(images, Tensor) else images]
        field_map = self._cached("field_map", (base.device,), lambda: delta_field_map(base.dtype, base.device))
        return torch.addmm(base, deltas, field_map)

    def refined_intrinsics(
        self, deltas: Tensor | None = None, images: Int[Tensor, " m"] | slice | None = None
    ) -> Intrinsics:
        """Intrinsics Phi' = Phi + dPhi (paper sec. 4), float64, differentiable, with the refined cameras' declared
        form (``intrinsics_form``): of every image, or of ``images`` (``deltas`` then holds theirs)."""
        fields = self.refined_fields(deltas, images)
        return Intrinsics.from_tensors(fields, model=self.projection, **self.intrinsics_form)

    def refined_c2w(
        self, deltas: Tensor | None = None, opengl: bool = False, images: Int[Tensor, " m"] | slice | None = None
    ) -> Float[Tensor, "m 3 4"]:
        """Refined c2w' = c2w exp(xi), float64, OpenCV frame unless ``opengl``: of every image, or of ``images``
        (``deltas`` then holds theirs)."""
        self.require_cameras()
        deltas = self.deltas(images) if deltas is None else deltas
        base = self.base_c2w_cv
        if images is not None:
            base = base[images.to(base.device) if isinstance(images, Tensor) else images]
        delta = se3_exp(deltas[:, :6])  # [m, 3, 4]
        rotation = base[:, :, :3] @ delta[:, :, :3]
        translation = torch.baddbmm(base[:, :, 3:], base[:, :, :3], delta[:, :, 3:])
        c2w = torch.cat([rotation, translation], dim=-1)
        return opengl_to_opencv(c2w) if opengl else c2w

    # ------------------------------------------------------------------------------------- track prior, gauge
    def set_track_prior(self, evidence: TrackPriorEvidence | None) -> None:
        """The track prior's anchor and scale per image (``core.track_prior``); None: no prior. Scales are stored in
        whitened units (pixels divided by max(W, H), the Gram matrix's pixel unit, paper eq. 5), the shared
        intrinsics' as the standard error of their pooled fit, the poses' as the standard error of each image's fit
        (``core.track_prior.pose_radius``). Every image with a prior starts at its anchor (``place_at_anchor``), the
        others where they are (the given camera at set-up)."""
        self.require_cameras()
        device = self.precond.device
        radius = torch.full((self.num_images,), float("nan"), dtype=torch.float64, device=device)
        anchor = torch.zeros(self.num_images, self.layout.num_params, dtype=torch.float64, device=device)
        observations = None
        if evidence is not None:
            anchor = evidence.anchor.to(device)
            observations = None if evidence.observations is None else evidence.observations.to(device)
            if evidence.rms_px is not None:
                radius = evidence.rms_px.to(device) / self.base_intrinsics_struct().image_scale()
        self.prior_radius = pose_radius(radius, observations, self.pose_prior_exponent)
        finite = torch.isfinite(radius)
        keep = self.latent_layout.anchor_mask(self, finite)
        self.prior_anchor = torch.where(keep, anchor, torch.zeros_like(anchor))
        self.has_track_prior = bool(finite.any())
        self.prior_radius_intrinsics = self.latent_layout.intrinsics_radius(self, radius, observations)
        if self.enabled:  # every camera with tracks starts where they put it, the others as given
            for block in self.latent_layout.prior_blocks(self):
                place_at_anchor(block.latent, block.anchor, block.radius)

    def prior_anchor_latents(self) -> tuple[Float[Tensor, "n j"], Float[Tensor, "c m"] | None]:
        """The anchor in the whitened latent under the current P (phi_hat = P phi, paper eq. 15): the pose latent
        per image (all K columns per image) and, with shared intrinsics, the intrinsics latent per physical camera."""
        blocks = self.latent_layout.prior_blocks(self)
        return blocks[0].anchor, blocks[1].anchor if len(blocks) > 1 else None

    def _prior_steps(self) -> list[tuple[nn.Parameter, Tensor, Tensor]]:
        """(latent, its anchor in the latent's dtype, 1 / radius) of each latent under the prior, derived once per P
        and prior (``_cached``): the training step's proximal step reads them as they are."""
        # The latents by identity alone: every optimizer step changes them in place.
        latents = (id(getattr(self, "whitened_delta", None)), id(getattr(self, "whitened_intrinsics", None)))
        key = self._key(self.precond, self.prior_anchor, self.prior_radius, self.prior_radius_intrinsics) + latents

        def build() -> list[tuple[nn.Parameter, Tensor, Tensor]]:
            blocks = self.latent_layout.prior_blocks(self)
            if self.prior_intrinsics_only and len(blocks) > 1:
                blocks = blocks[1:]
            dtype = blocks[0].latent.dtype
            return [(b.latent, b.anchor.to(dtype), inverse_radius(b.radius).to(dtype)) for b in blocks]

        return self._cached("prior_steps", key + (self.prior_intrinsics_only,), build)

    @torch.no_grad()
    def apply_track_prior(self, lr: float) -> None:
        """One proximal step of the track prior after an optimizer step of learning rate ``lr``
        (``core.track_prior.apply_track_prior``); images without tracks are untouched."""
        # A Python flag, not a look at the radii: no device synchronisation on the training step's path.
        if not self.enabled or not self.has_track_prior or lr <= 0:
            return
        for latent, anchor, inverse in self._prior_steps():
            apply_track_prior(latent, anchor, inverse, lr)

    def set_track_term(self, term: TrackTerm | None) -> None:
        """The tracks as a loss term (``core.track_loss``, a benchmark candidate), its tensors moved to the refiner's
        device once; None: none."""
        device = self.precond.device
        names = ("image", "points_cam", "pixels", "point", "points", "rotation", "center")
        on_device = {name: getattr(term, name).to(device) for name in names if getattr(term, name) is not None}
        self.track_term = None if term is None else replace(term, **on_device)
        self._track_points = None if self.track_term is None else self.track_term.points

    def track_loss(self, photometric_mse: Tensor, factor: float = 1.0) -> Float[Tensor, ""] | None:
        """The track term in the photometric loss's units, w sum_obs rho(s_o) (``core.track_loss`` eq. 1), with
        sigma_c^2 a running mean (100 steps) of the photometric loss ``photometric_mse`` and ``factor`` its
        likelihood's (1 for an MSE, 0.5 for an L1 loss); differentiable in the deltas; None without a term or when
        disabled. With the points free each call first steps them to their optimum at the current deltas
        (``core.track_loss.refine_points``; kept in memory, not in checkpoints)."""
        term = self.track_term
        if term is None or not self.enabled:
            return None
        mse = photometric_mse.detach().to(self.precond)
        running = self._photometric_mse
        self._photometric_mse = mse if running is None else 0.99 * running + 0.01 * mse
        weight = factor * photometric_weight(self._photometric_mse, term.num_pixels, term.noise_variance)
        deltas, intrinsics = self.deltas(), self.base_intrinsics_struct()
        if term.point is not None:
            self._track_points = refine_points(term, self._track_points, deltas, intrinsics)
        return weight * track_cost(term, deltas, intrinsics, self._track_points)

    @torch.no_grad()
    def remove_common_motion(self) -> None:
        """Subtract the mean over trainable images of the rotation part omega of the pose deltas phi, each in its
        own camera frame, from every image's, in the latent: phi_hat += P[:, :, c] d for the rotation columns c
        (paper eq. 15; with shared intrinsics the pose rows of the block-triangular P, so no intrinsics change).

        A rotation every camera makes at once is the similarity gauge in disguise, which the photometric loss does
        not see (docs/DESIGN-NOTES.md sec. 6). Everything else stays; a no-op when disabled or with fewer than
        three trainable images. With the track prior the rotation is measured from the prior's anchor: the tracks
        fix the world, so the rotation the anchors share is no gauge and stays."""
        if not self.enabled or self.num_trainable < 3:
            return
        latent = self.whitened_delta
        rows, weight, mask, anchor = self._gauge_terms()
        motion = (self.precond_inv[:, ROTATION_COLUMNS, :] @ self.latent_layout.latent(self, None)[..., None])[..., 0]
        if anchor is not None:
            motion = motion - anchor  # [n, 3]
        mean = weight @ motion  # [3]: the mean over trainable images
        latent.sub_(((rows @ mean[:, None])[..., 0] * mask).to(latent.dtype))

    def _gauge_terms(self) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """What ``remove_common_motion`` reads, derived once per P and prior (``_cached``): P's rotation columns on the
        pose latent's rows [n, pose columns, 3], the trainable images' averaging weights [n], their mask [n, 1], and
        the anchors' rotation [n, 3] (None without the prior)."""
        key = self._key(self.precond, self.prior_anchor) + (self.has_track_prior,)

        def build() -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
            columns = self.whitened_delta.shape[1]
            rows = self.precond[:, :columns, ROTATION_COLUMNS].to(torch.float64)
            mask = self._trainable_mask()
            anchor = self.layout.expand(self.prior_anchor)[:, ROTATION_COLUMNS] if self.has_track_prior else None
            return rows, mask[:, 0] / self.num_trainable, mask, anchor

        return self._cached("gauge", key, build)

    # ------------------------------------------------------------------------------------------------- refresh
    @torch.no_grad()
    def refresh(self, step: int, optimizer: torch.optim.Optimizer | None = None, stacklevel: int = 1) -> None:
        """Recompute P from the current refined intrinsics without moving the cameras (paper sec. 4).

        The latent and Adam's moments are re-expressed in the new basis by ``core.preconditioner.reexpress_latent``
        (phi = P^-1 phi_hat is unchanged; m_new = M^-T m_old exactly, v mapped with the elementwise square of M^-T,
        the step count kept, so no full-size step follows a refresh as it would after a state reset).

        The pose columns of the new P are the local-twist Jacobian at the refined pose; for the accumulated twist
        xi the exact Jacobian differs by SE(3)'s right Jacobian, the identity up to O(|xi|) (small corrections).
        If the refined intrinsics are invalid (e.g. distortion folding inside the image) P is kept and a warning
        (naming the caller ``stacklevel`` frames up) says why, so a refresh never stops training.
        """
        self.require_cameras()
        try:
            self._recompute_preconditioner(optimizer)
        except ValueError as error:
            message = f"preconditioner refresh at step {step} skipped, P kept: {error}"
            warnings.warn(message, stacklevel=stacklevel + 1)
            return
        self._stale_preconditioner = None
        self._record_refresh(step)

    def _record_refresh(self, step: int) -> None:
        self.last_refresh_step.fill_(step)
        self.last_refresh = step
        self.num_refreshes.add_(1)
        self._take_newton_iterations()

    @torch.no_grad()
    def _recompute_preconditioner(self, optimizer: torch.optim.Optimizer | None) -> None:
        """P at the current refined intrinsics, the latents and Adam's moments re-expressed so that no camera moves;
        ValueError (nothing changed) if the refined intrinsics admit no P. The fingerprint records the cameras."""
        if self.precondition and self.enabled:
            self.latent_layout.recompute(self, optimizer)
            self.gram_known = True
        self.precond_base_intrinsics.copy_(self.base_intrinsics)
        self.precond_proxy_range.copy_(self.proxy_range)

    def sampling_ranges(self, images: Tensor | None = None) -> Tensor | None:
        """The stored per-image proxy range for ``compute_preconditioner`` (of ``images`` only if given); None when
        the config fixes the range (the sampling's own, so a fixed range computes P exactly as it always did)."""
        if not self.sampling.auto:
            return None
        return (self.proxy_range if images is None else self.proxy_range[images]).cpu()

    # ---------------------------------------------------------------------------------------------- checkpoints
    def check_checkpoint_size(self, state_dict: dict, prefix: str) -> None:
        saved = state_dict.get(prefix + "precond")
        if saved is not None and saved.shape[0] != self.num_images:
            # torch would list a size mismatch per tensor without saying why; the cause is another scene or split.
            raise ValueError(
                f"the camera optimizer's checkpoint holds {saved.shape[0]} training cameras, but this model has "
                f"{self.num_images}: it is a checkpoint of another scene or of another train/eval split"
            )

    def mark_unrecorded_fingerprint(self, state_dict: dict, prefix: str, missing_keys: list[str]) -> bool:
        """After loading: a checkpoint without the fingerprint of its P (written before it was recorded) leaves it
        NaN, unknown. False when the checkpoint holds no P at all (the current one stands)."""
        if prefix + "precond" not in state_dict:
            return False
        for name in ("precond_base_intrinsics", "precond_proxy_range"):
            if prefix + name not in state_dict:
                missing_keys.remove(prefix + name)
                getattr(self, name).fill_(float("nan"))
        if prefix + "undistortion_steps" not in state_dict:  # taken anew from the loaded cameras (``after_load``)
            missing_keys.remove(prefix + "undistortion_steps")
            self.undistortion_steps.fill_(-1)
        return True

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ) -> None:
        self.check_checkpoint_size(state_dict, prefix)
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        recorded = self.mark_unrecorded_fingerprint(state_dict, prefix, missing_keys)
        self.after_load()
        if recorded and self.has_cameras:
            self.check_fingerprint(stacklevel=2)

    def after_load(self) -> None:
        """The host's copies of loaded state (``last_refresh``, ``newton_iterations``) read once, after a checkpoint
        is loaded; the Newton steps taken from the loaded cameras where the checkpoint has none."""
        self.last_refresh = int(self.last_refresh_step)
        steps = int(self.undistortion_steps)
        if steps >= 0:
            self.newton_iterations = steps
        elif self.has_cameras:
            self._take_newton_iterations()

    def check_fingerprint(self, stacklevel: int = 1) -> None:
        """Flag a loaded P that was computed for other base intrinsics or another proxy range; it is never used for
        a step. The warning names the caller ``stacklevel`` frames up.

        Same fingerprint (a resumed run): the saved P is kept, so the run continues with bit-identical camera
        parameters. Otherwise the cameras themselves are right (phi = P_old^-1 phi_hat is what was learned), but P
        does not whiten their Jacobian: ``recompute_stale_preconditioner`` recomputes P at the current refined
        intrinsics and re-expresses the latents and Adam's moments, as a refresh does, before the next step.
        """
        self._stale_preconditioner = None
        same_intrinsics = torch.equal(self.precond_base_intrinsics, self.base_intrinsics)
        same_range = torch.equal(self.precond_proxy_range, self.proxy_range)
        if same_intrinsics and same_range:
            return
        if not (self.precondition and self.enabled):  # P = I does not depend on the cameras
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
            stacklevel=stacklevel + 1,
        )

    def _largest_intrinsics_change(self) -> str:
        difference = (self.base_intrinsics - self.precond_base_intrinsics).abs()  # columns: TENSOR_FIELDS
        camera, column = divmod(int(difference.argmax()), difference.shape[1])
        return (
            f"{TENSOR_FIELDS[column]} of camera {camera}: {float(self.precond_base_intrinsics[camera, column]):g} -> "
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
        """Before a training step: if the loaded P was computed for other cameras, recompute it at the current refined
        intrinsics and re-express the latents and Adam's (loaded) moments, exactly as a refresh does. Raises
        ValueError, naming why, if no P exists for these cameras: a stale P is never used."""
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
        self._record_refresh(step)


def describe_proxy_ranges(ranges: ProxyRanges, num_points: int, sampling: SamplingConfig) -> str:
    """The start-up note on the proxy ranges chosen from ``num_points`` scene points (``CameraRefiner.set_cameras``)."""
    fixed = sampling.fixed_range()
    if num_points == 0:
        return (
            "S2CamP proxy range: the scene has no points (dataparser metadata 'points3D_xyz'), so every camera "
            f"uses the fixed contracted range ({fixed[0]:g}, {fixed[1]:g}) (sampling.t-near / t-far set it)"
        )
    count = ranges.t_near.shape[0]
    fell_back = int(ranges.fallback.sum())
    chosen = "t_near " + span(ranges.t_near) + ", t_far " + span(ranges.t_far)
    message = f"S2CamP proxy range from {num_points} scene points, {count} physical cameras: {chosen} (contracted)"
    if fell_back:
        message += (
            f"; {fell_back} camera(s) see fewer than {sampling.auto_range.min_points} points and use the fixed "
            f"range ({fixed[0]:g}, {fixed[1]:g})"
        )
    return message


__all__ = [
    "describe_proxy_ranges",
    "CameraRefiner",
    "PerCameraIntrinsics",
    "PerImageIntrinsics",
    "PriorBlock",
    "ROTATION_COLUMNS",
]
