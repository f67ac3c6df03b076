"""Latent maps written out in full, the tests' references for the refiner's compact ones (paper eq. 15):
per-image re-expression of a latent and of Adam's moments under a change of P, and the joint Gram, inverse and deltas
of images that share intrinsics (``s2camp_ns.core.shared_intrinsics`` stores only the per-camera blocks)."""

from __future__ import annotations

import torch
from jaxtyping import Float, Int
from torch import Tensor

from s2camp_ns.core.preconditioner import Preconditioner
from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS, _check_camera_index
from s2camp_ns.core.validation import check_range


@torch.no_grad()
def reexpress_latent(
    latent: Float[Tensor, "n k"], old: Preconditioner, new: Preconditioner, adam_state: dict | None = None
) -> None:
    """phi_hat_new = P_new P_old^-1 phi_hat_old in place, so phi is unchanged (paper eq. 15); Adam's state too."""
    change = new.matrix @ old.inverse
    latent.copy_((change.to(latent.device) @ latent.to(torch.float64)[..., None])[..., 0].to(latent.dtype))
    if adam_state:
        reexpress_adam_state(old, new, adam_state)


def reexpress_adam_state(old: Preconditioner, new: Preconditioner, adam_state: dict) -> None:
    """Map Adam's moments from P_old to P_new in place (eq. 15), M = P_new P_old^-1: m_new = M^-T m_old (exact),
    v_new = (M^-T)^2 v_old elementwise (exact for diagonal M). The step count is kept."""
    gradient_map = new.inverse.transpose(-1, -2) @ old.matrix.transpose(-1, -2)
    if "exp_avg" in adam_state:
        m = adam_state["exp_avg"]
        m.copy_((gradient_map.to(m.device) @ m.to(torch.float64)[..., None])[..., 0].to(m.dtype))
    if "exp_avg_sq" in adam_state:
        v = adam_state["exp_avg_sq"]
        v.copy_(((gradient_map**2).to(v.device) @ v.to(torch.float64)[..., None])[..., 0].to(v.dtype))


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
    """Arrowhead Gram over (d_1, ..., d_n, e) of ``num_images`` images sharing intrinsics, each with ``sigma``."""
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
