"""Forward maps that training never needs, kept as the tests' independent references: the frustum's CDF, the
inverse of ``s2camp_ns.core.frustum.sample_frustum`` (paper eqs. 6, 11), and the contraction of points (paper eq. 10)
with its inverse (the package contracts radii only, ``s2camp_ns.core.contraction``)."""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.frustum import Radial, Transform, validate_frustum
from s2camp_ns.core.validation import check_finite, check_range


def _column(bounds: Tensor, index: int, like: Tensor) -> Tensor:
    """Bound ``index`` of each camera, shaped to broadcast against ``like`` of shape [N, ...]."""
    return bounds[:, index].reshape((-1,) + (1,) * (like.ndim - 1))


def _pyramid_strip(a: Tensor, s0: Tensor, s1: Tensor) -> Tensor:
    """Solid angle ``G(a, b1) - G(a, b0)`` of ``[0, a] x [b0, b1]``, with ``s_j = sin(atan b_j)``."""
    x = a / torch.sqrt(1.0 + a * a)
    return torch.asin(x * s1) - torch.asin(x * s0)


def unit_from_radius(radius: Tensor, t_near: float, t_far: float, radial: str = "volume") -> Tensor:
    """Radial CDF: ``(r^3 - t0^3) / (t1^3 - t0^3)`` (paper eq. 11, ``"volume"``) or ``(r - t0) / (t1 - t0)``."""
    if radial == "ray":
        return (radius - t_near) / (t_far - t_near)
    return (radius**3 - t_near**3) / (t_far**3 - t_near**3)


def unit_from_directions(directions: Tensor, bounds: Tensor, transform: str) -> tuple[Tensor, Tensor]:
    """Forward angular CDFs ``(u_vertical, u_horizontal)`` of directions (paper eq. 11)."""
    x, y, z = directions.unbind(-1)
    a0, a1 = _column(bounds, 0, x), _column(bounds, 1, x)
    b0, b1 = _column(bounds, 2, x), _column(bounds, 3, x)
    if transform == "pixel":
        return (y / z - b0) / (b1 - b0), (x / z - a0) / (a1 - a0)
    if transform == "spherical":
        az = torch.atan2(x, z)
        sin_el = y / torch.linalg.vector_norm(directions, dim=-1)
        sin_e0, sin_e1 = b0 / torch.sqrt(1.0 + b0 * b0), b1 / torch.sqrt(1.0 + b1 * b1)
        u_h = (az - torch.atan(a0)) / (torch.atan(a1) - torch.atan(a0))
        return (sin_el - sin_e0) / (sin_e1 - sin_e0), u_h
    a, b = x / z, y / z
    s0, s1 = b0 / torch.sqrt(1.0 + b0 * b0), b1 / torch.sqrt(1.0 + b1 * b1)
    c_lo, c_hi = _pyramid_strip(a0, s0, s1), _pyramid_strip(a1, s0, s1)
    u_h = (_pyramid_strip(a, s0, s1) - c_lo) / (c_hi - c_lo)
    rho = 1.0 + a * a
    h0, h1 = b0 / torch.sqrt(rho + b0 * b0), b1 / torch.sqrt(rho + b1 * b1)
    return (b / torch.sqrt(rho + b * b) - h0) / (h1 - h0), u_h


def frustum_to_unit(
    contracted: Tensor,
    tangent_bounds: Tensor,
    t_near: float,
    t_far: float,
    transform: Transform = "pyramid",
    radial: Radial = "volume",
) -> Tensor:
    """Forward CDF ``F(p)`` [N, L, 3] of contracted frustum points [N, L, 3]; points outside the frustum get
    coordinates outside ``[0, 1]``."""
    bounds = validate_frustum(tangent_bounds, t_near, t_far, transform, radial)
    points = contracted.to(device=bounds.device, dtype=torch.float64)
    radius = torch.linalg.vector_norm(points, dim=-1)
    u_v, u_h = unit_from_directions(points, bounds, transform)
    return torch.stack([unit_from_radius(radius, t_near, t_far, radial), u_v, u_h], dim=-1)


def uncontract(points: Tensor) -> Tensor:
    """Closed-form inverse of ``contract`` (paper eq. 10) for points [..., 3] of radius below 2."""
    check_finite("points", points)
    radius = torch.linalg.vector_norm(points, dim=-1, keepdim=True)
    check_range("contracted radius |points|", radius, low=0.0, high=2.0, high_inclusive=False)
    far = radius.clamp_min(1.0)
    return points * torch.where(radius <= 1.0, torch.ones_like(radius), 1.0 / ((2.0 - far) * far))


def _norm(points: Tensor) -> Tensor:
    return torch.linalg.vector_norm(points, dim=-1, keepdim=True)


def contract(points: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
    """Contract camera-centred Euclidean points into the radius-2 ball (paper eq. 10)."""
    check_finite("points", points)
    radius = _norm(points)
    # s(r) / r, exactly 1 for r <= 1
    far = radius.clamp_min(1.0)
    factor = torch.where(radius <= 1.0, torch.ones_like(radius), (2.0 - 1.0 / far) / far)
    return points * factor
