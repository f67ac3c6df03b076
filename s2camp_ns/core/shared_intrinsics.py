"""Preconditioner for intrinsics shared by all images of one physical camera (pose per image).

Setting. Image i of physical camera c refines its own pose delta d_i (the local twist, 6 columns) and shares the
intrinsics delta e_c (m columns: focal, principal point, skew, distortion as the layout enables them) with the other
images of c. Per image, the proxy-point Gram matrix (paper eq. 5) over (d_i, e_c) is

    Sigma = [[A, B], [B^T, C]]        A: 6 x 6 (pose), B: 6 x m (pose-intrinsics), C: m x m (intrinsics)

and it depends only on the intrinsics (the pose columns use the local twist), so all images of camera c share the
same Sigma_c. The projections of all images of c stack into one objective, sum_i |J [d_i; e_c]|^2, whose Gram is the
arrowhead matrix with blocks A on the diagonal, B in the last block column and n_c C in the corner.

Exact block factorization, no approximation of the cross terms. Completing the square per image,

    [d; e]^T Sigma [d; e] = |A^(1/2) (d + A^-1 B e)|^2 + e^T S e,    S = C - B^T A^-1 B  (Schur complement),

so the latents z_i = A^(1/2) (d_i + G e_c) with G = A^-1 B, and w_c = S^(1/2) e_c, turn every image's Gram into the
identity: per image the latent is T [d; e] with the block upper-triangular

    T = [[A^(1/2), A^(1/2) G], [0, S^(1/2)]],    T^-1 = [[A^-(1/2), -G S^-(1/2)], [0, S^-(1/2)]],   T^T T = Sigma.

T is an admissible preconditioner of paper eq. 17 (P^T P = Sigma); by eqs. 18-19 it is the symmetric root of eq. 20
up to an orthogonal factor, T = Q Sigma^(1/2), chosen here because it keeps the shared block separate: with one
image per camera it gives the same whitened spectrum as the per-image P. For the whole camera, the objective in the
latents is sum_i |z_i|^2 + n_c |w_c|^2: the whitened arrowhead is diag(I, ..., I, n_c I). The n_c is kept on purpose
(the "mean over images" convention): a unit step of w_c then moves every image's proxy points by one normalized unit
RMS, exactly as a unit step of z_i moves image i's, so one learning rate means the same image-space step for every
latent coordinate; the n_c-fold larger gradient of w_c (it sums n_c images) is what Adam's per-coordinate
normalization removes. The pose latent carries the compensating pose change -G e_c: when the shared intrinsics move,
each image's pose follows along the least-squares direction that keeps its proxy projections in place, which is what
decouples focal length from forward translation.

Damping (CamP's, as in ``s2camp_ns.core.preconditioner.damped_gram``) is added to Sigma before the factorization, so
A is positive definite and S >= damping_rel diag(C) stays positive definite when the intrinsics are nearly
unobservable. All of it is float64.
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
from s2camp_ns.core.validation import check_finite, check_range

NUM_POSE_PARAMS = 6


@dataclass(frozen=True)
class SharedPreconditioner:
    """Block upper-triangular T and T^-1 per physical camera (latent = T phi), and the undamped Gram they came from."""

    matrix: Float[Tensor, "c k k"]
    inverse: Float[Tensor, "c k k"]
    gram: Float[Tensor, "c k k"]

    @property
    def num_intrinsics(self) -> int:
        return self.matrix.shape[-1] - NUM_POSE_PARAMS


def block_triangular_factor(
    sigma: Float[Tensor, "c k k"], damping: DampingConfig | None = None
) -> tuple[Float[Tensor, "c k k"], Float[Tensor, "c k k"]]:
    """T and T^-1 with T^T T = Sigma + damping, T = [[A^(1/2), A^(1/2) G], [0, S^(1/2)]] (module docstring;
    paper eqs. 17-19 with the block-triangular choice of Q).

    The first ``NUM_POSE_PARAMS`` columns are the pose. With no intrinsics column T is the symmetric root of eq. 20.
    """
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
    """T and T^-1 for each physical camera (one row of ``intrinsics`` per camera) from its proxy points; ``ranges``:
    each camera's contracted [t_near, t_far] (``core.proxy_range``), None: the sampling's fixed range."""
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


def deltas_from_latents(
    pose_latent: Float[Tensor, "n 6"],
    intrinsics_latent: Float[Tensor, "c m"],
    camera_of_image: Int[Tensor, " n"],
    inverse: Float[Tensor, "c k k"],
) -> Float[Tensor, "n k"]:
    """Per-image deltas phi_i = T_c^-1 [z_i; w_c] (paper eq. 15 with the shared latent), float64, differentiable."""
    _check_camera_index(camera_of_image, intrinsics_latent.shape[0], pose_latent.shape[0])
    latent = torch.cat([pose_latent.to(torch.float64), intrinsics_latent.to(torch.float64)[camera_of_image]], dim=-1)
    return (inverse[camera_of_image] @ latent[..., None])[..., 0]


def joint_gram(sigma: Float[Tensor, "k k"], num_images: int) -> Float[Tensor, "kk kk"]:
    """Gram of the stacked projections of ``num_images`` images sharing intrinsics (the arrowhead matrix), over
    (d_1, ..., d_n, e), each image contributing ``sigma``."""
    check_range("num_images", num_images, low=1)
    p, k = NUM_POSE_PARAMS, sigma.shape[-1]
    m = k - p
    size = p * num_images + m
    out = sigma.new_zeros(size, size, dtype=torch.float64)
    sigma = sigma.to(torch.float64)
    for i in range(num_images):
        rows = slice(p * i, p * (i + 1))
        out[rows, rows] = sigma[:p, :p]
        out[rows, size - m :] = sigma[:p, p:]
        out[size - m :, rows] = sigma[p:, :p]
    out[size - m :, size - m :] = num_images * sigma[p:, p:]
    return out


def joint_inverse(inverse: Float[Tensor, "k k"], num_images: int) -> Float[Tensor, "kk kk"]:
    """The map from the joint latent (z_1, ..., z_n, w) to the joint deltas (d_1, ..., d_n, e) of one camera."""
    check_range("num_images", num_images, low=1)
    p, k = NUM_POSE_PARAMS, inverse.shape[-1]
    m = k - p
    size = p * num_images + m
    out = inverse.new_zeros(size, size, dtype=torch.float64)
    for i in range(num_images):
        rows = slice(p * i, p * (i + 1))
        out[rows, rows] = inverse[:p, :p]
        out[rows, size - m :] = inverse[:p, p:]
    out[size - m :, size - m :] = inverse[p:, p:]
    return out


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
    """Switch the latents from P_old to P_new in place without moving any camera (phi_i unchanged, paper eq. 15).

    Per intrinsics row c, M = P_new P_old^-1: z_i' = M_zz z_i + M_zw w_c and w_c' = M_ww w_c + sum_i M_wz z_i over
    the row's images. A block-triangular P (shared intrinsics) has M_wz = 0; the symmetric root has one image per row,
    so the sum is that image's term. Gradients map with G = M^-T = (P_old P_new^-1)^T the same way (g_z' = G_zz g_z
    + G_zw g_w, g_w' = G_ww g_w + sum_i G_wz g_z_i), and so does Adam's first moment, linear in the gradients; the
    second (elementwise) is mapped with the elementwise squares, assuming uncorrelated components (exact for a
    diagonal M). P changes slowly between refreshes, so M stays near the identity. ``intrinsics_latent`` None: the
    layout refines no intrinsics (K = 6).
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
    """[z; w] <- matrix [z; w] in place per image and row (``reexpress_latents``): z [n, 6] per image, w [c, m] per
    row, the rows' terms from their images summed in."""
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
    """Each image's row replaced by the mean over the images of its physical camera (``camera_of_image``, one index
    below ``num_cameras`` per image): the base intrinsics shared intrinsics start from, in ``values``' dtype."""
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
    "deltas_from_latents",
    "joint_gram",
    "joint_inverse",
    "mean_per_camera",
    "reexpress_latents",
]
