"""Refined pinhole intrinsics expressed as a view-matrix change.

For pinhole K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] and the refined K', A = K^-1 K' is upper triangular with third
row (0, 0, 1), so K' x = K (A x) and (A x)_z = x_z: rendering A x with K is rendering x with K'. A rasterizer with
gradients for the view matrix only (gsplat) thus refines the intrinsics through [[A R, A t], [0, 1]] and the base K;
depth, EWA covariance and everything in pixel space agree exactly.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def intrinsics_matrix(
    fx: Float[Tensor, " n"],
    fy: Float[Tensor, " n"],
    cx: Float[Tensor, " n"],
    cy: Float[Tensor, " n"],
    skew: Float[Tensor, " n"] | None = None,
) -> Float[Tensor, "n 3 3"]:
    """Pinhole K [n, 3, 3] with u = fx x/z + skew y/z + cx, v = fy y/z + cy (``core.camera``'s convention);
    differentiable in every entry."""
    zeros = torch.zeros_like(fx)
    ones = torch.ones_like(fx)
    skew = zeros if skew is None else skew
    rows = [
        torch.stack([fx, skew, cx], dim=-1),
        torch.stack([zeros, fy, cy], dim=-1),
        torch.stack([zeros, zeros, ones], dim=-1),
    ]
    return torch.stack(rows, dim=-2)


def intrinsics_correction(
    base_k: Float[Tensor, "n 3 3"], refined_k: Float[Tensor, "n 3 3"], check: bool = True
) -> Float[Tensor, "n 3 3"]:
    """A = K^-1 K' [n, 3, 3] in closed form, differentiable in K'. ValueError if K or K' is not a pinhole matrix
    with positive focal lengths; ``check=False`` skips that test (a device synchronization)."""
    if base_k.shape[-2:] != (3, 3) or refined_k.shape[-2:] != (3, 3):
        raise ValueError(f"base_k and refined_k must have shape [n, 3, 3], got {tuple(base_k.shape)}, "
                         f"{tuple(refined_k.shape)}")  # fmt: skip
    for name, k in (("base_k", base_k), ("refined_k", refined_k)) if check else ():
        lower = torch.stack([k[..., 1, 0], k[..., 2, 0], k[..., 2, 1], k[..., 2, 2] - 1], dim=-1)
        if bool((lower.detach().abs() > 1e-6).any()):
            raise ValueError(f"{name} must be a pinhole intrinsics matrix (upper triangular, K[2] = (0, 0, 1))")
        if bool((k[..., 0, 0].detach() <= 0).any() | (k[..., 1, 1].detach() <= 0).any()):
            raise ValueError(f"{name} must have positive focal lengths, got fx, fy = {k[..., 0, 0]}, {k[..., 1, 1]}")
    fx, s, cx = base_k[..., 0, 0], base_k[..., 0, 1], base_k[..., 0, 2]
    fy, cy = base_k[..., 1, 1], base_k[..., 1, 2]
    fx2, s2, cx2 = refined_k[..., 0, 0], refined_k[..., 0, 1], refined_k[..., 0, 2]
    fy2, cy2 = refined_k[..., 1, 1], refined_k[..., 1, 2]
    # K A = K': second row first (fy a22 = fy', fy a23 + cy = cy'), then the first.
    a22 = fy2 / fy
    a23 = (cy2 - cy) / fy
    a11 = fx2 / fx
    a12 = (s2 - s * a22) / fx
    a13 = (cx2 - cx - s * a23) / fx
    zeros = torch.zeros_like(a11)
    return torch.stack(
        [
            torch.stack([a11, a12, a13], dim=-1),
            torch.stack([zeros, a22, a23], dim=-1),
            torch.stack([zeros, zeros, torch.ones_like(a11)], dim=-1),
        ],
        dim=-2,
    )


def corrected_viewmat(viewmat: Float[Tensor, "n 4 4"], correction: Float[Tensor, "n 3 3"]) -> Float[Tensor, "n 4 4"]:
    """World-to-camera [[A R, A t], [0, 1]]: with the base K it renders as K' = K A; differentiable in both."""
    top = correction @ viewmat[..., :3, :]
    return torch.cat([top, viewmat[..., 3:, :]], dim=-2)


__all__ = ["corrected_viewmat", "intrinsics_correction", "intrinsics_matrix"]
