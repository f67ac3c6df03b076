"""Each physical camera's contracted proxy range [t_near, t_far] from the scene's own points (paper eqs. 10-12).

The proxy points fill a camera's contracted frustum between two contracted radii (paper eq. 12; t = d for d <= 1,
2 - 1/d beyond, eq. 10, d in normalized scene units). The Gram matrix (eq. 5) averages over them, so the range
weighs the depths: too far, rotation and translation look alike; too near, the 1/d^2 translation terms of unseen
points dominate. The range follows the distances d of the sparse points each image sees (in front of it, inside
it), pooled over a physical camera's images. ``rule``:

- "moments" (default): the proxy's E[1/d], E[1/d^2] match the content's (Sigma's translation block averages 1/z^2,
  its coupling 1/z, eqs. 4-5; the rest depends on direction only): (t0, t1) is the ``GRID_STEP`` grid point in
  [``T_NEAR_MIN``, ``T_FAR_MAX``], width >= ``min_width``, minimising (log M1/m1)^2 + (log M2/m2)^2, M the proxy's
  moments (midpoint rule over eq. 12's radial law), m the content's, its distances first clipped to their
  ``clip_quantile`` and 1 - ``clip_quantile`` quantiles.
- "fit": the proxy's radial CDF (eq. 11: (t^3 - t0^3) / (t1^3 - t0^3) for "volume", (t - t0) / (t1 - t0) for
  "ray") is a < b (``low_quantile``, ``high_quantile``) at the content's contracted quantiles c_a, c_b.
- "span": [t0, t1] = [c_a, c_b].

Points hidden behind nearer content count (sparse points carry no surface). ``margin`` is added on each side, then
t_near >= ``T_NEAR_MIN``, t_far <= ``T_FAR_MAX`` (t = 2 is infinity) and t_far - t_near >= ``min_width`` (grown about
the middle, then shifted back inside). A camera with fewer than ``min_points`` visible points gets ``DEFAULT_T_NEAR``,
``DEFAULT_T_FAR`` (``ProxyRanges.fallback``). An explicit ``t_near`` or ``t_far`` overrides that end for every
camera; the other is still chosen. Large scenes are thinned (``max_points``, ``max_images``). Float64, deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, in_image, project
from s2camp_ns.core.contraction import contract_radius, uncontract_radius
from s2camp_ns.core.frustum import radius_from_unit
from s2camp_ns.core.validation import check_finite, check_positive_int, check_range

__all__ = [
    "describe_proxy_ranges",
    "span",
    "DEFAULT_T_FAR",
    "DEFAULT_T_NEAR",
    "RULES",
    "T_FAR_MAX",
    "T_NEAR_MIN",
    "ProxyRangeConfig",
    "ProxyRanges",
    "clamp_range",
    "fit_radial_law",
    "fixed_range",
    "interpolated_quantile",
    "inverse_distance_moments",
    "match_inverse_moments",
    "proxy_ranges",
    "visible_distances",
]

DEFAULT_T_NEAR = 0.4
"""Near contracted radius of the fallback range (no points)."""
DEFAULT_T_FAR = 1.5
"""Far contracted radius of the fallback range (Euclidean 2, paper eq. 10)."""
T_NEAR_MIN = 0.1
"""Smallest chosen near radius (contracted = Euclidean below 1)."""
T_FAR_MAX = 1.99
"""Largest chosen far radius: the paper's, Euclidean 100 (paper eq. 10)."""
RULES: tuple[str, ...] = ("moments", "fit", "span")
GRID_STEP = 0.01
"""Resolution of the "moments" rule's search over (t0, t1), contracted units."""
_MOMENT_NODES = 512
"""Midpoint-rule nodes of the proxy radial law's moments."""
_PAIRS_PER_CHUNK = 1 << 20
"""Image-point pairs projected at a time by ``visible_distances``."""


@dataclass(frozen=True)
class ProxyRangeConfig:
    """How the proxy range is chosen from the scene's points (module docstring)."""

    rule: Literal["moments", "fit", "span"] = "moments"
    """"moments": match E[1/d], E[1/d^2]; "fit": match the radial law at two quantiles; "span": the two quantiles."""
    clip_quantile: float = 0.02
    """"moments": distances are clipped to this quantile and 1 - it first."""
    low_quantile: float = 0.25
    """"fit", "span": lower quantile level a of the distances."""
    high_quantile: float = 0.75
    """"fit", "span": upper quantile level b (above a)."""
    margin: float = 0.0
    """Contracted units added below t_near and above t_far before clamping."""
    min_width: float = 0.2
    """Smallest t_far - t_near, contracted units."""
    min_points: int = 20
    """Fewest visible points (pooled over a camera's images) for a chosen range; fewer: the defaults."""
    max_points: int = 50_000
    """Scene points used at most: a larger scene keeps every k-th point, k = ceil(M / max_points)."""
    max_images: int = 100
    """Images used at most per physical camera (evenly spread over its images, in their order)."""

    def validate(self) -> None:
        if self.rule not in RULES:
            raise ValueError(f"rule must be one of {', '.join(map(repr, RULES))}, got {self.rule!r}")
        check_range("clip_quantile", self.clip_quantile, low=0.0, high=0.5, high_inclusive=False)
        check_range("low_quantile", self.low_quantile, low=0.0, high=1.0, high_inclusive=False)
        check_range("high_quantile", self.high_quantile, low=self.low_quantile, high=1.0, low_inclusive=False)
        check_range("margin", self.margin, low=0.0, high=1.0)
        check_range("min_width", self.min_width, low=0.0, high=T_FAR_MAX - T_NEAR_MIN)
        check_positive_int("min_points", self.min_points)
        check_positive_int("max_points", self.max_points)
        check_positive_int("max_images", self.max_images)


@dataclass(frozen=True)
class ProxyRanges:
    """One contracted range per physical camera, how many visible points chose it, and which fell back."""

    t_near: Float[Tensor, " c"]
    t_far: Float[Tensor, " c"]
    num_points: Int[Tensor, " c"]
    fallback: Bool[Tensor, " c"]

    def stacked(self) -> Float[Tensor, "c 2"]:
        """[t_near, t_far] per camera, the layout ``compute_preconditioner`` takes."""
        return torch.stack([self.t_near, self.t_far], dim=-1)


def validate_overrides(t_near: float | None, t_far: float | None, config: ProxyRangeConfig) -> None:
    """Explicit ends: both, 0 <= t_near < t_far < 2; one, leaving ``min_width`` inside [T_NEAR_MIN, T_FAR_MAX]."""
    if t_near is not None and t_far is not None:
        check_range("t_near", t_near, low=0.0)
        check_range("t_far", t_far, low=t_near, high=2.0, low_inclusive=False, high_inclusive=False)
    elif t_near is not None:
        check_range("t_near", t_near, low=0.0, high=T_FAR_MAX - config.min_width)
    elif t_far is not None:
        check_range("t_far", t_far, low=T_NEAR_MIN + config.min_width, high=2.0, high_inclusive=False)


def clamp_range(
    t_near: Float[Tensor, " c"],
    t_far: Float[Tensor, " c"],
    config: ProxyRangeConfig,
    near_override: float | None = None,
    far_override: float | None = None,
) -> tuple[Float[Tensor, " c"], Float[Tensor, " c"]]:
    """Chosen ranges clamped into [T_NEAR_MIN, T_FAR_MAX] with width >= ``min_width``; explicit ends kept as given."""
    t_near, t_far = t_near.to(torch.float64), t_far.to(torch.float64)
    if near_override is not None and far_override is not None:
        return torch.full_like(t_near, near_override), torch.full_like(t_far, far_override)
    if near_override is not None:
        near = torch.full_like(t_near, near_override)
        return near, t_far.clamp(max=T_FAR_MAX).clamp(min=near_override + config.min_width)
    if far_override is not None:
        far = torch.full_like(t_far, far_override)
        return t_near.clamp(min=T_NEAR_MIN).clamp(max=far_override - config.min_width), far
    near, far = t_near.clamp(T_NEAR_MIN, T_FAR_MAX), t_far.clamp(T_NEAR_MIN, T_FAR_MAX)
    grow = (config.min_width - (far - near)).clamp(min=0.0) / 2.0
    near, far = near - grow, far + grow
    # min_width <= T_FAR_MAX - T_NEAR_MIN (validated): at most one of the two shifts is nonzero.
    shift = (T_NEAR_MIN - near).clamp(min=0.0) - (far - T_FAR_MAX).clamp(min=0.0)
    near, far = near + shift, far + shift
    return near, far


def fixed_range(
    config: ProxyRangeConfig | None = None, t_near: float | None = None, t_far: float | None = None
) -> tuple[float, float]:
    """The range without scene points: the defaults, with explicit ends kept and the other clamped to them."""
    config = config or ProxyRangeConfig()
    near, far = clamp_range(
        torch.tensor([DEFAULT_T_NEAR], dtype=torch.float64),
        torch.tensor([DEFAULT_T_FAR], dtype=torch.float64),
        config,
        t_near,
        t_far,
    )
    return float(near[0]), float(far[0])


def interpolated_quantile(values: Float[Tensor, " m"], q: float) -> Tensor:
    """Quantile ``q`` of non-empty ``values``, linear between order statistics (numpy's default), any size."""
    ordered = torch.sort(values.to(torch.float64)).values
    position = q * (ordered.shape[0] - 1)
    low = int(position)
    high = min(low + 1, ordered.shape[0] - 1)
    fraction = position - low
    return ordered[low] + fraction * (ordered[high] - ordered[low])


def fit_radial_law(
    low: Tensor, high: Tensor, low_level: float, high_level: float, radial: str = "volume"
) -> tuple[Tensor, Tensor]:
    """(t0, t1) whose radial CDF (paper eq. 11; "volume" or "ray", module docstring) is ``low_level``,
    ``high_level`` at the contracted radii ``low`` <= ``high``; a negative t0 is returned as 0."""
    if radial not in ("volume", "ray"):
        raise ValueError(f"radial must be one of 'volume', 'ray', got {radial!r}")
    power = 3.0 if radial == "volume" else 1.0
    low_p, high_p = low.to(torch.float64) ** power, high.to(torch.float64) ** power
    spread = (high_p - low_p) / (high_level - low_level)
    t0_p = (low_p - low_level * spread).clamp(min=0.0)
    t1_p = low_p + (1.0 - low_level) * spread
    return t0_p ** (1.0 / power), t1_p ** (1.0 / power)


def inverse_distance_moments(distances: Float[Tensor, " m"], clip_quantile: float) -> tuple[float, float]:
    """E[1/d] and E[1/d^2] of distances clipped to their ``clip_quantile`` and 1 - ``clip_quantile`` quantiles."""
    low = interpolated_quantile(distances, clip_quantile)
    high = interpolated_quantile(distances, 1.0 - clip_quantile)
    inverse = 1.0 / distances.to(torch.float64).clamp(min=float(low), max=float(high))
    return float(inverse.mean()), float((inverse * inverse).mean())


@lru_cache(maxsize=8)
def _moment_grid(radial: str, min_width: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Every (t0, t1) of the grid with t1 - t0 >= min_width, and the proxy's E[1/d], E[1/d^2] there (radius Q_r(u)
    of paper eq. 12 at midpoint nodes u, d by the inverse of eq. 10)."""
    per_unit = round(1.0 / GRID_STEP)  # grid values k / 100: correctly rounded, 0.3 is the double nearest 0.3
    indices = torch.arange(round(T_NEAR_MIN * per_unit), round(T_FAR_MAX * per_unit) + 1, dtype=torch.float64)
    values = indices / per_unit
    t0, t1 = torch.meshgrid(values, values, indexing="ij")
    keep = t1 - t0 >= min_width - 1e-9
    t0, t1 = t0[keep], t1[keep]
    nodes = (torch.arange(_MOMENT_NODES, dtype=torch.float64) + 0.5) / _MOMENT_NODES
    radius = radius_from_unit(nodes, t0[:, None], t1[:, None], radial)
    inverse = 1.0 / uncontract_radius(radius.clamp(max=T_FAR_MAX))
    return t0, t1, inverse.mean(dim=-1), (inverse * inverse).mean(dim=-1)


def match_inverse_moments(
    first: float, second: float, radial: str = "volume", min_width: float = 0.2
) -> tuple[float, float]:
    """The grid range (t0, t1) whose proxy E[1/d], E[1/d^2] minimise (log M1/first)^2 + (log M2/second)^2 (module
    docstring, "moments"); ties go to the smallest t0, then t1."""
    if radial not in ("volume", "ray"):
        raise ValueError(f"radial must be one of 'volume', 'ray', got {radial!r}")
    check_range("first", first, low=0.0, low_inclusive=False)
    check_range("second", second, low=0.0, low_inclusive=False)
    t0, t1, m1, m2 = _moment_grid(radial, float(min_width))
    cost = torch.log(m1 / first) ** 2 + torch.log(m2 / second) ** 2
    best = int(torch.argmin(cost))
    return float(t0[best]), float(t1[best])


def _spread(items: list[int], count: int) -> list[int]:
    """At most ``count`` of ``items``, evenly spread and in order (all of them when there are few enough)."""
    if len(items) <= count:
        return items
    return [items[(k * len(items)) // count] for k in range(count)]


def visible_distances(
    points: Float[Tensor, "m 3"], c2w: Float[Tensor, "n 3 4"], intrinsics: Intrinsics
) -> list[Float[Tensor, " v"]]:
    """Per image, the Euclidean distances from its camera centre of the points it sees (in front of it and inside it,
    distortion included). ``c2w``: OpenCV camera-to-world. Projected in chunks of ``_PAIRS_PER_CHUNK`` pairs."""
    points = points.detach().to(torch.float64)
    c2w = c2w.detach().to(device=points.device, dtype=torch.float64)
    intrinsics = intrinsics.detach().to(device=points.device, dtype=torch.float64)
    n, m = c2w.shape[0], points.shape[0]
    out: list[Tensor] = []
    step = max(1, _PAIRS_PER_CHUNK // max(m, 1))
    for start in range(0, n, step):
        stop = min(start + step, n)
        rotation, centre = c2w[start:stop, :, :3], c2w[start:stop, :, 3]
        offsets = points[None] - centre[:, None, :]
        camera = offsets @ rotation  # x_cam = R^T (x - c), in row-vector form
        pixels, margin = project(camera, intrinsics[start:stop])
        visible = in_image(pixels, margin, intrinsics[start:stop])
        distances = torch.linalg.vector_norm(offsets, dim=-1)
        out.extend(distances[i][visible[i]] for i in range(stop - start))
    return out


def proxy_ranges(
    points: Float[Tensor, "m 3"] | None,
    c2w: Float[Tensor, "n 3 4"],
    intrinsics: Intrinsics,
    camera_of_image: Int[Tensor, " n"],
    config: ProxyRangeConfig | None = None,
    t_near: float | None = None,
    t_far: float | None = None,
    radial: str = "volume",
) -> ProxyRanges:
    """Contracted proxy range per physical camera from the points it sees (module docstring), float64 on ``c2w``'s
    device. ``points``: world points (None or empty: every camera falls back); ``c2w``: OpenCV camera-to-world per
    image; ``camera_of_image``: camera 0..C-1 of each image; ``t_near``, ``t_far``: explicit ends; ``radial``: the
    proxy radial map ("volume" or "ray", ``SamplingConfig.radial``)."""
    config = config or ProxyRangeConfig()
    config.validate()
    validate_overrides(t_near, t_far, config)
    n = c2w.shape[0]
    if c2w.ndim != 3 or c2w.shape[1:] != (3, 4):
        raise ValueError(f"c2w must have shape [N, 3, 4], got {tuple(c2w.shape)}")
    if intrinsics.num_cameras != n:
        raise ValueError(f"intrinsics must hold N = {n} cameras like c2w, got {intrinsics.num_cameras}")
    groups = torch.as_tensor(camera_of_image).reshape(-1).to(torch.long).cpu()
    if groups.shape[0] != n or (n and int(groups.min()) < 0):
        raise ValueError(f"camera_of_image must hold {n} ids >= 0 (one per image), got shape {tuple(groups.shape)}")
    c = int(groups.max()) + 1 if n else 0
    check_finite("c2w", c2w.detach())
    near = torch.full((c,), DEFAULT_T_NEAR, dtype=torch.float64)
    far = torch.full((c,), DEFAULT_T_FAR, dtype=torch.float64)
    counts = torch.zeros(c, dtype=torch.long)
    if points is not None and points.numel() > 0:
        if points.ndim != 2 or points.shape[-1] != 3:
            raise ValueError(f"points must have shape [M, 3], got {tuple(points.shape)}")
        check_finite("points", points.detach())
        points = points.detach().cpu()
        points = points[:: -(-points.shape[0] // config.max_points)]  # every k-th point, k = ceil(M / max_points)
        images_of = [_spread(torch.nonzero(groups == camera)[:, 0].tolist(), config.max_images) for camera in range(c)]
        used = torch.tensor(sorted({i for images in images_of for i in images}), dtype=torch.long)
        seen = visible_distances(points, c2w.cpu()[used], intrinsics.to(device="cpu")[used])
        per_image = dict(zip(used.tolist(), seen, strict=True))
        for camera in range(c):
            images = images_of[camera]
            pooled = torch.cat([per_image[i] for i in images]) if images else torch.zeros(0, dtype=torch.float64)
            counts[camera] = pooled.shape[0]
            if pooled.shape[0] < config.min_points:
                continue
            if config.rule == "moments":
                moments = inverse_distance_moments(pooled, config.clip_quantile)
                low, high = match_inverse_moments(*moments, radial, config.min_width)
            else:
                levels = (config.low_quantile, config.high_quantile)
                low, high = contract_radius(torch.stack([interpolated_quantile(pooled, q) for q in levels]))
                if config.rule == "fit":
                    low, high = fit_radial_law(low, high, *levels, radial)
            near[camera] = low - config.margin
            far[camera] = high + config.margin
    fallback = counts < config.min_points
    near, far = clamp_range(near, far, config, t_near, t_far)
    device = c2w.device
    return ProxyRanges(
        t_near=near.to(device), t_far=far.to(device), num_points=counts.to(device), fallback=fallback.to(device)
    )


def describe_proxy_ranges(
    ranges: ProxyRanges | None, num_points: int, fixed: tuple[float, float], min_points: int
) -> str:
    """The start-up note on the ranges chosen from ``num_points`` points (``fixed``: the fallback range)."""
    if ranges is None or num_points == 0:
        return (
            "S2CamP proxy range: the scene has no points (dataparser metadata 'points3D_xyz'), so every camera "
            f"uses the fixed contracted range ({fixed[0]:g}, {fixed[1]:g})"
        )
    chosen = f"t_near {span(ranges.t_near)}, t_far {span(ranges.t_far)} (contracted)"
    message = f"S2CamP proxy range from {num_points} scene points, {ranges.t_near.shape[0]} physical cameras: {chosen}"
    fell_back = int(ranges.fallback.sum())
    if fell_back:
        message += (
            f"; {fell_back} camera(s) see fewer than {min_points} points and use the fixed range "
            f"({fixed[0]:g}, {fixed[1]:g})"
        )
    return message


def span(values: Tensor) -> str:
    """ "low..high" of ``values`` to three decimals, one number when they agree."""
    low, high = float(values.min()), float(values.max())
    return f"{low:.3f}" if low == high else f"{low:.3f}..{high:.3f}"
