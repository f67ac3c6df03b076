"""Reprojection drift: how far refined cameras move the images of the scene's 3D points, in pixels.

Pose and focal errors together: every 3D point a true image sees (in front of it, inside it; no occlusion test) is
projected through the true and the refined camera (paper eq. 2, distortion included), the refined poses aligned to the
true ones by the similarity of their centres; the RMS of the pixel displacement over these pairs. OpenCV cameras.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.alignment import MIN_CAMERAS_FOR_ALIGNMENT, align_cameras
from s2camp_ns.core.camera import Intrinsics, project
from s2camp_ns.core.validation import check_finite


@dataclass(frozen=True)
class Drift:
    """Result of :func:`reprojection_drift`."""

    rms_px: float
    """RMS pixel displacement over the (image, point) pairs visible in the true image."""
    max_px: float
    """Largest pixel displacement of those pairs."""
    pairs: int
    """Number of (image, point) pairs measured."""
    behind: int
    """Pairs visible in the true camera but behind the refined one (left out: their pixels are meaningless)."""


def _world_to_camera(points: Float[Tensor, "p 3"], c2w: Float[Tensor, "n 3 4"]) -> Float[Tensor, "n p 3"]:
    """Camera-frame coordinates R^T (x - c) of every point in every camera (the [R | t] of paper eq. 2)."""
    return (points[None, :, :] - c2w[:, None, :, 3]) @ c2w[:, :, :3]


def _check_cameras(name: str, c2w: Tensor, intrinsics: Intrinsics, n: int) -> None:
    if c2w.ndim != 3 or c2w.shape[1:] != (3, 4) or c2w.shape[0] != n:
        raise ValueError(f"{name}_c2w must have shape [{n}, 3, 4], got {tuple(c2w.shape)}")
    if intrinsics.num_cameras != n:
        raise ValueError(f"{name}_intrinsics must describe {n} cameras, got {intrinsics.num_cameras}")
    check_finite(f"{name}_c2w", c2w)


def reprojection_drift(
    points: Float[Tensor, "p 3"], true_c2w: Float[Tensor, "n 3 4"], true_intrinsics: Intrinsics,
    refined_c2w: Float[Tensor, "n 3 4"], refined_intrinsics: Intrinsics, align: bool = True,
) -> Drift:
    """Reprojection displacement (px) of ``points`` between the true and the refined cameras (module docstring);
    ``align``: refined poses first mapped onto the true ones (needs 3 distinct centres). Raises ``ValueError`` for
    mismatched shapes, non-finite input, or when no point is visible in any true image."""
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ValueError(f"points must have shape [P, 3] with P >= 1, got {tuple(points.shape)}")
    n = true_c2w.shape[0] if true_c2w.ndim == 3 else -1
    if n < 1:
        raise ValueError(f"true_c2w must have shape [N, 3, 4] with N >= 1, got {tuple(true_c2w.shape)}")
    _check_cameras("true", true_c2w, true_intrinsics, n)
    _check_cameras("refined", refined_c2w, refined_intrinsics, n)
    points = points.detach().to(torch.float64)
    check_finite("points", points)
    true_c2w = true_c2w.detach().to(torch.float64)
    refined_c2w = refined_c2w.detach().to(device=true_c2w.device, dtype=torch.float64)
    if align:
        if n < MIN_CAMERAS_FOR_ALIGNMENT:
            raise ValueError(f"align needs at least {MIN_CAMERAS_FOR_ALIGNMENT} cameras, got {n}")
        refined_c2w = align_cameras(refined_c2w, true_c2w).apply_to_poses(refined_c2w)
    true_intrinsics = true_intrinsics.to(device=true_c2w.device, dtype=torch.float64)
    refined_intrinsics = refined_intrinsics.to(device=true_c2w.device, dtype=torch.float64)
    points = points.to(true_c2w.device)
    true_pixels, true_margin = project(_world_to_camera(points, true_c2w), true_intrinsics)
    refined_pixels, refined_margin = project(_world_to_camera(points, refined_c2w), refined_intrinsics)
    width, height = true_intrinsics.width[:, None], true_intrinsics.height[:, None]
    u, v = true_pixels[..., 0], true_pixels[..., 1]
    visible = (true_margin > 0) & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    if not bool(visible.any()):
        raise ValueError("points: none is visible in any true camera (in front of it and inside its image)")
    behind = visible & ~(refined_margin > 0)
    measured = visible & (refined_margin > 0)
    if bool(behind.any()):
        warnings.warn(
            f"reprojection_drift: {int(behind.sum())} visible point(s) lie behind their refined camera and are "
            "left out",
            stacklevel=2,
        )
    if not bool(measured.any()):
        raise ValueError("refined cameras: every visible point lies behind its refined camera")
    displacement = torch.linalg.norm(refined_pixels - true_pixels, dim=-1)[measured]
    return Drift(
        rms_px=float(torch.sqrt(torch.mean(displacement**2))), max_px=float(displacement.max()),
        pairs=int(measured.sum()), behind=int(behind.sum()),
    )
