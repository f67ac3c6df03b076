"""Camera error metrics after a similarity (Umeyama / Procrustes) alignment, as CamP reports them.

Joint NeRF + camera optimization can only recover cameras up to a similarity of the world (gauge freedom: the
radiance field moves with them), so estimated cameras are first aligned to the reference cameras by the
similarity that best maps estimated centres onto reference centres (least squares, Umeyama 1991), and errors are
measured afterwards. Rotation errors are the geodesic angle between rotations; they do not depend on whether
both pose sets use the OpenCV or the OpenGL camera axes, as long as they use the same one.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.validation import check_finite

MIN_CAMERAS_FOR_ALIGNMENT = 3
"""Fewer centres do not fix a similarity in 3D (two centres leave the rotation about their line free)."""


@dataclass
class Similarity:
    """x -> scale * rotation @ x + translation."""

    scale: float
    rotation: Float[Tensor, "3 3"]
    translation: Float[Tensor, " 3"]

    @classmethod
    def identity(cls, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Similarity:
        return cls(1.0, torch.eye(3, dtype=dtype, device=device), torch.zeros(3, dtype=dtype, device=device))

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


def _relative_skew_and_angle(
    r_a: Float[Tensor, "n 3 3"], r_b: Float[Tensor, "n 3 3"]
) -> tuple[Float[Tensor, "n 3"], Float[Tensor, " n"]]:
    """Of R = r_a^T r_b: the vector of R - R^T (2 sin(angle) times the axis) and the angle, atan2 form."""
    relative = r_a.transpose(-1, -2) @ r_b
    trace = relative.diagonal(dim1=-2, dim2=-1).sum(dim=-1)
    skew = torch.stack(
        [
            relative[:, 2, 1] - relative[:, 1, 2],
            relative[:, 0, 2] - relative[:, 2, 0],
            relative[:, 1, 0] - relative[:, 0, 1],
        ],
        dim=-1,
    )
    return skew, torch.atan2(0.5 * torch.linalg.norm(skew, dim=-1), 0.5 * (trace - 1.0))


def rotation_angle(r_a: Float[Tensor, "n 3 3"], r_b: Float[Tensor, "n 3 3"]) -> Float[Tensor, " n"]:
    """Geodesic angle (rad, in [0, pi]) between rotations, atan2 form: accurate for tiny and near-pi angles."""
    return _relative_skew_and_angle(r_a, r_b)[1]


def rotation_vector(r_a: Float[Tensor, "n 3 3"], r_b: Float[Tensor, "n 3 3"]) -> Float[Tensor, "n 3"]:
    """Axis-angle vector (rad) of r_a^T r_b, the rotation from r_a to r_b in r_a's own frame, for angles below pi
    (at pi the axis is not defined by R - R^T); zero for identical rotations."""
    skew, angle = _relative_skew_and_angle(r_a, r_b)
    norm = torch.linalg.norm(skew, dim=-1, keepdim=True)
    return torch.where(norm > 0, skew * (angle[:, None] / norm.clamp(min=torch.finfo(skew.dtype).tiny)), 0.0)


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
    """Camera errors of estimated against reference cameras.

    Returns floats: ``rot_err_mean/max`` (rad, geodesic), ``pos_err_mean/max`` (reference scene units) after the
    similarity alignment of the estimated to the reference cameras, ``focal_err_mean/max`` (px, if both focal
    lengths are given; a similarity does not change focal lengths), the same pose errors without alignment under
    the prefix ``raw_``, plus ``aligned`` (1.0 or 0.0) and ``align_scale``. With fewer than 3 cameras, or centres
    that all coincide, there is no similarity to fit: the aligned errors then equal the raw ones, ``aligned`` is
    0.0 and a warning says so.
    """
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
