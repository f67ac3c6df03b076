"""Inverse transforms from the unit cube to the contracted camera view frustum (paper eqs. 6-14).

``u = (u1, u2, u3)`` in ``[0, 1]^3`` maps to contracted radius ``r = Q_r(u1)``, a vertical coordinate from ``u2`` and
a horizontal one from ``u3``, then to the Euclidean OpenCV camera frame by the inverse contraction (paper eq. 10). The
angular extent per camera is ``tangent_bounds [N, 4] = (a_min, a_max, b_min, b_max)`` of ``a = x/z``, ``b = y/z``.

Angular transforms:

- ``"spherical"``: the paper's separable transform (eqs. 11-12) in azimuth ``az`` about y, uniform in
  ``[atan a_min, atan a_max]``, and elevation ``el = asin(sin e0 + u2 (sin e1 - sin e0))``, ``e = atan b`` (eq. 14's
  polar angle makes eq. 11's denominator zero); near the left and right edges some samples leave the image.
- ``"pyramid"``: the exact pinhole pyramid, density ``(1 + a^2 + b^2)^(-3/2)`` on tangents; ``a`` from its marginal
  CDF ``c(a) = asin(x s1) - asin(x s0)``, ``x = sin(atan a)``, ``s_j = sin(atan b_j)``, inverted as
  ``x = sin c / sqrt((s1 - s0)^2 + 4 s0 s1 sin^2(c/2))``, ``a = x / sqrt(1 - x^2)``; then ``b`` given ``a`` from
  ``h(b) = b / sqrt(1 + a^2 + b^2)``, ``b = h sqrt(1 + a^2) / sqrt(1 - h^2)``. Every sample projects into the image.
- ``"pixel"``: uniform in tangents (CamP's angular measure); not volume preserving.

Radial maps: ``"volume"`` is the paper's ``Q_r`` (eq. 12), uniform in contracted volume; ``"ray"`` is uniform in
contracted distance along each ray, ``r = t0 + u1 (t1 - t0)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.contraction import uncontract_radius
from s2camp_ns.core.validation import check_choice, check_finite, check_range

__all__ = [
    "RADIALS", "TRANSFORMS", "Range", "FrustumSamples", "Radial", "Transform", "directions_from_unit",
    "map_unit_to_frustum", "radius_from_unit", "radius_per_camera", "sample_frustum", "validate_frustum",
]  # fmt: skip

Transform = Literal["pyramid", "spherical", "pixel"]
TRANSFORMS: tuple[str, ...] = ("pyramid", "spherical", "pixel")
Radial = Literal["volume", "ray"]
RADIALS: tuple[str, ...] = ("volume", "ray")


@dataclass(frozen=True)
class FrustumSamples:
    """[n, l, 3] contracted points (radius in ``[t_near, t_far]``) and their Euclidean camera-frame preimages."""

    contracted: Float[Tensor, "n l 3"]
    camera: Float[Tensor, "n l 3"]


def validate_frustum(
    tangent_bounds: Float[Tensor, "n 4"],
    t_near: Range,
    t_far: Range,
    transform: str = "pyramid",
    radial: str = "volume",
) -> Float[Tensor, "n 4"]:
    """ValueError unless the frustum is valid; returns the bounds as float64 on their device."""
    check_choice("transform", transform, TRANSFORMS)
    check_choice("radial", radial, RADIALS)
    check_range("t_far", t_far, low=0.0, high=2.0, low_inclusive=False, high_inclusive=False)
    if isinstance(t_near, Tensor) or isinstance(t_far, Tensor):
        near = torch.as_tensor(t_near, dtype=torch.float64)
        far = torch.as_tensor(t_far, dtype=torch.float64)
        check_range("t_near", near, low=0.0)
        check_range("t_far - t_near", far - near, low=0.0, low_inclusive=False)
        for name, value in (("t_near", near), ("t_far", far)):
            if value.ndim > 0 and (value.ndim != 1 or value.numel() != tangent_bounds.shape[0]):
                raise ValueError(
                    f"{name} must be a float or hold one value per camera (N = "
                    f"{tangent_bounds.shape[0]}), got shape {tuple(value.shape)}"
                )
    else:
        check_range("t_near", t_near, low=0.0, high=float(t_far), high_inclusive=False)
    if not isinstance(tangent_bounds, Tensor) or tangent_bounds.ndim != 2 or tangent_bounds.shape[-1] != 4:
        shape = tuple(tangent_bounds.shape) if isinstance(tangent_bounds, Tensor) else type(tangent_bounds).__name__
        raise ValueError(f"tangent_bounds must have shape [N, 4] (a_min, a_max, b_min, b_max), got {shape}")
    bounds = tangent_bounds.detach().to(torch.float64)
    # finite tangents also exclude fields of view of 180 degrees or more
    check_finite("tangent_bounds", bounds)
    check_range("tangent_bounds a_max - a_min", bounds[:, 1] - bounds[:, 0], low=0.0, low_inclusive=False)
    check_range("tangent_bounds b_max - b_min", bounds[:, 3] - bounds[:, 2], low=0.0, low_inclusive=False)
    return bounds


Range = float | Tensor
"""A contracted radius for every camera (float) or one per camera (tensor [N])."""


def radius_per_camera(u1: Float[Tensor, " l"], t_near: Tensor, t_far: Tensor, radial: str = "volume") -> Tensor:
    """Radii [N, L] of ``u1`` [L] for ranges [N], each distinct range mapped with Python floats, so a camera's
    radii are the same bits whatever its batch (vectorised and scalar ``pow`` round differently)."""
    ranges = torch.stack([t_near.reshape(-1), t_far.reshape(-1)], dim=-1).detach().to(torch.float64).cpu()
    unique, index = torch.unique(ranges, dim=0, return_inverse=True)
    radii = [radius_from_unit(u1, float(near), float(far), radial) for near, far in unique.tolist()]
    return torch.stack(radii)[index.to(u1.device)]


def radius_from_unit(u1: Tensor, t_near: float, t_far: float, radial: str = "volume") -> Tensor:
    """``[t0^3 + u1 (t1^3 - t0^3)]^(1/3)`` (``"volume"``, paper eq. 12) or ``t0 + u1 (t1 - t0)`` (``"ray"``)."""
    if radial == "ray":
        return t_near + u1 * (t_far - t_near)
    cube = t_near**3 + u1 * (t_far**3 - t_near**3)
    return cube.clamp_min(0.0).pow(1.0 / 3.0)


def _column(bounds: Tensor, index: int, like: Tensor) -> Tensor:
    """Bound ``index`` per camera, broadcastable against ``like`` [N, ...]."""
    return bounds[:, index].reshape((-1,) + (1,) * (like.ndim - 1))


def _pyramid_strip(a: Tensor, s0: Tensor, s1: Tensor) -> Tensor:
    """Solid angle ``c(a) = G(a, b1) - G(a, b0)`` of ``[0, a] x [b0, b1]``, with ``s_j = sin(atan b_j)``."""
    x = a / torch.sqrt(1.0 + a * a)
    return torch.asin(x * s1) - torch.asin(x * s0)


def _pyramid_strip_inverse(c: Tensor, s0: Tensor, s1: Tensor) -> Tensor:
    """Closed-form inverse of ``_pyramid_strip`` (module docstring)."""
    half = torch.sin(0.5 * c)
    x = torch.sin(c) / torch.sqrt((s1 - s0) ** 2 + 4.0 * s0 * s1 * half * half)
    x = x.clamp(-1.0 + 1e-16, 1.0 - 1e-16)
    return x / torch.sqrt((1.0 - x) * (1.0 + x))


def directions_from_unit(
    u_vertical: Float[Tensor, "*batch"],
    u_horizontal: Float[Tensor, "*batch"],
    bounds: Float[Tensor, "n 4"],
    transform: str,
) -> Float[Tensor, "*batch 3"]:
    """Unit ray directions from ``u_vertical`` (u2: elevation / ``b``) and ``u_horizontal`` (u3: azimuth / ``a``)."""
    a0, a1 = _column(bounds, 0, u_horizontal), _column(bounds, 1, u_horizontal)
    b0, b1 = _column(bounds, 2, u_vertical), _column(bounds, 3, u_vertical)
    if transform == "pixel":
        a = a0 + u_horizontal * (a1 - a0)
        b = b0 + u_vertical * (b1 - b0)
        direction = torch.stack([a, b, torch.ones_like(a)], dim=-1)
        return direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True)
    if transform == "spherical":
        az = torch.atan(a0) + u_horizontal * (torch.atan(a1) - torch.atan(a0))
        sin_e0, sin_e1 = b0 / torch.sqrt(1.0 + b0 * b0), b1 / torch.sqrt(1.0 + b1 * b1)
        sin_el = (sin_e0 + u_vertical * (sin_e1 - sin_e0)).clamp(-1.0, 1.0)
        cos_el = torch.sqrt((1.0 - sin_el) * (1.0 + sin_el))
        return torch.stack([cos_el * torch.sin(az), sin_el, cos_el * torch.cos(az)], dim=-1)
    s0, s1 = b0 / torch.sqrt(1.0 + b0 * b0), b1 / torch.sqrt(1.0 + b1 * b1)
    c_lo, c_hi = _pyramid_strip(a0, s0, s1), _pyramid_strip(a1, s0, s1)
    a = _pyramid_strip_inverse(c_lo + u_horizontal * (c_hi - c_lo), s0, s1)
    # the inverse can overshoot the box by an ulp
    a = torch.minimum(torch.maximum(a, a0), a1)
    rho = 1.0 + a * a
    h0, h1 = b0 / torch.sqrt(rho + b0 * b0), b1 / torch.sqrt(rho + b1 * b1)
    h = h0 + u_vertical * (h1 - h0)
    b = h * torch.sqrt(rho / ((1.0 - h) * (1.0 + h)))
    b = torch.minimum(torch.maximum(b, b0), b1)
    direction = torch.stack([a, b, torch.ones_like(a)], dim=-1)
    return direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True)


def _as_batched_unit(unit_points: Tensor, num_cameras: int, device: torch.device) -> Tensor:
    if not isinstance(unit_points, Tensor) or unit_points.ndim not in (2, 3) or unit_points.shape[-1] != 3:
        shape = tuple(unit_points.shape) if isinstance(unit_points, Tensor) else type(unit_points).__name__
        raise ValueError(f"unit_points must have shape [L, 3] or [N, L, 3], got {shape}")
    if unit_points.ndim == 3 and unit_points.shape[0] != num_cameras:
        raise ValueError(
            f"unit_points must have N = {num_cameras} cameras to match tangent_bounds, got {unit_points.shape[0]}"
        )
    check_range("unit_points", unit_points, low=0.0, high=1.0)
    return unit_points.detach().to(device=device, dtype=torch.float64)


def map_unit_to_frustum(
    unit_points: Float[Tensor, "l 3"] | Float[Tensor, "n l 3"],
    bounds: Float[Tensor, "n 4"],
    t_near: Range,
    t_far: Range,
    transform: str,
    radial: str = "volume",
) -> Float[Tensor, "n l 3"]:
    """Contracted points ``Q(u)`` (paper eqs. 8-9, 12) without validation; shared points ([L, 3]) give each camera
    the same bits whatever its batch."""
    if isinstance(t_near, Tensor) or isinstance(t_far, Tensor):
        n = bounds.shape[0]
        near = torch.as_tensor(t_near, dtype=torch.float64, device=bounds.device).expand(n)
        far = torch.as_tensor(t_far, dtype=torch.float64, device=bounds.device).expand(n)
        if unit_points.ndim == 2:
            radius = radius_per_camera(unit_points[..., 0], near, far, radial)
        else:
            radius = radius_from_unit(unit_points[..., 0], near[:, None], far[:, None], radial)
    else:
        radius = radius_from_unit(unit_points[..., 0], t_near, t_far, radial)
    if unit_points.ndim == 2:
        unit_points = unit_points.expand(bounds.shape[0], -1, -1)
    directions = directions_from_unit(unit_points[..., 1], unit_points[..., 2], bounds, transform)
    return radius.unsqueeze(-1) * directions


def sample_frustum(
    unit_points: Float[Tensor, "l 3"] | Float[Tensor, "n l 3"],
    tangent_bounds: Float[Tensor, "n 4"],
    t_near: Range,
    t_far: Range,
    transform: Transform = "pyramid",
    radial: Radial = "volume",
) -> FrustumSamples:
    """Unit-cube points [L, 3] or [N, L, 3] into each contracted frustum and back to Euclidean (paper eqs. 6-14),
    float64 on the bounds' device. ``t_near``, ``t_far``: floats or [N]."""
    bounds = validate_frustum(tangent_bounds, t_near, t_far, transform, radial)
    u = _as_batched_unit(unit_points, bounds.shape[0], bounds.device)
    if not isinstance(t_near, Tensor) and not isinstance(t_far, Tensor):
        t_near, t_far = float(t_near), float(t_far)
    contracted = map_unit_to_frustum(u, bounds, t_near, t_far, transform, radial)
    radius = torch.linalg.vector_norm(contracted, dim=-1, keepdim=True)
    # r_euclid / r_contracted, exactly 1 for r <= 1
    scale = torch.where(radius <= 1.0, torch.ones_like(radius), uncontract_radius(radius) / radius.clamp_min(1.0))
    return FrustumSamples(contracted=contracted, camera=contracted * scale)
