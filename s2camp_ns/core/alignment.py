"""Camera error metrics after a similarity (Umeyama) alignment, as CamP reports them.

Joint field and camera optimization recovers cameras only up to a similarity of the world, so the estimated poses
are first mapped onto the reference ones by the least-squares similarity of their centres (Umeyama 1991). Rotation
errors are geodesic angles, the same in OpenCV and OpenGL axes as long as both pose sets use one.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.validation import check_finite

MIN_CAMERAS_FOR_ALIGNMENT = 3
"""Fewer centres do not fix a similarity in 3D."""


@dataclass
class Similarity:
    """x -> scale * rotation @ x + translation."""

    scale: float
    rotation: Float[Tensor, "3 3"]
    translation: Float[Tensor, " 3"]

    def apply_to_points(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
        return self.scale * points @ self.rotation.T + self.translation

    def apply_to_poses(self, c2w: Float[Tensor, "n 3 4"]) -> Float[Tensor, "n 3 4"]:
        """Move camera-to-world poses with the similarity; the camera axes rotate, the centres map as points."""
        rotation = self.rotation @ c2w[:, :, :3]
        centre = self.apply_to_points(c2w[:, :, 3])
        return torch.cat([rotation, centre[:, :, None]], dim=-1)


def umeyama(source: Float[Tensor, "n 3"], target: Float[Tensor, "n 3"]) -> Similarity:
    """Similarity minimizing sum ||target_i - (s R source_i + t)||^2 (Umeyama's closed form, with det(R) = +1)."""
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(
            f"source and target must both have shape [N, 3], got {tuple(source.shape)} and {tuple(target.shape)}"
        )
    n = source.shape[0]
    if n < MIN_CAMERAS_FOR_ALIGNMENT:
        raise ValueError(f"umeyama needs at least {MIN_CAMERAS_FOR_ALIGNMENT} points, got {n}")
    source, target = source.double(), target.double()
    mu_s, mu_t = source.mean(dim=0), target.mean(dim=0)
    src, tgt = source - mu_s, target - mu_t
    var_s = (src * src).sum() / n
    if float(var_s) <= 1e-24:
        raise ValueError("umeyama needs source points that are not all identical")
    covariance = tgt.T @ src / n
    u, singular, vh = torch.linalg.svd(covariance)
    sign = torch.ones(3, dtype=source.dtype, device=source.device)
    if float(torch.det(u) * torch.det(vh)) < 0:
        sign[2] = -1.0
    rotation = u @ torch.diag(sign) @ vh
    scale = float((singular * sign).sum() / var_s)
    translation = mu_t - scale * rotation @ mu_s
    return Similarity(scale, rotation, translation)


def relative_rotation(
    r_a: Float[Tensor, "n 3 3"], r_b: Float[Tensor, "n 3 3"]
) -> tuple[Float[Tensor, "n 3"], Float[Tensor, " n"]]:
    """Of R = r_a^T r_b: the vector of R - R^T (2 sin(angle) times the axis) and the angle, atan2 form."""
    r = r_a.transpose(-1, -2) @ r_b
    trace = r.diagonal(dim1=-2, dim2=-1).sum(dim=-1)
    skew = torch.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], dim=-1)
    return skew, torch.atan2(0.5 * torch.linalg.norm(skew, dim=-1), 0.5 * (trace - 1.0))


def rotation_angle(r_a: Float[Tensor, "n 3 3"], r_b: Float[Tensor, "n 3 3"]) -> Float[Tensor, " n"]:
    """Geodesic angle (rad, in [0, pi]) between rotations, atan2 form: accurate for tiny and near-pi angles."""
    return relative_rotation(r_a, r_b)[1]


def align_cameras(est_c2w: Float[Tensor, "n 3 4"], ref_c2w: Float[Tensor, "n 3 4"]) -> Similarity:
    """Similarity mapping the estimated camera centres onto the reference ones (Umeyama)."""
    return umeyama(est_c2w[:, :, 3], ref_c2w[:, :, 3])


def _stats(prefix: str, name: str, values: Tensor) -> dict[str, float]:
    return {f"{prefix}{name}_mean": float(values.mean()), f"{prefix}{name}_max": float(values.max())}


def _pose_errors(prefix: str, est: Tensor, ref: Tensor) -> dict[str, float]:
    errors = _stats(prefix, "rot_err", rotation_angle(est[:, :, :3], ref[:, :, :3]))
    errors.update(_stats(prefix, "pos_err", torch.linalg.norm(est[:, :, 3] - ref[:, :, 3], dim=-1)))
    return errors


def camera_errors(
    est_c2w: Float[Tensor, "n 3 4"],
    ref_c2w: Float[Tensor, "n 3 4"],
    est_fx: Float[Tensor, " n"] | None = None,
    ref_fx: Float[Tensor, " n"] | None = None,
    align: bool = True,
) -> dict[str, float]:
    """Errors of estimated against reference poses: ``rot_err_mean/max`` (rad), ``pos_err_mean/max`` (reference
    units) after the similarity alignment, the same unaligned under ``raw_``, ``focal_err_mean/max`` (px, when both
    focal lengths are given), ``aligned`` (1.0 or 0.0) and ``align_scale``. With fewer than 3 images or coincident
    centres the aligned errors are the raw ones, ``aligned`` is 0.0 and a warning says so."""
    if est_c2w.shape != ref_c2w.shape or est_c2w.ndim != 3 or est_c2w.shape[1:] != (3, 4):
        raise ValueError(
            f"est_c2w and ref_c2w must both have shape [N, 3, 4], got {tuple(est_c2w.shape)} and {tuple(ref_c2w.shape)}"
        )
    n = est_c2w.shape[0]
    if n == 0:
        raise ValueError("camera_errors needs at least one camera, got N = 0")
    est = est_c2w.detach().double()
    ref = ref_c2w.detach().to(device=est.device, dtype=torch.float64)
    check_finite("est_c2w", est)
    check_finite("ref_c2w", ref)
    errors = _pose_errors("raw_", est, ref)
    similarity = None
    if align:
        if n < MIN_CAMERAS_FOR_ALIGNMENT:
            warnings.warn(
                f"camera_errors: {n} camera(s) cannot fix a similarity (need {MIN_CAMERAS_FOR_ALIGNMENT}); "
                "reporting unaligned errors",
                stacklevel=2,
            )
        else:
            try:
                similarity = align_cameras(est, ref)
            except ValueError as error:
                warnings.warn(f"camera_errors: alignment skipped ({error}); reporting unaligned errors", stacklevel=2)
    aligned = similarity.apply_to_poses(est) if similarity is not None else est
    errors.update(_pose_errors("", aligned, ref))
    errors["aligned"] = 1.0 if similarity is not None else 0.0
    errors["align_scale"] = similarity.scale if similarity is not None else 1.0
    if (est_fx is None) != (ref_fx is None):
        raise ValueError("camera_errors: give both est_fx and ref_fx, or neither")
    if est_fx is not None and ref_fx is not None:
        est_f = est_fx.detach().double().reshape(-1)
        ref_f = ref_fx.detach().to(device=est_f.device, dtype=torch.float64).reshape(-1)
        if est_f.shape[0] != n or ref_f.shape[0] != n:
            raise ValueError(f"est_fx and ref_fx must have {n} elements, got {est_f.shape[0]} and {ref_f.shape[0]}")
        errors.update(_stats("", "focal_err", (est_f - ref_f).abs()))
    return errors
