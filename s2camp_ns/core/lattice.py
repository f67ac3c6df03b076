"""Point sets in the unit cube ``[0, 1]^3`` (float64, exactly ``L`` points) for frustum sampling (paper Sec. 3).

Frolov lattice (``frolov_lattice``)
    The Minkowski embedding of the ring of integers of a totally real cubic field: generator ``V[i, j] = theta_i^j``
    for the roots ``theta_i`` of a monic irreducible integer polynomial; every nonzero ``x = V k`` has
    ``|x1 x2 x3| >= 1`` with ``det V = sqrt(discriminant)``. The bound survives every diagonal scaling of
    determinant one, which the frustum transforms apply locally, so the points stay separated in the frustum
    (Frisch et al.). Fields: ``x^3 + x^2 - 2x - 1`` (discriminant 49, the default) and ``x^3 - 3x + 1`` (81). Free
    parameters: a unit-group scaling ``D = exp(t1 log|theta| + t2 log|theta'|)``, ``(t1, t2)`` in ``[0, 1)^2``, a
    shift ``c`` in ``[0, 1)^3``, coordinate sign flips and a transposition.

Exact ``L`` (scale sweep)
    Points ``x_k(s) = s M k + c`` (``det M = 1``) stay in the cube for ``0 < s <= s_max(k)``, ``s_max(k) = min_i``
    of ``(1 - c_i) / m_i`` (``m_i > 0``) or ``c_i / |m_i|`` (``m_i < 0``), ``m = M k``; ``s`` strictly between the
    ``L``-th and ``(L + 1)``-th largest ``s_max`` gives exactly ``L`` points.

Parameters come from ``_TABLE``, found offline (Gram-matrix error first, covering second); a size without an entry
takes the nearest tabulated size's (``table_params``). Also here: seeded random, scrambled Sobol and Halton points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.validation import check_choice, check_positive_int, check_range

__all__ = [
    "FrolovParams", "PointSetKind", "halton_sequence", "frolov_lattice", "frolov_points", "halton_points",
    "random_points", "sobol_points", "table_params", "unit_cube_points",
]  # fmt: skip

PointSetKind = Literal["frolov", "random", "sobol", "halton"]
POINT_SET_KINDS: tuple[str, ...] = ("frolov", "random", "sobol", "halton")

# real roots, ordered so that the Galois action theta -> theta^2 - 2 shifts the coordinates cyclically
_ROOTS: dict[int, tuple[float, float, float]] = {
    49: tuple(2.0 * math.cos(2.0 * math.pi * k / 7.0) for k in (1, 2, 4)),  # x^3 + x^2 - 2x - 1
    81: tuple(2.0 * math.cos(2.0 * math.pi * k / 9.0) for k in (1, 2, 4)),  # x^3 - 3x + 1
}


@dataclass(frozen=True)
class FrolovParams:
    """Free parameters of a Frolov lattice (module docstring)."""

    discriminant: int = 49
    t1: float = 0.0
    t2: float = 0.0
    shift: tuple[float, float, float] = (0.5, 0.5, 0.5)
    signs: tuple[int, int, int] = (1, 1, 1)
    transpose: bool = False


def _generator(params: FrolovParams) -> list[list[float]]:
    """Determinant-one generator ``M = P S D V / det(V)^(1/3)`` as Python floats (bit-stable across devices)."""
    roots = _ROOTS[params.discriminant]
    vander = [[r**j for j in range(3)] for r in roots]
    det = abs(
        (roots[1] - roots[0]) * (roots[2] - roots[0]) * (roots[2] - roots[1])
    )  # Vandermonde determinant = sqrt(discriminant)
    logs = [math.log(abs(r)) for r in roots]
    logs_conj = logs[1:] + logs[:1]  # embeddings of the conjugate unit theta^2 - 2
    rows = []
    for i in range(3):
        scale = math.exp(params.t1 * logs[i] + params.t2 * logs_conj[i]) / det ** (1.0 / 3.0)
        rows.append([params.signs[i] * scale * v for v in vander[i]])
    if params.transpose:
        rows[1], rows[2] = rows[2], rows[1]
    return rows


def _enumerate(matrix: Tensor, shift: Tensor, scale: float) -> Tensor:
    """[K, 3] float64: every integer ``k`` with ``scale * M k + shift`` in the closed unit cube."""
    corners = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.float64)
    k_corners = torch.linalg.solve(matrix, ((corners - shift) / scale).T).T
    low, high = k_corners.amin(0).floor(), k_corners.amax(0).ceil()
    k1, k2 = torch.meshgrid(
        torch.arange(int(low[0]), int(high[0]) + 1, dtype=torch.float64),
        torch.arange(int(low[1]), int(high[1]) + 1, dtype=torch.float64),
        indexing="ij",
    )
    k1, k2 = k1.reshape(-1), k2.reshape(-1)
    base = k1[:, None] * matrix[:, 0] + k2[:, None] * matrix[:, 1]
    # each coordinate bounds k3 to an interval (no entry of M is zero)
    edge_a = (-shift / scale - base) / matrix[:, 2]
    edge_b = ((1.0 - shift) / scale - base) / matrix[:, 2]
    k3_low = torch.minimum(edge_a, edge_b).amax(1).ceil()
    k3_high = torch.maximum(edge_a, edge_b).amin(1).floor()
    counts = (k3_high - k3_low + 1.0).clamp_min(0.0).long()
    owner = torch.repeat_interleave(torch.arange(counts.numel()), counts)
    offset = torch.arange(int(counts.sum()), dtype=torch.float64) - torch.repeat_interleave(
        (torch.cumsum(counts, 0) - counts).double(), counts
    )
    return torch.stack([k1[owner], k2[owner], k3_low[owner] + offset], dim=1)


def frolov_points(num_points: int, params: FrolovParams = FrolovParams()) -> Float[Tensor, "l 3"]:
    """Exactly ``num_points`` points of the Frolov lattice ``params`` in ``[0, 1]^3`` (scale sweep)."""
    check_positive_int("num_points", num_points)
    check_choice("discriminant", params.discriminant, tuple(_ROOTS))
    for i, value in enumerate(params.shift):
        check_range(f"shift[{i}]", value, low=0.0, high=1.0, high_inclusive=False)
    matrix = torch.tensor(_generator(params), dtype=torch.float64)
    shift = torch.tensor(params.shift, dtype=torch.float64)
    nominal = num_points ** (-1.0 / 3.0)
    scale = 0.85 * nominal
    while True:
        ks = _enumerate(matrix, shift, scale)
        if ks.shape[0] > num_points:
            break
        scale *= 0.85
    # elementwise products (no BLAS): bit-identical across runs and thread counts
    m = ks[:, 0:1] * matrix[:, 0] + ks[:, 1:2] * matrix[:, 1] + ks[:, 2:3] * matrix[:, 2]
    inf = torch.full_like(m, math.inf)
    s_max = torch.where(m > 0, (1.0 - shift) / m, torch.where(m < 0, shift / (-m), inf)).amin(1)
    order = torch.argsort(s_max, descending=True, stable=True)
    kept, first_out = s_max[order[num_points - 1]].item(), s_max[order[num_points]].item()
    s = 2.0 * first_out if math.isinf(kept) else math.sqrt(kept * first_out)
    chosen = ks[order[:num_points]]
    points = s * (chosen[:, 0:1] * matrix[:, 0] + chosen[:, 1:2] * matrix[:, 1] + chosen[:, 2:3] * matrix[:, 2])
    points = (points + shift).clamp(0.0, 1.0)
    # canonical order: by the radial coordinate
    return points[torch.argsort(points[:, 0], stable=True)].contiguous()


def _radical_inverse(index: Tensor, base: int) -> Tensor:
    result = torch.zeros(index.shape, dtype=torch.float64)
    factor = 1.0 / base
    remaining = index.clone()
    while bool((remaining > 0).any()):
        result += factor * (remaining % base).double()
        remaining = remaining // base
        factor /= base
    return result


def halton_sequence(num_points: int, bases: tuple[int, ...], start: int = 1) -> Float[Tensor, "l d"]:
    """Radical-inverse (Halton) points in the given bases, indices ``start`` to ``start + num_points - 1``."""
    index = torch.arange(start, start + num_points, dtype=torch.int64)
    return torch.stack([_radical_inverse(index, b) for b in bases], dim=1)


# from the offline search, by the number of points
_TABLE: dict[int, FrolovParams] = {
    100: FrolovParams(
        49, 0.5126953125, 0.14677640603566527, (0.06432, 0.7559350270720533, 0.169045830202855), (1, 1, -1), False
    ),
    500: FrolovParams(
        81, 0.1796875, 0.9053497942386831, (0.352, 0.6180758017492711, 0.6280991735537189), (1, 1, 1), True
    ),
    5000: FrolovParams(
        49, 0.3359375, 0.6337448559670782, (0.272, 0.16909620991253643, 0.7107438016528925), (1, 1, -1), False
    ),
}


def table_params(num_points: int) -> FrolovParams:
    """``_TABLE``'s entry for ``num_points``, else that of the tabulated size nearest in log L (no search runs)."""
    check_positive_int("num_points", num_points)
    if num_points in _TABLE:
        return _TABLE[num_points]
    nearest = min(_TABLE, key=lambda size: (abs(math.log(size / num_points)), size))
    return _TABLE[nearest]


@lru_cache(maxsize=64)
def _frolov_cached(num_points: int) -> Tensor:
    return frolov_points(num_points, table_params(num_points))


def frolov_lattice(num_points: int) -> Float[Tensor, "l 3"]:
    """Exactly ``num_points`` Frolov-lattice points in ``[0, 1]^3``, float64, bit-identical across calls."""
    check_positive_int("num_points", num_points)
    return _frolov_cached(num_points).clone()


def random_points(num_points: int, seed: int = 0) -> Float[Tensor, "l 3"]:
    """Uniform random points from a CPU ``torch.Generator`` seeded with ``seed``."""
    check_positive_int("num_points", num_points)
    generator = torch.Generator().manual_seed(int(seed))
    return torch.rand((num_points, 3), generator=generator, dtype=torch.float64)


def sobol_points(num_points: int, seed: int = 0) -> Float[Tensor, "l 3"]:
    """First ``num_points`` points of a 3-D Sobol sequence, scrambled with ``seed``."""
    check_positive_int("num_points", num_points)
    engine = torch.quasirandom.SobolEngine(dimension=3, scramble=True, seed=int(seed))
    return engine.draw(num_points, dtype=torch.float64)


def halton_points(num_points: int) -> Float[Tensor, "l 3"]:
    """Halton points in bases 2, 3, 5, starting at index 1 (index 0 is the corner ``(0, 0, 0)``)."""
    check_positive_int("num_points", num_points)
    return halton_sequence(num_points, (2, 3, 5))


def unit_cube_points(kind: PointSetKind, num_points: int, seed: int = 0) -> Float[Tensor, "l 3"]:
    """Points of ``kind``; ``seed`` is used by ``random`` and ``sobol`` only."""
    check_choice("kind", kind, POINT_SET_KINDS)
    if kind == "frolov":
        return frolov_lattice(num_points)
    if kind == "random":
        return random_points(num_points, seed)
    if kind == "sobol":
        return sobol_points(num_points, seed)
    return halton_points(num_points)
