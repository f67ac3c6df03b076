"""CamP's published proxy-point sampler (the random baseline of paper sec. 5), ``'frustum_raydist_fn'``.

- a uniform random pixel in ``[0, W - 1/2] x [0, H - 1/2]`` (CamP scales uniform draws by ``size - 1 + 1/2``),
  unprojected through the camera model to a unit ray;
- a Euclidean distance ``t`` along it, uniform in ``s = (L(t) - L(t_near)) / (L(t_far) - L(t_near))`` with Tukey's
  power ladder ``L(x) = |p - 1| / p ((1 + x / |p - 1|)^p - 1)`` (published ``p = -1.5``, ``t`` in ``[0.4, 1000]``).

No scene contraction: the points, and the Gram matrix, depend on the intrinsics only.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, pixel_to_ray_direction
from s2camp_ns.core.validation import check_positive_int, check_range

__all__ = [
    "CAMP_LADDER_P", "CAMP_T_FAR", "CAMP_T_NEAR", "camp_frustum_points", "inverse_power_ladder", "ladder_distance",
    "power_ladder", "validate_ladder",
]  # fmt: skip

CAMP_T_NEAR = 0.4  # CamP's PRECONDITION_NEAR: near distance along the unit ray, scene units
CAMP_T_FAR = 1000.0  # CamP's PRECONDITION_FAR
CAMP_LADDER_P = -1.5  # CamP's RAYDIST_FN_P: exponent of the power-ladder ray warp


def validate_ladder(t_near: float, t_far: float, ladder_p: float) -> None:
    """ValueError unless ``0 < t_near < t_far < inf`` and ``ladder_p < 0``."""
    check_range("t_near", t_near, low=0.0, low_inclusive=False)
    check_range("t_far", t_far, low=float(t_near), low_inclusive=False)
    check_range("ladder_p", ladder_p, high=0.0, high_inclusive=False)


def power_ladder(x: Tensor | float, p: float) -> Tensor | float:
    """Tukey's power ladder ``L(x) = |p - 1| / p ((1 + x / |p - 1|)^p - 1)`` for ``x >= 0`` and ``p < 0``."""
    q = abs(p - 1.0)
    return q / p * ((1.0 + x / q) ** p - 1.0)


def inverse_power_ladder(y: Tensor | float, p: float) -> Tensor | float:
    """Inverse of ``power_ladder``: ``x = |p - 1| ((1 + p y / |p - 1|)^(1/p) - 1)``."""
    q = abs(p - 1.0)
    return q * ((1.0 + p * y / q) ** (1.0 / p) - 1.0)


def ladder_distance(s: Tensor, t_near: float, t_far: float, ladder_p: float) -> Tensor:
    """``t = L^-1((1 - s) L(t_near) + s L(t_far))`` for ``s`` in ``[0, 1]``, clipped to ``[t_near, t_far]``."""
    near, far = power_ladder(t_near, ladder_p), power_ladder(t_far, ladder_p)
    t = inverse_power_ladder((1.0 - s) * near + s * far, ladder_p)
    return t.clamp(min=t_near, max=t_far)


def _pixel_directions(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 3"]:
    """Unit rays through pixels; without distortion the inverse intrinsics directly, the same numbers as
    ``pixel_to_ray_direction`` without its Newton iterations."""
    distortion = torch.stack([getattr(intrinsics, name) for name in ("k1", "k2", "k3", "k4", "p1", "p2")])
    if intrinsics.is_fisheye or bool((distortion != 0).any()):
        return pixel_to_ray_direction(pixels, intrinsics)
    b = (pixels[..., 1] - intrinsics.cy[:, None]) / intrinsics.fy[:, None]
    a = (pixels[..., 0] - intrinsics.cx[:, None] - intrinsics.skew[:, None] * b) / intrinsics.fx[:, None]
    directions = torch.stack([a, b, torch.ones_like(a)], dim=-1)
    return directions / torch.linalg.norm(directions, dim=-1, keepdim=True)


def camp_frustum_points(
    intrinsics: Intrinsics,
    num_points: int,
    t_near: float = CAMP_T_NEAR,
    t_far: float = CAMP_T_FAR,
    ladder_p: float = CAMP_LADDER_P,
    generator: torch.Generator | None = None,
    seed: int = 0,
) -> Float[Tensor, "n l 3"]:
    """[n, l, 3] float64 random proxy points in each OpenCV camera frame from draws ``(d_u, d_v, s)``: pixel
    ``(d_u (W - 1/2), d_v (H - 1/2))``, distance ``ladder_distance(s)``. Drawn on the CPU (``generator`` or
    ``seed``), so every device gets the same points."""
    check_positive_int("num_points", num_points)
    validate_ladder(t_near, t_far, ladder_p)
    intrinsics = intrinsics.detach().to(dtype=torch.float64)
    if generator is None:
        generator = torch.Generator().manual_seed(int(seed))
    draws = torch.rand((intrinsics.num_cameras, num_points, 3), generator=generator, dtype=torch.float64)
    draws = draws.to(intrinsics.device)
    extent = torch.stack([intrinsics.width, intrinsics.height], dim=-1) - 0.5
    pixels = draws[..., :2] * extent[:, None, :]
    directions = _pixel_directions(pixels, intrinsics)
    distance = ladder_distance(draws[..., 2], float(t_near), float(t_far), float(ladder_p))
    return distance.unsqueeze(-1) * directions
