"""Analytic Jacobian of the stacked projection (paper eq. 4) and the sensitivity Gram matrix (paper eq. 5).

The Jacobian is taken with respect to the 12 deltas of ``camera.PARAMETER_NAMES`` at the current camera: the pose
delta is the local twist xi at zero, so the pose columns depend only on the camera-frame proxy points and the
preconditioner is independent of where the camera sits in the world. Closed forms at xi = 0:

    dx'/drho = -I,    dx'/domega = [x]_x            (x' = R_d^T (x - t_d), R_d = exp([omega]_x))
    da/dx = (1/z, 0, -x/z^2),   db/dx = (0, 1/z, -y/z^2)
    a_d = a D, b_d = b D, D = 1 + k1 r^2 + k2 r^4, D' = dD/d(r^2) = k1 + 2 k2 r^2
    d(a_d, b_d)/d(a, b) = D I + 2 D' (a, b)^T (a, b)
    u = fx a_d + s b_d + cx,  v = fy b_d + cy
    du/dfocal = a_d, dv/dfocal = b_d;  du/dcx = 1, dv/dcy = 1;  du/dskew = b_d
    d(u, v)/dk1 = (fx a + s b, fy b) r^2,   d(u, v)/dk2 = (fx a + s b, fy b) r^4
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, ParameterLayout, in_image, project, skew_matrix


def projection_jacobian(
    points_cam: Float[Tensor, "n l 3"],
    intrinsics: Intrinsics,
    layout: ParameterLayout | None = None,
) -> tuple[Float[Tensor, "n l 2"], Float[Tensor, "n l 2 k"], Bool[Tensor, "n l"]]:
    """Pixels, the analytic Jacobian d(u, v)/dPhi (paper eq. 4) per point, and the in-image mask.

    Columns follow ``layout.indices`` (all 12 parameters by default). Computed in the dtype of the inputs; pass
    float64 inputs when the result feeds a Gram matrix.
    """
    layout = layout or ParameterLayout()
    x, y, z = points_cam.unbind(dim=-1)
    pixels, depth = project(points_cam, intrinsics)
    mask = in_image(pixels, depth, intrinsics)
    safe_z = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    inv_z = 1.0 / safe_z
    a, b = x * inv_z, y * inv_z
    r2 = a * a + b * b
    k1, k2 = intrinsics.k1[:, None], intrinsics.k2[:, None]
    fx, fy, skew = intrinsics.fx[:, None], intrinsics.fy[:, None], intrinsics.skew[:, None]
    factor = 1.0 + r2 * (k1 + k2 * r2)
    factor_slope = k1 + 2.0 * k2 * r2
    a_d, b_d = a * factor, b * factor

    zeros = torch.zeros_like(a)
    # d(a, b)/d(x, y, z): [n, l, 2, 3]
    dab_dx = torch.stack(
        [torch.stack([inv_z, zeros, -a * inv_z], dim=-1), torch.stack([zeros, inv_z, -b * inv_z], dim=-1)], dim=-2
    )
    # d(a_d, b_d)/d(a, b): [n, l, 2, 2]
    dd_dab = torch.stack(
        [
            torch.stack([factor + 2.0 * factor_slope * a * a, 2.0 * factor_slope * a * b], dim=-1),
            torch.stack([2.0 * factor_slope * a * b, factor + 2.0 * factor_slope * b * b], dim=-1),
        ],
        dim=-2,
    )
    # d(u, v)/d(a_d, b_d): [n, 1, 2, 2]
    duv_dd = torch.stack([torch.stack([fx, skew], dim=-1), torch.stack([torch.zeros_like(fy), fy], dim=-1)], dim=-2)
    duv_dx = duv_dd @ dd_dab @ dab_dx  # [n, l, 2, 3]
    # Local twist at zero: dx'/drho = -I, dx'/domega = [x]_x.
    d_rho = -duv_dx
    d_omega = duv_dx @ skew_matrix(points_cam)

    ones = torch.ones_like(a)
    radial_u = fx * a + skew * b
    radial_v = fy * b
    columns = [
        d_rho[..., 0],
        d_rho[..., 1],
        d_rho[..., 2],
        d_omega[..., 0],
        d_omega[..., 1],
        d_omega[..., 2],
        torch.stack([a_d, b_d], dim=-1),
        torch.stack([ones, zeros], dim=-1),
        torch.stack([zeros, ones], dim=-1),
        torch.stack([b_d, zeros], dim=-1),
        torch.stack([radial_u * r2, radial_v * r2], dim=-1),
        torch.stack([radial_u * r2 * r2, radial_v * r2 * r2], dim=-1),
    ]
    jacobian = torch.stack([columns[i] for i in layout.indices], dim=-1)
    return pixels, jacobian, mask


def gram_matrix(
    jacobian: Float[Tensor, "n l 2 k"], mask: Bool[Tensor, "n l"], image_scale: Float[Tensor, " n"]
) -> tuple[Float[Tensor, "n k k"], Tensor]:
    """Sensitivity Gram matrix Sigma = J^T J (paper eq. 5) in float64, and the number of points used per camera.

    Two choices that eq. 5 leaves open (docs/DESIGN-NOTES.md sec. 2 and 3): pixels are divided by max(W, H), so
    Sigma does not depend on the image resolution, and the sum is replaced by the mean over the points that project
    inside the image, so Sigma (and with it the effective learning rate) does not grow with the number of points L.
    A camera with no valid point gets Sigma = 0; the preconditioner's damping then keeps P finite.
    """
    jac = jacobian.to(torch.float64) / image_scale.to(torch.float64)[:, None, None, None]
    jac = jac * mask[..., None, None].to(torch.float64)
    count = mask.sum(dim=-1)
    sigma = torch.einsum("nlik,nlij->nkj", jac, jac)
    sigma = sigma / count.clamp(min=1).to(torch.float64)[:, None, None]
    return 0.5 * (sigma + sigma.transpose(-1, -2)), count


def relative_gram_error(sigma: Float[Tensor, "n k k"], reference: Float[Tensor, "n k k"]) -> Float[Tensor, " n"]:
    """Relative Frobenius error ||Sigma_L - Sigma_ref||_F / ||Sigma_ref||_F per camera."""
    diff = torch.linalg.matrix_norm((sigma - reference).to(torch.float64))
    return diff / torch.linalg.matrix_norm(reference.to(torch.float64))
