"""Inverse transforms from the unit cube to the normalized (contracted) camera view frustum (paper eqs. 6-14).

A point ``u = (u1, u2, u3)`` of ``[0, 1]^3`` is mapped to contracted radius ``r = Q_r(u1)`` (paper eq. 12,
cube root, so that equal volumes get equal mass), a vertical coordinate from ``u2`` and a horizontal one from
``u3``, then to the Euclidean camera frame through the inverse contraction (paper eq. 10). The camera frame is
OpenCV (x right, y down, z forward); the angular extent is given per camera as ``tangent_bounds [N, 4] =
(a_min, a_max, b_min, b_max)`` of the image-plane tangents ``a = x/z``, ``b = y/z``.

Three angular transforms; the first two are volume preserving up to the constant frustum volume (with the
``"volume"`` radial map, uniform in ``u`` means uniform in the contracted frustum):

``"spherical"``
    The paper's separable transform (eqs. 11-12) written with a well-defined angle pair. Eq. 14 takes the polar
    angle theta in ``[-alpha_y, alpha_y]``, which makes the eq. 11 denominator ``cos(theta_min) - cos(theta_max)``
    zero; we use azimuth ``az`` about the y axis and elevation ``el`` from the x-z plane instead, with volume
    element ``r^2 cos(el) dr d(el) d(az)``: ``az = Q_az(u3)`` uniform in ``[atan a_min, atan a_max]``,
    ``el = Q_el(u2) = asin(sin e0 + u2 (sin e1 - sin e0))`` with ``e = atan b``. This region is a latitude-longitude
    rectangle, not the pinhole pyramid: near the left and right image edges some samples project above or below
    the image (a few percent of the volume for typical cameras).
``"pyramid"``
    The exact pinhole pyramid. On tangents the solid-angle density is ``(1 + a^2 + b^2)^(-3/2)``; a conditional
    (Rosenblatt) transform samples ``a`` from its marginal and ``b`` given ``a``:

    - marginal CDF of ``a`` is proportional to ``c(a) = G(a, b1) - G(a, b0)`` with
      ``G(a, b) = atan(a b / sqrt(1 + a^2 + b^2)) = asin(sin(atan a) sin(atan b))``. Writing
      ``x = sin(atan a)`` and ``s_j = sin(atan b_j)``, ``c = asin(x s1) - asin(x s0)`` inverts in closed form for
      any (also asymmetric) b range: ``x = sin c / sqrt((s1 - s0)^2 + 4 s0 s1 sin^2(c/2))`` (take the cosine of
      both sides; the ``x^4`` terms cancel), then ``a = x / sqrt(1 - x^2)``.
    - conditional CDF of ``b`` given ``a`` is proportional to ``h(b) = b / sqrt(1 + a^2 + b^2)``, inverted by
      ``b = h sqrt(1 + a^2) / sqrt(1 - h^2)``.

    Every sample lies inside the tangent box, so every sample projects into the image.
``"pixel"``
    Uniform in the image-plane tangents, ``a = a0 + u3 (a1 - a0)``, ``b = b0 + u2 (b1 - b0)``: a uniform pixel of
    the undistorted pinhole camera, CamP's angular measure (without distortion). Not volume preserving: the
    solid-angle density grows towards the image corners as ``(1 + a^2 + b^2)^(3/2)``.

Two radial maps (``radial``):

``"volume"``
    The paper's ``Q_r`` (eq. 12): uniform in the contracted volume, so most points lie near ``t_far``.
``"ray"``
    Uniform in contracted distance along each ray, ``r = t0 + u1 (t1 - t0)`` (volume density ``1 / r^2`` in the
    contracted ball, weighting near points). This is not CamP's radial measure: CamP's published configuration
    warps Euclidean distance with a power ladder and does not contract (s2camp_ns/core/camp_sampling.py).
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
    "RADIALS",
    "TRANSFORMS",
    "Range",
    "FrustumSamples",
    "Radial",
    "Transform",
    "directions_from_unit",
    "map_unit_to_frustum",
    "radius_from_unit",
    "radius_per_camera",
    "sample_frustum",
    "validate_frustum",
]

Transform = Literal["pyramid", "spherical", "pixel"]
TRANSFORMS: tuple[str, ...] = ("pyramid", "spherical", "pixel")
Radial = Literal["volume", "ray"]
RADIALS: tuple[str, ...] = ("volume", "ray")


@dataclass(frozen=True)
class FrustumSamples:
    """Frustum samples per camera: contracted points (radius in ``[t_near, t_far]``) and their Euclidean preimages."""

    contracted: Float[Tensor, "n l 3"]
    camera: Float[Tensor, "n l 3"]


def validate_frustum(
    tangent_bounds: Float[Tensor, "n 4"],
    t_near: Range,
    t_far: Range,
    transform: str = "pyramid",
    radial: str = "volume",
) -> Float[Tensor, "n 4"]:
    """Check the frustum description and return the bounds as float64 on their own device."""
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
    # Finite tangents also exclude fields of view of 180 degrees or more.
    check_finite("tangent_bounds", bounds)
    check_range("tangent_bounds a_max - a_min", bounds[:, 1] - bounds[:, 0], low=0.0, low_inclusive=False)
    check_range("tangent_bounds b_max - b_min", bounds[:, 3] - bounds[:, 2], low=0.0, low_inclusive=False)
    return bounds


Range = float | Tensor
"""A contracted radius for every camera (float) or one per camera (tensor [N])."""


def radius_per_camera(u1: Float[Tensor, " l"], t_near: Tensor, t_far: Tensor, radial: str = "volume") -> Tensor:
    """Radii [N, L] of shared unit coordinates ``u1`` [L] for per-camera ranges ``t_near``, ``t_far`` [N].

    Each distinct range is mapped on its own by ``radius_from_unit`` with Python floats, exactly as a range given for
    all cameras is: a camera's radii are then the same bits whatever the batch it is computed in (vectorised and
    scalar ``pow`` loops round differently, and which elements take which loop depends on the batch layout).
    """
    ranges = torch.stack([t_near.reshape(-1), t_far.reshape(-1)], dim=-1).detach().to(torch.float64).cpu()
    unique, index = torch.unique(ranges, dim=0, return_inverse=True)
    radii = [radius_from_unit(u1, float(near), float(far), radial) for near, far in unique.tolist()]
    return torch.stack(radii)[index.to(u1.device)]


def radius_from_unit(u1: Tensor, t_near: float, t_far: float, radial: str = "volume") -> Tensor:
    """Radial inverse CDF: ``Q_r(u1) = [t0^3 + u1 (t1^3 - t0^3)]^(1/3)`` (paper eq. 12, ``"volume"``) or
    ``t0 + u1 (t1 - t0)`` (``"ray"``, uniform contracted distance)."""
    if radial == "ray":
        return t_near + u1 * (t_far - t_near)
    cube = t_near**3 + u1 * (t_far**3 - t_near**3)
    return cube.clamp_min(0.0).pow(1.0 / 3.0)


def _column(bounds: Tensor, index: int, like: Tensor) -> Tensor:
    """Bound ``index`` of each camera, shaped to broadcast against ``like`` of shape [N, ...]."""
    return bounds[:, index].reshape((-1,) + (1,) * (like.ndim - 1))


def _pyramid_strip(a: Tensor, s0: Tensor, s1: Tensor) -> Tensor:
    """Solid angle ``c(a) = G(a, b1) - G(a, b0)`` of ``[0, a] x [b0, b1]``, with ``s_j = sin(atan b_j)``."""
    x = a / torch.sqrt(1.0 + a * a)
    return torch.asin(x * s1) - torch.asin(x * s0)


def _pyramid_strip_inverse(c: Tensor, s0: Tensor, s1: Tensor) -> Tensor:
    """Closed-form inverse of :func:`_pyramid_strip` (derivation in the module docstring)."""
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
    """Unit ray directions from the two angular CDF coordinates (paper eqs. 8-9, 12, 14).

    ``u_vertical`` (``u2``) drives elevation / the ``b`` tangent, ``u_horizontal`` (``u3``) azimuth / ``a``.
    """
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
    # The inverse can overshoot the box by an ulp; clamping keeps "every sample projects inside" exact.
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
    """Contracted frustum points ``Q(u)`` (paper eqs. 8-9, 12), no validation (internal fast path).

    With points shared by all cameras ([L, 3]) and one range the radius does not depend on the camera and is
    computed once; this also keeps each camera's points bit-identical whatever the batch it is computed in
    (vectorised and scalar loops of ``pow`` round differently, and which elements take which loop depends on the
    batch's layout). Per-camera ranges (tensors [N]) keep that property with shared points (``radius_per_camera``).
    """
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
    """Map unit-cube points into each camera's contracted frustum and back to Euclidean camera-frame points.

    With the default ``"pyramid"`` / ``"volume"`` maps, uniform points in ``[0, 1]^3`` become uniform points in the
    contracted frustum with radius in ``[t_near, t_far]`` (paper eqs. 6-14; the other maps are described in the
    module docstring); the Euclidean points follow from the inverse contraction (paper eq. 10). Output is float64
    on the device of ``tangent_bounds``. With ``t_near = 0`` a point with ``u1 = 0`` sits on the camera centre.
    ``t_near`` and ``t_far`` are floats (every camera) or tensors [N] (one range per camera).
    """
    bounds = validate_frustum(tangent_bounds, t_near, t_far, transform, radial)
    u = _as_batched_unit(unit_points, bounds.shape[0], bounds.device)
    if not isinstance(t_near, Tensor) and not isinstance(t_far, Tensor):
        t_near, t_far = float(t_near), float(t_far)
    contracted = map_unit_to_frustum(u, bounds, t_near, t_far, transform, radial)
    radius = torch.linalg.vector_norm(contracted, dim=-1, keepdim=True)
    # Scale by r_euclid / r_contracted; for r <= 1 the ratio is exactly 1 (the contraction is the identity there).
    scale = torch.where(radius <= 1.0, torch.ones_like(radius), uncontract_radius(radius) / radius.clamp_min(1.0))
    return FrustumSamples(contracted=contracted, camera=contracted * scale)
