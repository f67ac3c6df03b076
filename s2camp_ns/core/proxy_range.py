"""Each physical camera's radial proxy range [t_near, t_far] from the scene's own points (paper eqs. 10-12).

The proxy points of the preconditioner fill a camera's contracted view frustum between two contracted radii
(paper sec. 4, eq. 12); the contraction is about the camera centre, t = d for d <= 1 and t = 2 - 1/d beyond
(paper eq. 10), d the Euclidean distance in the scene's (normalized) units. A fixed range fits one kind of scene
only: the Gram matrix (eq. 5) weights each depth by its volume, so a far end beyond the content puts most of the
weight where rotation and translation look alike, and one short of it misses content the camera does see.

Here the range follows the content. For every image, the sparse points (an SfM reconstruction's, or any other
sample of the surfaces) that lie in front of the camera and project inside its image give distances d; the
images of one physical camera are pooled (its intrinsics, and so its proxy frustum, are shared). Of these
distances the ``near_quantile`` and ``far_quantile`` quantiles (linear interpolation between order statistics)
are contracted (eq. 10), widened by ``margin`` contracted units on each side and clamped:

- t_near >= ``T_NEAR_MIN``: below it the 1/d^2 growth of the translation columns lets a few stray points near the
  camera dominate Sigma;
- t_far <= ``T_FAR_MAX`` = 1.99 (the paper's far radius, d = 100): t = 2 is the point at infinity;
- t_far - t_near >= ``min_width``: content at one depth (a wall facing the camera) would otherwise give a thin
  shell, on which translation across the view and rotation about the perpendicular axis are indistinguishable;
  the width is grown about the middle of the range, then the range is shifted back inside the bounds.

Why quantiles, and why 5% / 95%: the extreme points of a reconstruction are its outliers (a mismatched track
triangulated behind the scene or in front of the lens) and single points must not move the range; a 5% / 95%
quantile ignores up to 5% of the visible points on either side, and covers 90% of what the camera sees.

Occlusion is not tested (sparse points carry no surface): a point hidden behind nearer content still counts.

Fallback: a camera with fewer than ``min_points`` visible points (none at all when the scene has no points) gets the
fixed defaults ``DEFAULT_T_NEAR`` = 0.4 and ``DEFAULT_T_FAR`` = 1.5 (tuned on the recovery benchmark's scenes,
docs/benchmarks/recovery.md); the result marks those cameras (``ProxyRanges.fallback``) and the caller says so in
its log. An explicit ``t_near`` or ``t_far`` overrides that end for every camera; the other end is still chosen
(clamped to keep ``min_width``).

Everything is float64 and deterministic (sorting, no sampling).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, in_image, project
from s2camp_ns.core.contraction import contract_radius
from s2camp_ns.core.validation import check_finite, check_positive_int, check_range

__all__ = [
    "DEFAULT_T_FAR",
    "DEFAULT_T_NEAR",
    "T_FAR_MAX",
    "T_NEAR_MIN",
    "ProxyRangeConfig",
    "ProxyRanges",
    "clamp_range",
    "fixed_range",
    "interpolated_quantile",
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
_PAIRS_PER_CHUNK = 1 << 20
"""Image-point pairs projected at a time by ``visible_distances`` (about 0.2 GB of float64 intermediates)."""


@dataclass(frozen=True)
class ProxyRangeConfig:
    """How the proxy range is chosen from the scene's points (module docstring)."""

    near_quantile: float = 0.05
    """Quantile of the visible points' distances that sets t_near."""
    far_quantile: float = 0.95
    """Quantile that sets t_far (above ``near_quantile``)."""
    margin: float = 0.0
    """Contracted units added below t_near and above t_far before clamping."""
    min_width: float = 0.2
    """Smallest t_far - t_near, contracted units."""
    min_points: int = 20
    """Fewest visible points (pooled over a physical camera's images) for a chosen range; fewer: the defaults."""

    def validate(self) -> None:
        check_range("near_quantile", self.near_quantile, low=0.0, high=1.0)
        check_range("far_quantile", self.far_quantile, low=self.near_quantile, high=1.0)
        check_range("margin", self.margin, low=0.0, high=1.0)
        check_range("min_width", self.min_width, low=0.0, high=T_FAR_MAX - T_NEAR_MIN)
        check_positive_int("min_points", self.min_points)


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
) -> ProxyRanges:
    """Contracted proxy range per physical camera from the points it sees (module docstring; paper eqs. 10, 12).

    ``points``: world points in the cameras' units (None or empty: every camera falls back); ``c2w``: OpenCV
    camera-to-world per image; ``camera_of_image``: physical camera 0..C-1 of each image (C = max + 1); ``t_near``,
    ``t_far``: explicit ends that override the chosen ones. Returns float64 ranges on the cameras' device.
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
        per_image = visible_distances(points.cpu(), c2w.cpu(), intrinsics.to(device="cpu"))
        for camera in range(c):
            images = torch.nonzero(groups == camera)[:, 0].tolist()
            pooled = torch.cat([per_image[i] for i in images]) if images else torch.zeros(0, dtype=torch.float64)
            counts[camera] = pooled.shape[0]
            if pooled.shape[0] < config.min_points:
                continue
            levels = (config.near_quantile, config.far_quantile)
            quantiles = torch.stack([interpolated_quantile(pooled, q) for q in levels])
            contracted = contract_radius(quantiles)
            near[camera] = contracted[0] - config.margin
            far[camera] = contracted[1] + config.margin
    fallback = counts < config.min_points
    near, far = clamp_range(near, far, config, t_near, t_far)
    device = c2w.device
    return ProxyRanges(t_near=near.to(device), t_far=far.to(device), num_points=counts.to(device), fallback=fallback)
