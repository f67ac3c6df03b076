"""Analytic Jacobian of the stacked projection (paper eq. 4) and the sensitivity Gram matrix (paper eq. 5).

Derivatives with respect to the 16 deltas of ``camera.PARAMETER_NAMES`` at the current camera, the pose delta a local
twist at xi = 0 (so P does not depend on where the camera sits in the world):

    dx'/drho = -I,    dx'/domega = [x]_x            (x' = R_d^T (x - t_d), R_d = exp([omega]_x))
    u = fx a_d + s b_d + cx,  v = fy b_d + cy
    du/dfocal = a_d, dv/dfocal = b_d;  du/dcx = 1, dv/dcy = 1;  du/dskew = b_d
    d(u, v)/dc = (fx da_d/dc + s db_d/dc, fy db_d/dc) for every distortion coefficient c

Perspective (a = x/z, b = y/z, r^2 = a^2 + b^2, D = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8, D' = dD/d(r^2)):

    da/dx = (1/z, 0, -x/z^2),   db/dx = (0, 1/z, -y/z^2)
    d(a_d, b_d)/d(a, b) = D I + 2 D' (a, b)^T (a, b) + [[2 p1 b + 6 p2 a, 2 p1 a + 2 p2 b],
                                                         [2 p2 b + 2 p1 a, 2 p2 a + 6 p1 b]]
    d(a_d, b_d)/dk_j = (a, b) r^(2j);  d/dp1 = (2 a b, r^2 + 2 b^2);  d/dp2 = (r^2 + 2 a^2, 2 a b)

Fisheye (rho = |(x, y)|, R = |x|^2, theta = atan2(rho, z), h = theta / rho, P = theta_d / theta as a polynomial in
theta^2, Q = dP/d(theta^2); (a_d, b_d) = (x, y) m with m = h P):

    dh/d(x, y) = (x, y) q with q = (z / R - h) / rho^2,   dh/dz = -1 / R
    d(theta^2)/d(x, y) = 2 z h (x, y) / R,   d(theta^2)/dz = -2 rho^2 h / R
    dm/d(x, y) = (x, y) c with c = q P + 2 z h^2 Q / R,   dm/dz = -(P + 2 rho^2 h^2 Q) / R
    d(a_d, b_d)/d(x, y, z) = [[m + x^2 c, x y c, x dm/dz], [x y c, m + y^2 c, y dm/dz]]
    d(a_d, b_d)/dk_j = (x, y) h theta^(2j)
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, ParameterLayout, in_image, project, skew_matrix
from s2camp_ns.core.distortion import distortion_factor, distortion_slope, fisheye_terms, tangent_distortion_jacobian


def _perspective_terms(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics, duv_dd: Float[Tensor, "n 1 2 2"]
) -> tuple[Float[Tensor, "n l 2 3"], list[Float[Tensor, "n l 2"]], Tensor, Tensor]:
    """d(u, v)/d(x, y, z), d(u, v)/d(k1, k2, k3, k4, p1, p2) and (a_d, b_d) of a perspective camera."""
    x, y, z = points_cam.unbind(dim=-1)
    safe_z = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    inv_z = 1.0 / safe_z
    a, b = x * inv_z, y * inv_z
    r2 = a * a + b * b
    k1, k2, k3, k4, p1, p2 = (getattr(intrinsics, name)[:, None] for name in ("k1", "k2", "k3", "k4", "p1", "p2"))
    fx, fy, skew = intrinsics.fx[:, None], intrinsics.fy[:, None], intrinsics.skew[:, None]
    factor = distortion_factor(r2, k1, k2, k3, k4)
    a_d = a * factor + (2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a))
    b_d = b * factor + (2.0 * p2 * a * b + p1 * (r2 + 2.0 * b * b))
    zeros = torch.zeros_like(a)
    # d(a, b)/d(x, y, z): [n, l, 2, 3]
    dab_dx = torch.stack(
        [torch.stack([inv_z, zeros, -a * inv_z], dim=-1), torch.stack([zeros, inv_z, -b * inv_z], dim=-1)], dim=-2
    )
    duv_dx = duv_dd @ tangent_distortion_jacobian(a, b, intrinsics) @ dab_dx
    radial_u = fx * a + skew * b
    radial_v = fy * b
    coefficients = [
        torch.stack([radial_u * r2, radial_v * r2], dim=-1),
        torch.stack([radial_u * r2 * r2, radial_v * r2 * r2], dim=-1),
        torch.stack([radial_u * r2 * r2 * r2, radial_v * r2 * r2 * r2], dim=-1),
        torch.stack([radial_u * r2 * r2 * r2 * r2, radial_v * r2 * r2 * r2 * r2], dim=-1),
    ]
    two_ab = 2.0 * a * b
    for d_a, d_b in ((two_ab, r2 + 2.0 * b * b), (r2 + 2.0 * a * a, two_ab)):
        coefficients.append(torch.stack([fx * d_a + skew * d_b, fy * d_b], dim=-1))
    return duv_dx, coefficients, a_d, b_d


def _fisheye_terms(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics, duv_dd: Float[Tensor, "n 1 2 2"]
) -> tuple[Float[Tensor, "n l 2 3"], list[Float[Tensor, "n l 2"]], Tensor, Tensor]:
    """d(u, v)/d(x, y, z), d(u, v)/d(k1, k2, k3, k4, p1, p2) and (a_d, b_d) of a fisheye camera (no p1, p2: zero)."""
    x, y, z = points_cam.unbind(dim=-1)
    terms = fisheye_terms(points_cam)
    h, theta2, q, norm2 = terms.h, terms.theta2, terms.q, terms.norm2
    k1, k2, k3, k4 = (getattr(intrinsics, name)[:, None] for name in ("k1", "k2", "k3", "k4"))
    poly = distortion_factor(theta2, k1, k2, k3, k4)
    slope = distortion_slope(theta2, k1, k2, k3, k4)
    m = h * poly
    c = q * poly + 2.0 * z * h * h * slope / norm2
    m_z = -(poly + 2.0 * (x * x + y * y) * h * h * slope) / norm2
    dd_dx = torch.stack([
        torch.stack([m + x * x * c, x * y * c, x * m_z], dim=-1),
        torch.stack([x * y * c, m + y * y * c, y * m_z], dim=-1),
    ], dim=-2)  # fmt: skip
    fx, fy, skew = intrinsics.fx[:, None], intrinsics.fy[:, None], intrinsics.skew[:, None]
    power = torch.ones_like(theta2)
    coefficients = []
    for _ in range(4):
        power = power * theta2
        d_a, d_b = x * h * power, y * h * power
        coefficients.append(torch.stack([fx * d_a + skew * d_b, fy * d_b], dim=-1))
    zeros = torch.zeros_like(x)
    coefficients += [torch.stack([zeros, zeros], dim=-1)] * 2
    return duv_dd @ dd_dx, coefficients, x * m, y * m


def projection_jacobian(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics, layout: ParameterLayout | None = None
) -> tuple[Float[Tensor, "n l 2"], Float[Tensor, "n l 2 k"], Bool[Tensor, "n l"]]:
    """Pixels, the Jacobian d(u, v)/dPhi (paper eq. 4) with columns ``layout.indices``, and the in-image mask, in the
    inputs' dtype (float64 for a Gram matrix). Fisheye p1, p2 columns are zero."""
    layout = layout or ParameterLayout()
    pixels, depth = project(points_cam, intrinsics)
    mask = in_image(pixels, depth, intrinsics)
    fx, fy, skew = intrinsics.fx[:, None], intrinsics.fy[:, None], intrinsics.skew[:, None]
    # d(u, v)/d(a_d, b_d): [n, 1, 2, 2]
    duv_dd = torch.stack([torch.stack([fx, skew], dim=-1), torch.stack([torch.zeros_like(fy), fy], dim=-1)], dim=-2)
    terms = _fisheye_terms if intrinsics.is_fisheye else _perspective_terms
    duv_dx, coefficients, a_d, b_d = terms(points_cam, intrinsics, duv_dd)  # duv_dx: [n, l, 2, 3]
    d_rho = -duv_dx  # dx'/drho = -I
    d_omega = duv_dx @ skew_matrix(points_cam)  # dx'/domega = [x]_x
    ones, zeros = torch.ones_like(a_d), torch.zeros_like(a_d)
    columns = [
        d_rho[..., 0], d_rho[..., 1], d_rho[..., 2], d_omega[..., 0], d_omega[..., 1], d_omega[..., 2],
        torch.stack([a_d, b_d], dim=-1),  # focal
        torch.stack([ones, zeros], dim=-1), torch.stack([zeros, ones], dim=-1),  # cx, cy
        torch.stack([b_d, zeros], dim=-1),  # skew
    ]  # fmt: skip
    columns += coefficients
    jacobian = torch.stack([columns[i] for i in layout.indices], dim=-1)
    return pixels, jacobian, mask


def gram_matrix(
    jacobian: Float[Tensor, "n l 2 k"], mask: Bool[Tensor, "n l"], image_scale: Float[Tensor, " n"]
) -> tuple[Float[Tensor, "n k k"], Tensor]:
    """Float64 Sigma = J^T J (paper eq. 5) per camera and its number of valid points: pixels divided by max(W, H)
    and the mean over valid points, so Sigma depends on neither resolution nor L; no valid point: Sigma = 0."""
    jac = jacobian.to(torch.float64) / image_scale.to(torch.float64)[:, None, None, None]
    jac = jac * mask[..., None, None].to(torch.float64)
    count = mask.sum(dim=-1)
    # one product per camera: a batched product's summation order depends on the batch, and P must not
    flat = jac.flatten(1, 2)
    k = jac.shape[-1]
    sigma = torch.stack([rows.T @ rows for rows in flat]) if len(flat) else jac.new_zeros((0, k, k))
    sigma = sigma / count.clamp(min=1).to(torch.float64)[:, None, None]
    return 0.5 * (sigma + sigma.transpose(-1, -2)), count


def relative_gram_error(sigma: Float[Tensor, "n k k"], reference: Float[Tensor, "n k k"]) -> Float[Tensor, " n"]:
    """Relative Frobenius error ||Sigma_L - Sigma_ref||_F / ||Sigma_ref||_F per camera."""
    diff = torch.linalg.matrix_norm((sigma - reference).to(torch.float64))
    return diff / torch.linalg.matrix_norm(reference.to(torch.float64))
