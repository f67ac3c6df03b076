"""Dispersion (largest empty ball with centre in the frustum) by branch and bound, against brute force."""

from __future__ import annotations

import pytest
import torch
from frustum_cdf import frustum_to_unit

from s2camp_bench.dispersion_bound import dispersion, reference_tangent_bounds
from s2camp_ns.core.frustum import sample_frustum

ROOM = reference_tangent_bounds("room")
OFF_CENTRE = torch.tensor([[-0.3, 0.9, 0.1, 0.6]], dtype=torch.float64)


@pytest.mark.parametrize("transform", ["pyramid", "spherical"])
def test_single_point_at_apex(transform: str) -> None:
    # One point on the camera centre: the farthest frustum point is on the far cap, at distance t_far.
    result = dispersion(torch.zeros(1, 1, 3, dtype=torch.float64), ROOM, 0.0, 1.5, transform, tol=3e-2)
    assert abs(float(result.value[0]) - 1.5) < 1e-9
    assert float(result.error_bound[0]) <= 3e-2


def test_two_points_far_corners() -> None:
    # Points at the two far corners of the left image edge of a symmetric box: the largest empty ball sits on the
    # right edge; compare with brute force over a fine probe set.
    box = torch.tensor([[-0.5, 0.5, -0.3, 0.3]], dtype=torch.float64)
    corners = torch.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0]], dtype=torch.float64)
    points = sample_frustum(corners, box, 0.0, 1.0, "pyramid").contracted
    result = dispersion(points, box, 0.0, 1.0, "pyramid", tol=1e-3)
    probes = sample_frustum(
        torch.rand((200_000, 3), dtype=torch.float64, generator=torch.Generator().manual_seed(1)), box, 0.0, 1.0
    ).contracted[0]
    brute = float(torch.cdist(probes, points[0]).amin(1).max())
    assert brute <= float(result.upper[0]) + 1e-12
    assert float(result.value[0]) >= brute - 1e-3


@pytest.mark.parametrize("transform", ["pyramid", "spherical"])
def test_random_points_against_probes(transform: str) -> None:
    gen = torch.Generator().manual_seed(3)
    points = sample_frustum(
        torch.rand((40, 3), generator=gen, dtype=torch.float64), OFF_CENTRE, 0.2, 1.8, transform
    ).contracted
    result = dispersion(points, OFF_CENTRE, 0.2, 1.8, transform, tol=1e-3)
    probes = sample_frustum(
        torch.rand((100_000, 3), generator=gen, dtype=torch.float64), OFF_CENTRE, 0.2, 1.8, transform
    ).contracted[0]
    brute = float(torch.cdist(probes, points[0]).amin(1).max())
    assert brute <= float(result.upper[0]) + 1e-12
    assert float(result.value[0]) >= brute - 0.02  # random probes miss the exact maximiser by a little
    assert 0.0 <= float(result.error_bound[0]) <= 1e-3
    centre_u = frustum_to_unit(result.centre[None], OFF_CENTRE, 0.2, 1.8, transform)
    assert bool(((centre_u > -1e-9) & (centre_u < 1 + 1e-9)).all())


def test_deterministic_and_batched() -> None:
    bounds = torch.cat([ROOM, OFF_CENTRE])
    u = torch.rand((60, 3), generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    points = sample_frustum(u, bounds, 0.0, 1.99).contracted
    first, second = dispersion(points, bounds, 0.0, 1.99), dispersion(points, bounds, 0.0, 1.99)
    assert torch.equal(first.value, second.value) and first.value.shape == (2,)
    single = dispersion(points[1:], OFF_CENTRE, 0.0, 1.99)
    assert torch.equal(single.value[0], first.value[1])


def test_dispersion_errors() -> None:
    points = torch.zeros(1, 5, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="tol"):
        dispersion(points, ROOM, 0.0, 1.0, tol=0.0)
    with pytest.raises(ValueError, match="points_contracted"):
        dispersion(torch.zeros(2, 5, 3, dtype=torch.float64), ROOM, 0.0, 1.0)
    with pytest.raises(ValueError, match="transform"):
        dispersion(points, ROOM, 0.0, 1.0, transform="cube")
    with pytest.raises(ValueError, match="t_far"):
        dispersion(points, ROOM, 0.0, 2.5)
