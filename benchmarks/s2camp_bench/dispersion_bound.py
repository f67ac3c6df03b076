"""Dispersion of a point set in the contracted view frustum (paper Sec. 5, Table 1).

Protocol. The dispersion of points ``P`` in a frustum ``F`` is the radius of the largest empty open ball whose
centre lies in ``F`` (the ball itself may stick out of ``F``): ``d(P) = max_{x in F} min_{p in P} |x - p|``.
The paper does not state how it evaluated this; we compute it by branch and bound over a grid of cells in
frustum parameters ``(rho, v, w) in [0, 1]^3`` with radius ``r = t_near + rho (t_far - t_near)`` (linear in
``r`` so cells near the apex stay small) and the angular CDF coordinates ``(v, w)`` of the frustum transform
(see :mod:`s2camp_ns.core.frustum`), so the cells tile exactly the frustum of that transform.

For a cell with mapped vertices ``c_k``, every point ``x`` of the cell is within ``h`` of some vertex, where ``h`` is
half the longest body diagonal of the mapped cell (exact for a parallelepiped; the mapped cells are curved, with a
deviation that is second order in the cell size). Since ``min_p |x - p|`` is 1-Lipschitz, ``f(x) <= max_k f(c_k) + h``.
Cells whose upper bound is below the best value found so far are discarded, the rest are split in two across their
longest mapped edge, until the gap between the best value (a lower bound, attained at a probe inside ``F``) and the
largest remaining upper bound is below the requested tolerance. The result reports both: ``lower <= d(P) <= upper`` (to
first order in the final cell size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.frustum import TRANSFORMS, directions_from_unit, validate_frustum
from s2camp_ns.core.validation import check_choice, check_finite, check_positive_int, check_range

__all__ = ["DispersionResult", "dispersion", "nearest_distance", "reference_tangent_bounds"]


@dataclass(frozen=True)
class DispersionResult:
    """Per-camera dispersion estimate ``value`` (a lower bound) with ``upper`` bound and the ball centre."""

    value: Float[Tensor, " n"]
    upper: Float[Tensor, " n"]
    centre: Float[Tensor, "n 3"]

    @property
    def error_bound(self) -> Float[Tensor, " n"]:
        """``upper - value``: the true dispersion lies in ``[value, value + error_bound]``."""
        return self.upper - self.value


def reference_tangent_bounds(name: str) -> Float[Tensor, "1 4"]:
    """Tangent box of a reference camera: ``"room"`` (mip-NeRF 360 room at 1/4 resolution: 778 x 518 pixels,
    fx 793.13, fy 793.49, cx 389.25, cy 259.375) or ``"wide"`` (90 degree horizontal field of view, 3:2)."""
    check_choice("name", name, ("room", "wide"))
    if name == "room":
        width, height, fx, fy, cx, cy = 778.0, 518.0, 793.13, 793.49, 389.25, 259.375
        box = [-cx / fx, (width - cx) / fx, -cy / fy, (height - cy) / fy]
    else:
        box = [-1.0, 1.0, -2.0 / 3.0, 2.0 / 3.0]
    return torch.tensor([box], dtype=torch.float64)


def nearest_distance(queries: Float[Tensor, "m 3"], points: Float[Tensor, "l 3"]) -> Float[Tensor, " m"]:
    """Euclidean distance from each query to its nearest point (a k-d tree: exact distances, on the CPU)."""
    from scipy.spatial import cKDTree

    distances, _ = cKDTree(points.detach().cpu().numpy()).query(queries.detach().cpu().numpy(), k=1)
    return torch.from_numpy(distances).to(dtype=points.dtype, device=points.device)


def _map_params(params: Tensor, bounds: Tensor, t_near: float, t_far: float, transform: str) -> Tensor:
    radius = t_near + params[..., 0] * (t_far - t_near)
    direction = directions_from_unit(params[None, :, 1], params[None, :, 2], bounds, transform)[0]
    return radius.unsqueeze(-1) * direction


_MAX_CELLS = 1 << 19

_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.float64)


def _dispersion_one(
    points: Tensor, bounds: Tensor, t_near: float, t_far: float, transform: str, tol: float, max_levels: int
) -> tuple[float, float, Tensor]:
    device = points.device
    corners = _CORNERS.to(device)
    a0, a1, b0, b1 = bounds[0].tolist()
    # Initial cells about half the mean point spacing along each mapped direction (the volume from the angular
    # spans, close to the frustum's for the fields of view measured here; it only sets where the search starts).
    sizes = (t_far - t_near, t_far * (math.atan(b1) - math.atan(b0)), t_far * (math.atan(a1) - math.atan(a0)))
    volume = (t_far**3 - t_near**3) / 3.0 * (math.atan(a1) - math.atan(a0)) * (math.atan(b1) - math.atan(b0))
    spacing = 0.5 * (volume / points.shape[0]) ** (1.0 / 3.0)
    counts = [max(2, min(256, math.ceil(size / spacing))) for size in sizes]
    axes = [torch.arange(c + 1, device=device, dtype=torch.float64) / c for c in counts]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
    mapped = _map_params(grid.reshape(-1, 3), bounds, t_near, t_far, transform)
    values = nearest_distance(mapped, points).reshape(grid.shape[:3])
    mapped = mapped.reshape(grid.shape)
    best = float(values.max())
    best_index = int(values.argmax())
    centre = mapped.reshape(-1, 3)[best_index]

    # Cell lower corners and per-cell vertex maxima / diagonals from the shared grid.
    def cell_view(t: Tensor) -> list[Tensor]:
        return [t[i : i + counts[0], j : j + counts[1], k : k + counts[2]] for i, j, k in corners.long().tolist()]

    vertex_values = torch.stack(cell_view(values), dim=-1)
    vertex_points = torch.stack(cell_view(mapped), dim=-2)
    low = grid[: counts[0], : counts[1], : counts[2]].reshape(-1, 3)
    step = torch.tensor([1.0 / c for c in counts], dtype=torch.float64, device=device).expand(low.shape[0], 3)
    upper = vertex_values.reshape(-1, 8).amax(-1) + _half_diagonal(vertex_points.reshape(-1, 8, 3))

    for _ in range(max_levels):
        keep = upper > best + tol
        # A flat maximum (e.g. a whole spherical cap at the same distance) would keep every cell on it alive;
        # stop at the cell budget and report the honest, larger upper bound instead of exhausting memory.
        if not bool(keep.any()) or 2 * int(keep.sum()) > _MAX_CELLS:
            break
        low, step, vpts = low[keep], step[keep], vertex_points.reshape(-1, 8, 3)[keep]
        # Split each surviving cell in two across its longest mapped edge: cells at the apex are long in radius
        # and tiny in angle, and an isotropic split would multiply them without shrinking their bound.
        edges = torch.stack([_edge_length(vpts, axis) for axis in range(3)], dim=-1)
        axis = edges.argmax(dim=-1, keepdim=True)
        half = torch.zeros_like(step).scatter(-1, axis, step.gather(-1, axis) / 2.0)
        step = (step - half).repeat(2, 1)
        low = torch.cat([low, low + half])
        verts = low[:, None, :] + corners[None, :, :] * step[:, None, :]
        vpts = _map_params(verts.reshape(-1, 3), bounds, t_near, t_far, transform)
        vvals = nearest_distance(vpts, points).reshape(-1, 8)
        level_best = float(vvals.max())
        if level_best > best:
            best = level_best
            centre = vpts[int(vvals.argmax())]
        vertex_points = vpts.reshape(-1, 8, 3)
        upper = vvals.amax(-1) + _half_diagonal(vertex_points)
    final_upper = max(best, float(upper.max()))
    return best, final_upper, centre


def _edge_length(vertices: Tensor, axis: int) -> Tensor:
    """Longest mapped edge of each cell along parameter ``axis`` (vertices in ``_CORNERS`` order)."""
    bit = 4 >> axis
    lower = [k for k in range(8) if not k & bit]
    return torch.linalg.vector_norm(vertices[:, lower, :] - vertices[:, [k | bit for k in lower], :], dim=-1).amax(-1)


def _half_diagonal(vertices: Tensor) -> Tensor:
    """Half the longest of the four body diagonals of hexahedra given by 8 vertices in ``_CORNERS`` order."""
    diagonals = vertices[:, :4, :] - vertices[:, [7, 6, 5, 4], :]
    return 0.5 * torch.linalg.vector_norm(diagonals, dim=-1).amax(-1)


def dispersion(
    points_contracted: Float[Tensor, "n l 3"] | Float[Tensor, "l 3"], tangent_bounds: Float[Tensor, "n 4"],
    t_near: float, t_far: float, transform: str = "pyramid", tol: float = 1e-3, max_levels: int = 200,
) -> DispersionResult:
    """Largest empty ball with centre in the contracted frustum of ``transform`` (paper Table 1).

    Branch and bound (module docstring) until the gap between the attained value and the upper bound is below
    ``tol`` or ``max_levels`` refinements were made. Deterministic: no random probes.
    """
    check_choice("transform", transform, TRANSFORMS)
    bounds = validate_frustum(tangent_bounds, t_near, t_far, transform)
    check_range("tol", tol, low=0.0, low_inclusive=False)
    check_positive_int("max_levels", max_levels)
    points = points_contracted.detach().to(device=bounds.device, dtype=torch.float64)
    if points.ndim == 2:
        points = points.expand(bounds.shape[0], -1, -1)
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[0] != bounds.shape[0] or points.shape[1] < 1:
        raise ValueError(f"points_contracted must have shape [N, L, 3] with L >= 1, got {tuple(points.shape)}")
    check_finite("points_contracted", points)
    values, uppers, centres = [], [], []
    for i in range(bounds.shape[0]):
        value, upper, centre = _dispersion_one(
            points[i], bounds[i : i + 1], float(t_near), float(t_far), transform, tol, max_levels
        )
        values.append(value)
        uppers.append(upper)
        centres.append(centre)
    as_tensor = lambda xs: torch.tensor(xs, dtype=torch.float64, device=bounds.device)  # noqa: E731
    return DispersionResult(value=as_tensor(values), upper=as_tensor(uppers), centre=torch.stack(centres))
