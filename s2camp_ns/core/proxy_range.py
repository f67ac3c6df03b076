"""Each physical camera's radial proxy range [t_near, t_far] from the scene's own points (paper eqs. 10-12).

The proxy points of the preconditioner fill a camera's contracted view frustum between two contracted radii
(paper sec. 4, eq. 12); the contraction is about the camera centre, t = d for d <= 1 and t = 2 - 1/d beyond
(paper eq. 10), d the Euclidean distance in the scene's (normalized) units. The Gram matrix (eq. 5) is an average
over the proxy points, so the range sets how much weight each depth gets: a far end beyond the content puts most of
it where rotation and translation look alike, a near end in front of the content lets the 1/d^2 translation terms
of points the camera never sees dominate. A fixed range fits one kind of scene only.

Here the range follows the content. For every image, the sparse points (an SfM reconstruction's, or any other
sample of the surfaces) that lie in front of the camera and project inside its image give distances d; the
images of one physical camera are pooled (its intrinsics, and so its proxy frustum, are shared). The range is
chosen from these distances by one of three rules (``rule``):

``"moments"`` (default)
    The proxy points reproduce the content's inverse-distance moments E[1/d] and E[1/d^2]. They are what the depth
    does to Sigma (eqs. 4-5): the translation columns of the Jacobian scale with 1/z, so the translation block of
    Sigma averages 1/z^2 and its coupling to rotation and intrinsics averages 1/z, while every other block depends
    on the direction only. The proxy moments of a range (t0, t1) follow from the radial law alone (eq. 12: radius
    Q_r(u1), u1 uniform; Euclidean d by the inverse of eq. 10), computed by the midpoint rule on ``_MOMENT_NODES``
    nodes; (t0, t1) is the point of a 0.01 grid in [``T_NEAR_MIN``, ``T_FAR_MAX``] (width >= ``min_width``) that
    minimises (log M1/m1)^2 + (log M2/m2)^2, M the proxy's moments and m the content's. The distances are first
    clipped to their ``clip_quantile`` and 1 - ``clip_quantile`` quantiles, so that a few stray points at the lens
    (a mismatched track) cannot dominate E[1/d^2]; points far away (the sky, a background) add almost nothing, as
    they add almost nothing to the translation columns of the real content.
``"fit"``
    The proxy radial law is matched to the content's at two quantiles c_a, c_b of the contracted distances (levels
    a < b: ``low_quantile``, ``high_quantile``; linear interpolation between order statistics): its CDF F(t) (paper
    eq. 11) is (t^3 - t0^3) / (t1^3 - t0^3) for the "volume" radial map (eq. 12) and (t - t0) / (t1 - t0) for "ray",
    and F(c_a) = a, F(c_b) = b is linear in (t0^3, t1^3), resp. (t0, t1).
``"span"``
    [t0, t1] = [c_a, c_b]: the range covers the content between the two quantiles (e.g. 5% / 95%). The volume law then
    crowds the points at the far end, and a background seen by more than 5% of the points sets t1 near 2.

On the generated scenes of docs/benchmarks/proxy-range.md the moment rule is within a few percent of the fixed range
or better in Gram error against the visible content, and "span" 5% / 95% is worse on every scene; the measured
numbers are there. Occlusion is not tested (sparse points carry no surface): points hidden behind nearer content
count, which biases the content towards larger distances.

Then ``margin`` contracted units are added on each side and the range is clamped:

- t_near >= ``T_NEAR_MIN`` (a negative t0^3 of "fit" included): below it the 1/d^2 growth of the translation
  columns lets the nearest proxy points dominate Sigma;
- t_far <= ``T_FAR_MAX`` = 1.99 (the paper's far radius, d = 100): t = 2 is the point at infinity;
- t_far - t_near >= ``min_width``: content at one depth (a wall facing the camera) would otherwise give a thin
  shell, on which translation across the view and rotation about the perpendicular axis are indistinguishable;
  the width is grown about the middle of the range, then the range is shifted back inside the bounds.

Fallback: a camera with fewer than ``min_points`` visible points (none at all when the scene has no points) gets the
fixed defaults ``DEFAULT_T_NEAR`` = 0.4 and ``DEFAULT_T_FAR`` = 1.5 (tuned on the recovery benchmark's scenes,
docs/benchmarks/recovery.md); the result marks those cameras (``ProxyRanges.fallback``) and the caller says so in
its log. An explicit ``t_near`` or ``t_far`` overrides that end for every camera; the other end is still chosen
(clamped to keep ``min_width``).

Large scenes are thinned before projecting: at most ``max_points`` points (every k-th) and ``max_images`` images per
physical camera (evenly spread). Everything is float64 and deterministic (strided thinning, sorting, a grid search;
no random numbers).
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
"""Fixed near contracted radius: the fallback without points, and the range before it was chosen per scene."""
DEFAULT_T_FAR = 1.5
"""Fixed far contracted radius (Euclidean 2 scene units, paper eq. 10): the fallback without points."""
T_NEAR_MIN = 0.1
"""Smallest chosen near radius (contracted = Euclidean below 1)."""
T_FAR_MAX = 1.99
"""Largest chosen far radius: the paper's 1.99, Euclidean distance 100 (paper eq. 10)."""
RULES: tuple[str, ...] = ("moments", "fit", "span")
GRID_STEP = 0.01
"""Resolution of the "moments" rule's search over (t0, t1), contracted units."""
_MOMENT_NODES = 512
"""Midpoint-rule nodes of the proxy radial law's moments."""
_PAIRS_PER_CHUNK = 1 << 20
"""Image-point pairs projected at a time by ``visible_distances`` (about 0.2 GB of float64 intermediates)."""


@dataclass(frozen=True)
class ProxyRangeConfig:
    """How the proxy range is chosen from the scene's points (module docstring)."""

    rule: Literal["moments", "fit", "span"] = "moments"
    """"moments": the proxy's E[1/d], E[1/d^2] matched to the visible points'; "fit": the proxy radial law matched
    to their distances at two quantiles; "span": the range is the two quantiles (module docstring)."""
    clip_quantile: float = 0.02
    """"moments": the distances are clipped to this quantile and 1 - it before the moments are taken."""
    low_quantile: float = 0.25
    """"fit" and "span": lower quantile level a of the visible points' distances."""
    high_quantile: float = 0.75
    """"fit" and "span": upper quantile level b (above a)."""
    margin: float = 0.0
    """Contracted units added below t_near and above t_far before clamping."""
    min_width: float = 0.2
    """Smallest t_far - t_near, contracted units."""
    min_points: int = 20
    """Fewest visible points (pooled over a physical camera's images) for a chosen range; fewer: the defaults."""
    max_points: int = 50_000
    """Scene points used at most: a larger scene keeps every k-th point (k = ceil(M / max_points)), so the start-up
    cost stays near images x max_points projections."""
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
    """Explicit ends: both given, 0 <= t_near < t_far < 2 (as a fixed range always was); one given, room is left
    for the chosen other end (``min_width`` inside [``T_NEAR_MIN``, ``T_FAR_MAX``])."""
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
    """Clamp chosen contracted ranges into [T_NEAR_MIN, T_FAR_MAX] with width >= ``min_width``; explicit ends are
    kept exactly as given and only the chosen end moves (module docstring)."""
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
    """Quantile ``q`` of ``values`` with linear interpolation between order statistics (numpy's default and
    ``torch.quantile``'s "linear"), without ``torch.quantile``'s input size limit. ``values`` non-empty."""
    ordered = torch.sort(values.to(torch.float64)).values
    position = q * (ordered.shape[0] - 1)
    low = int(position)
    high = min(low + 1, ordered.shape[0] - 1)
    fraction = position - low
    return ordered[low] + fraction * (ordered[high] - ordered[low])


def fit_radial_law(
    low: Tensor, high: Tensor, low_level: float, high_level: float, radial: str = "volume"
) -> tuple[Tensor, Tensor]:
    """(t0, t1) whose radial CDF (paper eq. 11: "volume" (t^3 - t0^3) / (t1^3 - t0^3), the law of eq. 12; "ray"
    (t - t0) / (t1 - t0)) takes the values ``low_level``, ``high_level`` at the contracted radii ``low`` <= ``high``.

    Linear in (t0^3, t1^3) resp. (t0, t1). t0 may come out below zero (content spread towards the camera); it is
    returned as 0 then and clamped later (``clamp_range``).
    """
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
    """Every (t0, t1) of the search grid with t1 - t0 >= min_width, and the proxy's E[1/d], E[1/d^2] there.

    Radius Q_r(u) of the radial law (paper eq. 12) at midpoint nodes u, Euclidean d by the inverse contraction (eq. 10).
    """
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
    """The grid range (t0, t1) whose proxy radial law (paper eqs. 10, 12) has E[1/d], E[1/d^2] closest to ``first``,
    ``second`` in the sense of (log M1/first)^2 + (log M2/second)^2 (module docstring, "moments"). Deterministic:
    ties go to the first grid point (smallest t0, then t1)."""
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
    """Per image, the Euclidean distances from its camera centre of the points it sees: in front of the camera and
    inside its image (``project`` and ``in_image``, distortion included). ``c2w``: OpenCV camera-to-world.

    Images are projected in chunks of about ``_PAIRS_PER_CHUNK`` image-point pairs; only the visible distances are
    kept, so memory grows with what the cameras see, not with images x points.
    """
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
    """Contracted proxy range per physical camera from the points it sees (module docstring; paper eqs. 10-12).

    ``points``: world points in the cameras' units (None or empty: every camera falls back); ``c2w``: OpenCV
    camera-to-world per image; ``camera_of_image``: physical camera 0..C-1 of each image (C = max + 1); ``t_near``,
    ``t_far``: explicit ends that override the chosen ones; ``radial``: the proxy radial map the rules match
    ("volume" or "ray", ``SamplingConfig.radial``). Returns float64 ranges on the cameras' device.
    """
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
    """The start-up note on the proxy ranges chosen from ``num_points`` scene points (``fixed``: the range without
    them; ``min_points``: the fewest points a camera's choice needs)."""
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
