"""Unit-cube point sets: exact counts, determinism, range, and the Frolov product property."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import pytest
import torch

from s2camp_ns.core import lattice
from s2camp_ns.core.lattice import (
    FrolovParams,
    frolov_lattice,
    frolov_points,
    halton_points,
    random_points,
    sobol_points,
    table_params,
    unit_cube_points,
)


@pytest.mark.parametrize("num_points", [1, 2, 3, 7, 13, 64, 100, 257, 500, 1000, 5000])
@pytest.mark.parametrize("params", [FrolovParams(), FrolovParams(81, 0.3, 0.7, (0.1, 0.9, 0.4), (1, -1, 1), True)])
def test_frolov_points_exact_count_and_range(num_points: int, params: FrolovParams) -> None:
    points = frolov_points(num_points, params)
    assert points.shape == (num_points, 3)
    assert points.dtype == torch.float64
    assert bool(((points >= 0.0) & (points <= 1.0)).all())
    assert torch.unique(points, dim=0).shape[0] == num_points


@pytest.mark.parametrize("num_points", [1, 7, 100, 500, 5000])
def test_frolov_lattice_exact_and_bit_identical(num_points: int) -> None:
    first = frolov_lattice(num_points)
    lattice._frolov_cached.cache_clear()
    second = frolov_lattice(num_points)
    assert first.shape == (num_points, 3)
    assert torch.equal(first, second)
    assert bool(((first >= 0.0) & (first <= 1.0)).all())


def test_table_covers_benchmark_sizes() -> None:
    assert {100, 500, 5000} <= set(lattice._TABLE)


def test_untabled_size_takes_the_nearest_entry_without_a_search() -> None:
    # 700 is nearer to 500 than to 5000 in log L; 3000 is nearer to 5000 (unless a 2000 entry exists).
    assert table_params(700) == lattice._TABLE[500]
    nearest = min(lattice._TABLE, key=lambda size: abs(math.log(size / 3000)))
    assert table_params(3000) == lattice._TABLE[nearest]
    assert frolov_lattice(700).shape == (700, 3)


def test_runtime_lattice_imports_nothing_above_validation() -> None:
    # Every import statement of the module, also those inside functions: only the validation helpers of the project.
    tree = ast.parse(Path(lattice.__file__).read_text(encoding="utf8"))
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    assert {name for name in imported if name.startswith("s2camp_ns")} == {"s2camp_ns.core.validation"}


def test_frolov_product_property() -> None:
    # Differences of Frolov points satisfy |dx1 dx2 dx3| >= s^3 / sqrt(disc) for the lattice scale s (Frolov 1976).
    num_points = 400
    points = frolov_points(num_points, FrolovParams())
    diff = (points[:, None, :] - points[None, :, :]).abs().prod(-1)
    off = diff[~torch.eye(num_points, dtype=torch.bool)]
    # The scale sweep keeps s within a few percent of L^(-1/3).
    assert float(off.min()) >= 0.8 / (7.0 * num_points)


def test_frolov_marginals_are_uniform() -> None:
    points = frolov_lattice(500)
    for axis in range(3):
        ordered = points[:, axis].sort().values
        grid = (torch.arange(500, dtype=torch.float64) + 0.5) / 500
        assert float((ordered - grid).abs().max()) < 0.02


@pytest.mark.parametrize("fn", [random_points, sobol_points])
def test_seeded_sets(fn) -> None:
    a, b, c = fn(123, seed=3), fn(123, seed=3), fn(123, seed=4)
    assert a.shape == (123, 3) and a.dtype == torch.float64
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    assert bool(((a >= 0.0) & (a <= 1.0)).all())


def test_halton_points() -> None:
    h = halton_points(10)
    assert h.shape == (10, 3)
    assert torch.allclose(h[:3, 0], torch.tensor([0.5, 0.25, 0.75], dtype=torch.float64))
    assert torch.allclose(h[:3, 1], torch.tensor([1 / 3, 2 / 3, 1 / 9], dtype=torch.float64))


@pytest.mark.parametrize("kind", ["frolov", "random", "sobol", "halton"])
def test_dispatcher(kind: str) -> None:
    points = unit_cube_points(kind, 100, seed=1)
    assert points.shape == (100, 3)


def test_errors_name_the_parameter() -> None:
    with pytest.raises(ValueError, match="num_points"):
        frolov_lattice(0)
    with pytest.raises(ValueError, match="num_points"):
        random_points(-3)
    with pytest.raises(ValueError, match="kind"):
        unit_cube_points("grid", 10)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="shift"):
        frolov_points(10, FrolovParams(shift=(0.5, 1.5, 0.5)))
