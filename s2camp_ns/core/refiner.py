"""Preconditioned camera refinement in plain PyTorch (paper sec. 4): ``CameraRefiner``, free of any framework.

Latents ``whitened_delta`` [n, 6] per image and ``whitened_intrinsics`` [C, K - 6] per ``row_of_image`` (camera or
image); phi = P^-1 phi_hat (paper eq. 15), P^T P = Sigma + damping (eqs. 4, 5, 20), per row the block-triangular T
of ``core.shared_intrinsics`` or the symmetric root of ``core.preconditioner``. Refined: c2w' = c2w exp(xi) (local
twist, OpenCV frame), Phi' = Phi + dPhi. ``refresh`` recomputes P without moving any image; a checkpoint loaded onto
other cameras flags its P stale (``check_fingerprint``).
"""

from __future__ import annotations

import warnings

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
from s2camp_ns.core.preconditioner import DampingConfig, SamplingConfig, compute_preconditioner
from s2camp_ns.core.proxy_range import ProxyRanges, proxy_ranges
from s2camp_ns.core.shared_intrinsics import (
    NUM_POSE_PARAMS,
    compute_shared_preconditioner,
    mean_per_camera,
    reexpress_latents,
)
from s2camp_ns.core.track_prior import (
    TrackPriorEvidence,
    apply_track_prior,
    inverse_radius,
    place_at_anchor,
    pooled_intrinsics_radius,
    pose_radius,
)

ROTATION_COLUMNS = [3, 4, 5]  # omega in the twist (rho_x, rho_y, rho_z, omega_x, omega_y, omega_z)
PRIOR_KEYS = ("prior_radius", "prior_radius_intrinsics", "prior_anchor")
"""The track prior's buffers, in checkpoints since the anchors' tracks are kept with the run (older ones lack them)."""
FACTORISATIONS = {"block": compute_shared_preconditioner, "symmetric": compute_preconditioner}  # each row's P


class CameraRefiner(nn.Module):
    """Whitened deltas, their P and its refresh, the track prior and the gauge fix; call ``set_cameras`` first.
    ``parameters``: a ``ParameterLayout`` preset; ``per_camera_intrinsics``: a camera's images share intrinsics
    ("block"), else per image ("symmetric"); ``precondition`` False: P = I; ``photometric`` False: gradients zeroed;
    ``enabled`` False: every delta zero; ``frozen_images``: deltas held at zero."""

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
        pose_prior_exponent: float = 1.0,
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
        self.pose_prior_exponent = pose_prior_exponent
        shared = enabled and per_camera_intrinsics and parameters != "pose"
        self.factorisation = "block" if shared else "symmetric"
        self.num_physical_cameras = num_images  # C, on the host: ``camera_of_image`` holds 0..C-1
        self._register_state(device)
        if enabled:
            self.whitened_delta = self._latent(torch.zeros(num_images, NUM_POSE_PARAMS), device)
        self._size_intrinsics_latent()
        self.frozen_images = frozen_images
        self.projection = "perspective"
        self.distortion_terms: tuple[str, ...] = ()  # ``core.camera.distortion_form``, set in ``set_cameras``
        self.newton_iterations = 0  # ``core.distortion.undistortion_iterations``, taken at every refresh
        self.last_refresh = -1  # ``last_refresh_step`` on the host: read without a device synchronisation
        self.gram_known = False  # whether ``gram`` holds a computed Gram matrix
        self.proxy_ranges: ProxyRanges | None = None
        self.groups_known = False
        self.has_cameras = False
        self.has_track_prior = False
        self.cameras_required = "CameraRefiner.set_cameras must be called before use"  # a framework names its call
        self._stale_preconditioner: str | None = None  # why a loaded P does not fit the base cameras

    def _register_state(self, device: torch.device | str) -> None:
        """Persistent: P, P^-1, the schedule, P's fingerprint, the track prior; the rest comes from the scene."""
        n, k = self.num_images, self.layout.num_params
        eye = torch.eye(k, dtype=torch.float64, device=device).expand(n, k, k).clone()
        self.register_buffer("precond", eye.clone())
        self.register_buffer("precond_inv", eye.clone())
        self.register_buffer("last_refresh_step", torch.tensor(-1, dtype=torch.long, device=device))
        self.register_buffer("num_refreshes", torch.tensor(0, dtype=torch.long, device=device))
        self.register_buffer("undistortion_steps", torch.tensor(-1, dtype=torch.long, device=device))
        self.register_buffer("base_c2w_cv", torch.zeros(n, 3, 4, dtype=torch.float64, device=device), persistent=False)
        base = torch.zeros(n, len(TENSOR_FIELDS), dtype=torch.float64, device=device)
        self.register_buffer("base_intrinsics", base, persistent=False)
        self.register_buffer("precond_base_intrinsics", torch.zeros_like(base))
        self.register_buffer("gram", torch.zeros_like(eye), persistent=False)
        no_range = torch.zeros(n, 2, dtype=torch.float64, device=device)
        self.register_buffer("proxy_range", no_range.clone(), persistent=False)  # contracted [t_near, t_far]
        self.register_buffer("precond_proxy_range", no_range.clone())
        self.register_buffer("camera_of_image", torch.arange(n, device=device), persistent=False)
        no_prior = torch.full((n,), float("nan"), dtype=torch.float64, device=device)
        # The track prior, kept in checkpoints: a loaded run has it without making tracks (``PRIOR_KEYS``).
        self.register_buffer("prior_radius", no_prior)  # pose radius per image, NaN: no prior
        self.register_buffer("prior_radius_intrinsics", no_prior.clone())  # per intrinsics row
        self.register_buffer("prior_anchor", torch.zeros(n, k, dtype=torch.float64, device=device))

    def _latent(self, values: Tensor, device: torch.device | str) -> nn.Parameter:
        """A latent on ``device``; with ``photometric`` False its gradient is zeroed."""
        latent = nn.Parameter(values.to(device))
        if not self.photometric:
            latent.register_hook(torch.zeros_like)
        return latent

    @property
    def row_of_image(self) -> Int[Tensor, " n"]:
        """[n] intrinsics row of each image: its camera ("block") or itself ("symmetric")."""
        if self.factorisation == "block":
            return self.camera_of_image
        device = self.precond.device
        return self._cached("rows", (device,), lambda: torch.arange(self.num_images, device=device))

    @property
    def num_rows(self) -> int:
        return self.num_physical_cameras if self.factorisation == "block" else self.num_images

    def _size_intrinsics_latent(self) -> None:
        """(Re)size the intrinsics latent to zeros [rows, K - 6]; none where the layout refines no intrinsics."""
        m = self.layout.num_params - NUM_POSE_PARAMS
        existing = getattr(self, "whitened_intrinsics", None)
        if not self.enabled or m == 0:
            if existing is not None:
                del self.whitened_intrinsics
            return
        if existing is None or existing.shape != (self.num_rows, m):
            self.whitened_intrinsics = self._latent(torch.zeros(self.num_rows, m), self.precond.device)

    def first_image_of_each_row(self) -> Int[Tensor, " c"]:
        index = self.row_of_image
        first = torch.full((self.num_rows,), self.num_images, dtype=torch.long, device=index.device)
        return first.scatter_reduce_(0, index, torch.arange(self.num_images, device=index.device), "amin")

    def set_camera_groups(self, camera_ids: Tensor | list[int]) -> None:
        """Camera id per image (relabelled 0..C-1 by first appearance); sizes the latent: call before optimizers."""
        ids = torch.as_tensor(camera_ids).reshape(-1)
        if ids.shape[0] != self.num_images:
            raise ValueError(f"camera_ids must hold {self.num_images} entries (one per image), got {ids.shape[0]}")
        _, first = torch.unique(ids, return_inverse=True)
        order: dict[int, int] = {}
        labels = [order.setdefault(int(value), len(order)) for value in first.tolist()]
        self.camera_of_image = torch.tensor(labels, dtype=torch.long, device=self.precond.device)
        self.num_physical_cameras = len(order)
        self.groups_known = True
        self._size_intrinsics_latent()

    def set_camera_model(self, camera_model: str) -> None:
        """Resize latents, P, P^-1 and Sigma to a COLMAP model's layout (no-op if unchanged); call before optimizers."""
        layout = ParameterLayout.from_preset(self.preset, camera_model)
        if layout == self.layout:
            return
        self.layout = layout
        if hasattr(self, "whitened_intrinsics"):
            del self.whitened_intrinsics
        self._size_intrinsics_latent()
        k, device = layout.num_params, self.precond.device
        eye = torch.eye(k, dtype=torch.float64, device=device).expand(self.num_images, k, k).clone()
        self.precond, self.precond_inv, self.gram = eye.clone(), eye.clone(), torch.zeros_like(eye)
        self.prior_anchor = torch.zeros(self.num_images, k, dtype=torch.float64, device=device)

    def set_cameras(
        self,
        c2w: Float[Tensor, "n 3 4"],
        intrinsics: Intrinsics,
        points: Float[Tensor, "m 3"] | None = None,
        groups: Int[Tensor, " n"] | None = None,
        stacklevel: int = 1,
    ) -> ProxyRanges | None:
        """Store the base images (OpenCV c2w), the proxy range from ``points`` and P (or check a loaded P);
        ``groups``: camera ids (default: by intrinsics). Returns the chosen proxy ranges (None: fixed)."""
        if c2w.shape[0] != self.num_images:
            raise ValueError(f"cameras must hold {self.num_images} training cameras, got {c2w.shape[0]}")
        if groups is None:
            groups = torch.unique(intrinsics.tensors().to(torch.float64), dim=0, return_inverse=True)[1]
        device = self.precond.device
        self.base_c2w_cv = c2w.to(torch.float64).to(device)
        self.projection = intrinsics.model
        self.set_camera_model(camera_model_of(intrinsics))
        if not self.groups_known:
            self.set_camera_groups(groups)
        self.base_intrinsics = self._row_means(intrinsics.tensors().to(device))
        self.distortion_terms = distortion_form(intrinsics, self.layout if self.enabled else None)
        chosen, per_image = self.choose_proxy_range(c2w, intrinsics, points)
        self.proxy_range = per_image.to(device)
        self.has_cameras = True
        if int(self.last_refresh_step) < 0:
            self.refresh(step=0, stacklevel=stacklevel + 1)
        else:  # a checkpoint was loaded before the cameras were known
            self.after_load()
            self.check_fingerprint(stacklevel=stacklevel + 1)
        return chosen

    def _row_means(self, base: Float[Tensor, "n 13"]) -> Float[Tensor, "n 13"]:
        """Base intrinsics per image: the mean over its intrinsics row; ValueError if the row mixes image sizes."""
        if self.factorisation == "symmetric":
            return base
        index, first = self.row_of_image, self.first_image_of_each_row()
        size_mismatch = (base[first][index, 7:9] != base[:, 7:9]).any(dim=-1)
        if bool(size_mismatch.any()):
            i = int(torch.nonzero(size_mismatch)[0])
            j = int(first[index[i]])
            raise ValueError(
                f"training image {i} is {int(base[i, 7])}x{int(base[i, 8])} but image {j} of the same physical camera "
                f"{int(index[i])} is {int(base[j, 7])}x{int(base[j, 8])}: shared intrinsics need one image size per "
                "camera (or --pipeline.model.camera-optimizer.intrinsics per-image)"
            )
        return mean_per_camera(base, index, self.num_rows)

    def choose_proxy_range(
        self, c2w: Tensor, intrinsics: Intrinsics, points: Tensor | None
    ) -> tuple[ProxyRanges | None, Float[Tensor, "n 2"]]:
        """(Per-camera ranges, None when fixed; [n, 2] contracted [t_near, t_far] per image)."""
        sampling = self.sampling
        if not (sampling.auto and self.enabled and self.precondition):  # P = I needs no range
            return None, torch.tensor(sampling.fixed_range(), dtype=torch.float64).expand(self.num_images, 2).clone()
        groups = self.camera_of_image.cpu()
        points = None if points is None else torch.as_tensor(points).detach().to(torch.float64).cpu()
        ranges = proxy_ranges(
            points, c2w.detach().to(torch.float64).cpu(), intrinsics.detach().to(device="cpu", dtype=torch.float64),
            groups, sampling.auto_range, sampling.t_near, sampling.t_far, sampling.radial,
        )  # fmt: skip
        self.proxy_ranges = ranges
        return ranges, ranges.stacked()[groups]

    def _take_newton_iterations(self) -> None:
        """Newton steps of the undistortion at the refined intrinsics (``undistortion_iterations``)."""
        self.newton_iterations = 0
        if self.distortion_terms:
            with torch.no_grad():
                refined = self.refined_intrinsics().detach()
            self.newton_iterations = undistortion_iterations(refined[self.first_image_of_each_row()])
        self.undistortion_steps.fill_(self.newton_iterations)

    def require_cameras(self) -> None:
        if not self.has_cameras:
            raise RuntimeError(self.cameras_required)

    def base_intrinsics_struct(self) -> Intrinsics:
        return Intrinsics.from_tensors(self.base_intrinsics, model=self.projection)

    def _cached(self, name: str, key: tuple, build):
        """``build()``, kept under ``name`` until ``key`` (tensors by id and ``_version``, see ``_key``) changes."""
        entry = self._caches.get(name)
        if entry is None or entry[0] != key:
            entry = (key, build())
            self._caches[name] = entry
        return entry[1]

    @staticmethod
    def _key(*tensors: Tensor | None) -> tuple:
        return tuple((id(t), t._version, t.device) if t is not None else None for t in tensors)

    @property
    def frozen_images(self) -> Int[Tensor, " f"] | None:
        """[f] images whose deltas are held at zero, or None."""
        return self._frozen_images

    @frozen_images.setter
    def frozen_images(self, images: Int[Tensor, " f"] | None) -> None:
        self._frozen_images = images
        self._caches.pop("trainable", None)
        self.num_trainable = self.num_images if images is None else int(self._trainable_mask().sum())

    def _trainable_mask(self) -> Float[Tensor, "n 1"]:
        """[n, 1] float64: 1 for trainable images, 0 for frozen ones."""

        def build() -> Tensor:
            keep = torch.ones(self.num_images, 1, dtype=torch.float64, device=self.precond.device)
            if self.frozen_images is not None:
                keep[self.frozen_images.to(keep.device)] = 0.0
            return keep

        return self._cached("trainable", (self.precond.device,), build)

    def latent(self, images: Int[Tensor, " m"] | slice | None = None) -> Float[Tensor, "m k"]:
        """[m, K] float64 whitened latent [z_i; w_row(i)] of every image or of ``images``."""
        pose, rows = self.whitened_delta, self.row_of_image
        if images is not None:
            pose, rows = pose[images], rows[images]
        if not hasattr(self, "whitened_intrinsics"):
            return pose.to(torch.float64)
        return torch.cat([pose.to(torch.float64), self.whitened_intrinsics.to(torch.float64)[rows]], dim=-1)

    def deltas(self, images: Int[Tensor, " m"] | slice | None = None) -> Float[Tensor, "m 16"]:
        """[m, 16] float64 phi = P^-1 phi_hat (paper eq. 15), differentiable, of every image or of ``images``."""
        if isinstance(images, Tensor):
            images = images.to(self.precond.device)
        if not self.enabled:
            count = self.num_images if images is None else self.precond[images].shape[0]
            return self.precond.new_zeros(count, len(PARAMETER_NAMES))
        precond_inv = self.precond_inv if images is None else self.precond_inv[images]
        layout, device = self.layout, self.precond.device
        expansion = self._cached(  # [K, 16]: phi @ E scatters the layout's K columns into the 16 exactly
            "expansion", (layout, device), lambda: layout.expand(torch.eye(layout.num_params, dtype=torch.float64,
                                                                               device=device))
        )  # fmt: skip
        phi = (precond_inv @ self.latent(images)[..., None])[..., 0] @ expansion  # [m, 16]
        if self.frozen_images is not None:
            mask = self._trainable_mask()
            phi = phi * (mask if images is None else mask[images])
        return phi

    @property
    def intrinsics_form(self) -> dict:
        """``Intrinsics`` keywords of the refined form (``distortion_terms``, ``newton_iterations``)."""
        return {"distortion_terms": self.distortion_terms, "newton_iterations": self.newton_iterations}

    def refined_fields(
        self, deltas: Tensor | None = None, images: Int[Tensor, " m"] | slice | None = None
    ) -> Float[Tensor, "m 13"]:
        """[m, 13] Phi' = Phi + dPhi as ``Intrinsics.tensors``, float64, differentiable; ``deltas``: of ``images``."""
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
        """``refined_fields`` as ``Intrinsics`` in ``intrinsics_form``."""
        fields = self.refined_fields(deltas, images)
        return Intrinsics.from_tensors(fields, model=self.projection, **self.intrinsics_form)

    def refined_c2w(
        self, deltas: Tensor | None = None, opengl: bool = False, images: Int[Tensor, " m"] | slice | None = None
    ) -> Float[Tensor, "m 3 4"]:
        """[m, 3, 4] c2w' = c2w exp(xi), float64, OpenCV unless ``opengl``, of every image or of ``images``."""
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

    def set_track_prior(self, evidence: TrackPriorEvidence | None) -> None:
        """Track prior anchor and radii (``core.track_prior``; None: none) in pixels over max(W, H) (paper eq. 5);
        images with a prior start at their anchor."""
        self.require_cameras()
        device, n, k = self.precond.device, self.num_images, self.layout.num_params
        radius = torch.full((n,), float("nan"), dtype=torch.float64, device=device)
        anchor = torch.zeros(n, k, dtype=torch.float64, device=device)
        observations = None
        if evidence is not None:
            anchor = evidence.anchor.to(device)
            observations = None if evidence.observations is None else evidence.observations.to(device)
            if evidence.rms_px is not None:
                radius = evidence.rms_px.to(device) / self.base_intrinsics_struct().image_scale()
        finite = torch.isfinite(radius)
        tracked = torch.zeros(self.num_rows, dtype=torch.bool, device=device)
        tracked[self.row_of_image[finite]] = True
        keep = finite[:, None].expand(n, k).clone()
        keep[:, NUM_POSE_PARAMS:] = tracked[self.row_of_image][:, None]  # a row anchored where any image has tracks
        self.prior_anchor = torch.where(keep, anchor, torch.zeros_like(anchor))
        self.prior_radius = pose_radius(radius, observations, self.pose_prior_exponent)
        self.prior_radius_intrinsics = pooled_intrinsics_radius(radius, observations, self.row_of_image, self.num_rows)
        self.has_track_prior = bool(finite.any())
        if self.enabled:
            for latent, block_anchor, block_radius in self._prior_blocks():
                place_at_anchor(latent, block_anchor, block_radius)

    def prior_anchor_latents(self) -> tuple[Float[Tensor, "n 6"], Float[Tensor, "c m"] | None]:
        """The anchor a_hat = P a (paper eq. 15) in the whitened latents: [n, 6] pose rows and, with intrinsics, the
        [c, m] rows of each intrinsics row's first image (else None)."""
        anchor = (self.precond @ self.prior_anchor[..., None])[..., 0]  # [n, K]
        if not hasattr(self, "whitened_intrinsics"):
            return anchor[:, :NUM_POSE_PARAMS], None
        return anchor[:, :NUM_POSE_PARAMS], anchor[self.first_image_of_each_row(), NUM_POSE_PARAMS:]

    def _prior_blocks(self) -> list[tuple[nn.Parameter, Tensor, Tensor]]:
        """(latent, its anchor, radius) per latent (``prior_anchor_latents``)."""
        pose, intrinsics = self.prior_anchor_latents()
        blocks = [(self.whitened_delta, pose, self.prior_radius)]
        if intrinsics is not None:
            blocks.append((self.whitened_intrinsics, intrinsics, self.prior_radius_intrinsics))
        return blocks

    @torch.no_grad()
    def apply_track_prior(self, lr: float) -> None:
        """The track prior's proximal step after an optimizer step of rate ``lr``; no host read."""
        if not self.enabled or not self.has_track_prior or lr <= 0:
            return
        latents = (id(self.whitened_delta), id(getattr(self, "whitened_intrinsics", None)))  # changed in place: by id
        key = self._key(self.precond, self.prior_anchor, self.prior_radius, self.prior_radius_intrinsics) + latents

        def build() -> list[tuple[nn.Parameter, Tensor, Tensor]]:
            dtype = self.whitened_delta.dtype
            return [(z, a.to(dtype), inverse_radius(r).to(dtype)) for z, a, r in self._prior_blocks()]

        for latent, anchor, inverse in self._cached("prior", key, build):
            apply_track_prior(latent, anchor, inverse, lr)

    @torch.no_grad()
    def remove_common_motion(self) -> None:
        """Subtract the trainable images' mean rotation omega (relative to the anchors with a track prior), a gauge
        the photometric loss does not see, via P's rotation columns (paper eq. 15); no-op under 3 trainable images."""
        if not self.enabled or self.num_trainable < 3:
            return
        key = self._key(self.precond, self.prior_anchor) + (self.has_track_prior,)
        columns, mask, anchor = self._cached("gauge", key, self._gauge_terms)
        motion = (self.precond_inv[:, ROTATION_COLUMNS, :] @ self.latent()[..., None])[..., 0]  # [n, 3]
        if anchor is not None:
            motion = motion - anchor
        mean = (mask[:, 0] / self.num_trainable) @ motion  # [3]
        correction = (columns @ mean[:, None])[..., 0] * mask  # [n, K]
        self.whitened_delta.sub_(correction[:, :NUM_POSE_PARAMS].to(self.whitened_delta.dtype))
        if self.factorisation == "symmetric" and hasattr(self, "whitened_intrinsics"):
            self.whitened_intrinsics.sub_(correction[:, NUM_POSE_PARAMS:].to(self.whitened_intrinsics.dtype))

    def _gauge_terms(self) -> tuple[Tensor, Tensor, Tensor | None]:
        """P's rotation columns [n, K, 3], the trainable mask [n, 1], the anchors' rotation [n, 3] or None."""
        anchor = self.layout.expand(self.prior_anchor)[:, ROTATION_COLUMNS] if self.has_track_prior else None
        return self.precond[:, :, ROTATION_COLUMNS].to(torch.float64), self._trainable_mask(), anchor

    @torch.no_grad()
    def refresh(self, step: int, optimizer: torch.optim.Optimizer | None = None, stacklevel: int = 1) -> None:
        """Recompute P and re-express latents and Adam's moments (no image moves); no P: keep P and warn."""
        self.require_cameras()
        try:
            self._recompute_preconditioner(optimizer)
        except ValueError as error:
            warnings.warn(f"preconditioner refresh at step {step} skipped, P kept: {error}", stacklevel=stacklevel + 1)
            return
        self._stale_preconditioner = None
        self._record_refresh(step)

    def _record_refresh(self, step: int) -> None:
        self.last_refresh_step.fill_(step)
        self.last_refresh = step
        self.num_refreshes.add_(1)
        self._take_newton_iterations()

    def _recompute_preconditioner(self, optimizer: torch.optim.Optimizer | None) -> None:
        """P per row at the refined intrinsics, latents re-expressed; ValueError (nothing changed) if none exists."""
        if self.precondition and self.enabled:
            device, first = self.precond.device, self.first_image_of_each_row()
            ranges = None if not self.sampling.auto else self.proxy_range[first].cpu()
            rows = self.refined_intrinsics().detach()[first]
            result = FACTORISATIONS[self.factorisation](rows, self.layout, self.sampling, self.damping, ranges=ranges)
            matrix, inverse = result.matrix.to(device), result.inverse.to(device)  # [C, K, K]
            latents = [self.whitened_delta, getattr(self, "whitened_intrinsics", None)]
            states = [None if optimizer is None or p is None else optimizer.state.get(p) for p in latents]
            reexpress_latents(*latents, self.row_of_image, self.precond[first], self.precond_inv[first], matrix,
                              inverse, *states)  # fmt: skip
            index = self.row_of_image
            self.precond.copy_(matrix[index])
            self.precond_inv.copy_(inverse[index])
            self.gram.copy_(result.gram.to(device)[index])
            self.gram_known = True
        self.precond_base_intrinsics.copy_(self.base_intrinsics)
        self.precond_proxy_range.copy_(self.proxy_range)

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ) -> None:
        """torch's loading; ValueError for another number of images; a missing fingerprint or Newton count: unknown."""
        saved = state_dict.get(prefix + "precond")
        if saved is not None and saved.shape[0] != self.num_images:
            raise ValueError(
                f"the camera optimizer's checkpoint holds {saved.shape[0]} training cameras, but this model has "
                f"{self.num_images}: it is a checkpoint of another scene or of another train/eval split"
            )
        for name in PRIOR_KEYS:  # data, not structure: take the saved shape (intrinsics rows as the run had them)
            value = state_dict.get(prefix + name)
            if value is not None and value.shape != getattr(self, name).shape:
                setattr(self, name, torch.empty(value.shape, dtype=value.dtype, device=self.precond.device))
        latent = state_dict.get(prefix + "whitened_delta")
        if latent is not None and latent.shape[-1] > NUM_POSE_PARAMS:  # a single per-image latent [n, K]
            state_dict[prefix + "whitened_delta"] = latent[:, :NUM_POSE_PARAMS]
            state_dict[prefix + "whitened_intrinsics"] = latent[:, NUM_POSE_PARAMS:]
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        if saved is None:
            return
        unrecorded = {"precond_base_intrinsics": float("nan"), "precond_proxy_range": float("nan"),
                      "undistortion_steps": -1}  # fmt: skip
        for name, value in unrecorded.items():
            if prefix + name not in state_dict:
                missing_keys.remove(prefix + name)
                getattr(self, name).fill_(value)
        if all(prefix + name in state_dict for name in PRIOR_KEYS):
            self.has_track_prior = bool(torch.isfinite(self.prior_radius).any())
        else:  # an older checkpoint: the prior set from the scene stays
            for name in PRIOR_KEYS:
                if prefix + name in missing_keys:
                    missing_keys.remove(prefix + name)
        self.after_load()
        if self.has_cameras:
            self.check_fingerprint()  # the warning names this line

    def after_load(self) -> None:
        """Host copies of loaded state (``last_refresh``, ``newton_iterations``)."""
        self.last_refresh = int(self.last_refresh_step)
        steps = int(self.undistortion_steps)
        if steps >= 0:
            self.newton_iterations = steps
        elif self.has_cameras:
            self._take_newton_iterations()

    def check_fingerprint(self, stacklevel: int = 1) -> None:
        """Flag (and warn, ``stacklevel`` frames up) a loaded P computed for other base intrinsics or proxy range:
        ``recompute_stale_preconditioner`` replaces it before the next step, keeping phi. A match keeps P."""
        self._stale_preconditioner = None
        same_intrinsics = torch.equal(self.precond_base_intrinsics, self.base_intrinsics)
        same_range = torch.equal(self.precond_proxy_range, self.proxy_range)
        if same_intrinsics and same_range:
            return
        if not (self.precondition and self.enabled):  # P = I does not depend on the cameras
            self.precond_base_intrinsics.copy_(self.base_intrinsics)
            self.precond_proxy_range.copy_(self.proxy_range)
            return
        self._stale_preconditioner = self._why_stale(same_intrinsics)
        warnings.warn(
            f"loaded camera-optimizer state: {self._stale_preconditioner}; P is recomputed for these cameras before "
            "the next training step, the latent and Adam's moments re-expressed (the learned camera deltas are kept)",
            stacklevel=stacklevel + 1,
        )

    def _why_stale(self, same_intrinsics: bool) -> str:
        if not bool(torch.isfinite(self.precond_base_intrinsics).all()):
            return "the intrinsics its P was computed for are not recorded (an older checkpoint)"
        if not same_intrinsics:
            difference = (self.base_intrinsics - self.precond_base_intrinsics).abs()  # columns: TENSOR_FIELDS
            camera, column = divmod(int(difference.argmax()), difference.shape[1])
            before, after = (float(t[camera, column]) for t in (self.precond_base_intrinsics, self.base_intrinsics))
            return (
                "the training cameras' intrinsics differ from those its P was computed for (largest change "
                f"{TENSOR_FIELDS[column]} of camera {camera}: {before:g} -> {after:g})"
            )
        if not bool(torch.isfinite(self.precond_proxy_range).all()):
            return "the proxy range its P was computed for is not recorded (an older checkpoint)"
        difference = (self.proxy_range - self.precond_proxy_range).abs()
        image, column = divmod(int(difference.argmax()), 2)
        before, after = (float(t[image, column]) for t in (self.precond_proxy_range, self.proxy_range))
        return (
            f"the proxy range differs from the one its P was computed for ({('t_near', 't_far')[column]} of image "
            f"{image}: {before:g} -> {after:g})"
        )

    @property
    def preconditioner_is_stale(self) -> bool:
        """Whether a loaded P awaits ``recompute_stale_preconditioner``."""
        return self._stale_preconditioner is not None

    @torch.no_grad()
    def recompute_stale_preconditioner(self, step: int, optimizer: torch.optim.Optimizer | None) -> None:
        """Recompute a stale P as a refresh does; ValueError, naming why, if no P exists for these cameras."""
        if not self.preconditioner_is_stale:
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


__all__ = ["FACTORISATIONS", "ROTATION_COLUMNS", "CameraRefiner"]
