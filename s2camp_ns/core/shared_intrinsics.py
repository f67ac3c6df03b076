"""Preconditioner for intrinsics shared by all images of one physical camera (pose per image).

Image i of camera c refines its pose delta d_i (local twist, 6 columns) and shares the intrinsics delta e_c (m
columns, as the layout enables them). The proxy-point Gram (paper eq. 5) over (d_i, e_c),

    Sigma = [[A, B], [B^T, C]]        A: 6 x 6 (pose), B: 6 x m (pose-intrinsics), C: m x m (intrinsics),

depends only on the intrinsics, so c's images share Sigma_c; their stacked objective sum_i |J [d_i; e_c]|^2 has the
arrowhead Gram with A on the diagonal, B in the last block column and n_c C in the corner.

Exact block factorization. Completing the square per image,

    [d; e]^T Sigma [d; e] = |A^(1/2) (d + A^-1 B e)|^2 + e^T S e,    S = C - B^T A^-1 B  (Schur complement),

so z_i = A^(1/2) (d_i + G e_c), G = A^-1 B, and w_c = S^(1/2) e_c whiten every image: its latent is T [d; e] with

    T = [[A^(1/2), A^(1/2) G], [0, S^(1/2)]],    T^-1 = [[A^-(1/2), -G S^-(1/2)], [0, S^-(1/2)]],   T^T T = Sigma.

T satisfies paper eq. 17 (P^T P = Sigma); by eqs. 18-19 it is eq. 20's symmetric root up to an orthogonal factor,
T = Q Sigma^(1/2), chosen to keep the shared block separate (one image per camera: the per-image P's spectrum). The
camera's whitened arrowhead is diag(I, ..., I, n_c I): a unit step of w_c moves every image's proxy points by one
unit RMS, as a unit step of z_i moves image i's, so one learning rate means the same image-space step for every
latent (Adam's normalization removes w_c's n_c-fold gradient). The pose latent carries the compensating pose change
-G e_c, which decouples focal length from forward translation.

Damping (``s2camp_ns.core.preconditioner.damped_gram``) is added to Sigma first, so A and S >= damping_rel diag(C)
stay positive definite when the intrinsics are nearly unobservable. Float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, ParameterLayout
from s2camp_ns.core.preconditioner import (
    DampingConfig,
    SamplingConfig,
    damped_gram,
    gram_from_points,
    sample_proxy_points,
    symmetric_sqrt_and_inverse,
)
from s2camp_ns.core.validation import check_finite

NUM_POSE_PARAMS = 6


@dataclass(frozen=True)
class SharedPreconditioner:
    """Block upper-triangular T and T^-1 per physical camera (latent = T phi), and the undamped Gram."""

    matrix: Float[Tensor, "c k k"]
    inverse: Float[Tensor, "c k k"]
    gram: Float[Tensor, "c k k"]


def block_triangular_factor(
    sigma: Float[Tensor, "c k k"], damping: DampingConfig | None = None
) -> tuple[Float[Tensor, "c k k"], Float[Tensor, "c k k"]]:
    """T and T^-1 with T^T T = Sigma + damping (module docstring; paper eqs. 17-19), the first ``NUM_POSE_PARAMS``
    columns the pose; without intrinsics columns T is eq. 20's symmetric root."""
    damping = damping or DampingConfig()
    if sigma.ndim != 3 or sigma.shape[-1] != sigma.shape[-2] or sigma.shape[-1] < NUM_POSE_PARAMS:
        raise ValueError(f"sigma must have shape [C, K, K] with K >= {NUM_POSE_PARAMS}, got {tuple(sigma.shape)}")
    sigma = sigma.to(torch.float64)
    check_finite("sigma", sigma)
    damped = damped_gram(0.5 * (sigma + sigma.transpose(-1, -2)), damping)
    p = NUM_POSE_PARAMS
    a, b, c = damped[:, :p, :p], damped[:, :p, p:], damped[:, p:, p:]
    a_root, a_inv_root = symmetric_sqrt_and_inverse(a, damping.diagonal_only)
    a_inverse = a_inv_root @ a_inv_root
    coupling = torch.zeros_like(b) if damping.diagonal_only else a_inverse @ b
    schur = c - b.transpose(-1, -2) @ coupling
    s_root, s_inv_root = symmetric_sqrt_and_inverse(schur, damping.diagonal_only)
    matrix = torch.zeros_like(damped)
    matrix[:, :p, :p] = a_root
    matrix[:, :p, p:] = a_root @ coupling
    matrix[:, p:, p:] = s_root
    inverse = torch.zeros_like(damped)
    inverse[:, :p, :p] = a_inv_root
    inverse[:, :p, p:] = -coupling @ s_inv_root
    inverse[:, p:, p:] = s_inv_root
    return matrix, inverse


def compute_shared_preconditioner(
    intrinsics: Intrinsics,
    layout: ParameterLayout | None = None,
    sampling: SamplingConfig | None = None,
    damping: DampingConfig | None = None,
    ranges: Float[Tensor, "c 2"] | None = None,
) -> SharedPreconditioner:
    """T and T^-1 per physical camera (one row of ``intrinsics`` each) from its proxy points; ``ranges``: contracted
    [t_near, t_far] per camera (``core.proxy_range``), None: the sampling's fixed range."""
    layout = layout or ParameterLayout()
    if not layout.pose:
        raise ValueError("shared intrinsics need the pose group in the layout: the pose is what stays per image")
    sampling = sampling or SamplingConfig()
    intrinsics = intrinsics.detach().to(dtype=torch.float64).general()  # T depends on the values alone
    intrinsics.validate()
    points = sample_proxy_points(intrinsics, sampling, ranges=ranges)
    sigma, _ = gram_from_points(points, intrinsics, layout)
    matrix, inverse = block_triangular_factor(sigma, damping)
    return SharedPreconditioner(matrix=matrix, inverse=inverse, gram=sigma)


@torch.no_grad()
def reexpress_latents(
    pose_latent: Float[Tensor, "n 6"],
    intrinsics_latent: Float[Tensor, "c m"] | None,
    row_of_image: Int[Tensor, " n"],
    old_matrix: Float[Tensor, "c k k"],
    old_inverse: Float[Tensor, "c k k"],
    new_matrix: Float[Tensor, "c k k"],
    new_inverse: Float[Tensor, "c k k"],
    pose_state: dict | None = None,
    intrinsics_state: dict | None = None,
) -> None:
    """Switch the latents from P_old to P_new in place without moving any image (phi_i unchanged, paper eq. 15).

    Per intrinsics row c, M = P_new P_old^-1: z_i' = M_zz z_i + M_zw w_c, w_c' = M_ww w_c + sum_i M_wz z_i over the
    row's images. Gradients, and Adam's first moment, map the same way with G = M^-T = (P_old P_new^-1)^T; the second
    moment with G's elementwise squares (exact for a diagonal M). ``intrinsics_latent`` None: no intrinsics (K = 6).
    """
    index = row_of_image.to(new_matrix.device)
    _check_camera_index(index, new_matrix.shape[0], pose_latent.shape[0])
    change = new_matrix.to(torch.float64) @ old_inverse.to(torch.float64)
    gradient = (old_matrix.to(torch.float64) @ new_inverse.to(torch.float64)).transpose(-1, -2)
    values = [pose_latent] if intrinsics_latent is None else [pose_latent, intrinsics_latent]
    _map_pair(values, change, index)
    for key, power in (("exp_avg", 1), ("exp_avg_sq", 2)):
        states = [pose_state] if intrinsics_latent is None else [pose_state, intrinsics_state]
        if all(state and key in state for state in states):
            _map_pair([state[key] for state in states], gradient**power, index)


def _map_pair(tensors: list[Tensor], matrix: Float[Tensor, "c k k"], index: Tensor) -> None:
    """[z; w] <- matrix [z; w] in place: z [n, 6] per image, w [c, m] per row, each row's image terms summed in."""
    p = NUM_POSE_PARAMS
    z = tensors[0].to(torch.float64)
    new_z = (matrix[index, :p, :p] @ z[..., None])[..., 0]
    if len(tensors) > 1:
        w = tensors[1].to(torch.float64)
        new_z = new_z + (matrix[index, :p, p:] @ w[index][..., None])[..., 0]
        from_images = (matrix[index, p:, :p] @ z[..., None])[..., 0]
        new_w = (matrix[:, p:, p:] @ w[..., None])[..., 0] + torch.zeros_like(w).index_add_(0, index, from_images)
        tensors[1].copy_(new_w.to(tensors[1].dtype))
    tensors[0].copy_(new_z.to(tensors[0].dtype))


def mean_per_camera(
    values: Float[Tensor, "n d"], camera_of_image: Int[Tensor, " n"], num_cameras: int
) -> Float[Tensor, "n d"]:
    """Each image's row replaced by the mean over its physical camera's images, in ``values``' dtype."""
    count = torch.bincount(camera_of_image, minlength=num_cameras).to(values)  # [C]
    sums = torch.zeros(num_cameras, values.shape[1], dtype=values.dtype, device=values.device)
    sums = sums.index_add_(0, camera_of_image, values)  # [C, d]
    return (sums / count.clamp(min=1.0)[:, None])[camera_of_image]


def _check_camera_index(camera_of_image: Tensor, num_cameras: int, num_images: int) -> None:
    if camera_of_image.ndim != 1 or camera_of_image.shape[0] != num_images:
        raise ValueError(
            f"camera_of_image must have shape [{num_images}] (one camera per image), got {tuple(camera_of_image.shape)}"
        )
    if camera_of_image.numel() and (int(camera_of_image.min()) < 0 or int(camera_of_image.max()) >= num_cameras):
        raise ValueError(
            f"camera_of_image must lie in [0, {num_cameras - 1}], got values in "
            f"[{int(camera_of_image.min())}, {int(camera_of_image.max())}]"
        )


__all__ = [
    "NUM_POSE_PARAMS",
    "SharedPreconditioner",
    "block_triangular_factor",
    "compute_shared_preconditioner",
    "mean_per_camera",
    "reexpress_latents",
]
