"""CamP's published proxy-point sampler (s2camp_ns/core/camp_sampling.py): measure, determinism, validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, pixel_to_ray_direction, project
from s2camp_ns.core.camp_sampling import (
    camp_frustum_points,
    inverse_power_ladder,
    ladder_distance,
    power_ladder,
)
from s2camp_ns.core.preconditioner import CAMP_SAMPLING, SamplingConfig, compute_preconditioner, sample_proxy_points

ROOM = Intrinsics.create(fx=793.13, fy=793.49, cx=389.25, cy=259.375, width=778, height=518)
DISTORTED = Intrinsics.create(fx=410.0, fy=405.0, cx=330.0, cy=210.0, width=640, height=420, k1=-0.03, k2=0.004)


def ladder_distance_density(t: Tensor, t_near: float, t_far: float, ladder_p: float) -> Tensor:
    """Density of ``ladder_distance`` of a uniform ``s``: ``L'(t) / (L(t_far) - L(t_near))`` (the reference the
    sampled distances are checked against)."""
    near, far = power_ladder(t_near, ladder_p), power_ladder(t_far, ladder_p)
    inside = (t >= t_near) & (t <= t_far)
    density = (1.0 + t / abs(ladder_p - 1.0)) ** (ladder_p - 1.0) / (far - near)
    return torch.where(inside, density, torch.zeros_like(density))


def test_power_ladder_published_values() -> None:
    # p = -1.5: L(x) = 5/3 (1 - (1 + x / 2.5)^-1.5), written out by hand.
    x = torch.tensor([0.0, 0.4, 2.5, 1000.0], dtype=torch.float64)
    expected = torch.tensor([5 / 3 * (1 - (1 + v / 2.5) ** -1.5) for v in x.tolist()], dtype=torch.float64)
    torch.testing.assert_close(power_ladder(x, -1.5), expected, rtol=1e-14, atol=1e-15)
    assert power_ladder(2.5, -1.5) == pytest.approx(5 / 3 * (1 - 2**-1.5), rel=1e-14)
    torch.testing.assert_close(inverse_power_ladder(power_ladder(x, -1.5), -1.5), x, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(inverse_power_ladder(power_ladder(x, -3.0), -3.0), x, rtol=1e-8, atol=1e-12)


def test_ladder_distance_end_points_and_median() -> None:
    s = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    t = ladder_distance(s, 0.4, 1000.0, -1.5)
    assert t[0].item() == pytest.approx(0.4, rel=1e-12) and t[2].item() == pytest.approx(1000.0, rel=1e-9)
    # Median by hand: (1 + t / 2.5)^-1.5 = 1 - 0.6 (L(0.4) + L(1000)) / 2.
    near, far = 5 / 3 * (1 - 1.16**-1.5), 5 / 3 * (1 - 401**-1.5)
    median = 2.5 * ((1 - 0.6 * (near + far) / 2) ** (-1 / 1.5) - 1)
    assert t[1].item() == pytest.approx(median, rel=1e-12)


def test_distances_follow_the_ladder_density() -> None:
    # CDF of the sampled distances against the density integrated numerically (trapezoid on a fine log grid).
    points = camp_frustum_points(ROOM, 40_000, seed=3)
    distance = points.norm(dim=-1)[0].sort().values
    grid = torch.logspace(math.log10(0.4), math.log10(1000.0), 200_001, dtype=torch.float64)
    density = ladder_distance_density(grid, 0.4, 1000.0, -1.5)
    steps = 0.5 * (density[1:] + density[:-1]) * grid.diff()
    cdf = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(steps, 0)])
    assert cdf[-1].item() == pytest.approx(1.0, abs=1e-6)
    expected = torch.from_numpy(np.interp(distance.numpy(), grid.numpy(), cdf.numpy()))
    empirical = torch.arange(1, len(distance) + 1, dtype=torch.float64) / len(distance)
    assert float((expected - empirical).abs().max()) < 1.95 / math.sqrt(len(distance))  # KS at alpha 1e-3


@pytest.mark.parametrize("intrinsics", [ROOM, DISTORTED], ids=["room", "distorted"])
def test_points_reproduce_the_uniform_pixel_and_distance_draws(intrinsics: Intrinsics) -> None:
    # The same draws, redone by hand: pixel = d (size - 1/2), distance = ladder(s); projecting gives them back.
    points = camp_frustum_points(intrinsics, 2000, t_near=0.3, t_far=50.0, ladder_p=-2.0, seed=11)
    draws = torch.rand((1, 2000, 3), generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    size = torch.tensor([intrinsics.width.item(), intrinsics.height.item()], dtype=torch.float64) - 0.5
    pixels, depth = project(points, intrinsics)
    assert bool((depth > 0).all())
    torch.testing.assert_close(pixels, draws[..., :2] * size, rtol=0, atol=1e-8)
    q = 3.0
    near, far = q / -2.0 * ((1 + 0.3 / q) ** -2.0 - 1), q / -2.0 * ((1 + 50.0 / q) ** -2.0 - 1)
    y = near + draws[..., 2] * (far - near)
    torch.testing.assert_close(points.norm(dim=-1), q * ((1 - 2.0 * y / q) ** -0.5 - 1), rtol=1e-12, atol=0)


def test_pinhole_shortcut_gives_the_undistortion_path_bit_for_bit() -> None:
    skewed = Intrinsics.create(fx=500.0, fy=480.0, cx=300.0, cy=200.0, width=640, height=400, skew=3.0)
    for intrinsics in (ROOM, skewed):
        points = camp_frustum_points(intrinsics, 500, seed=2)
        draws = torch.rand((1, 500, 3), generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        size = torch.tensor([intrinsics.width.item(), intrinsics.height.item()], dtype=torch.float64) - 0.5
        directions = pixel_to_ray_direction(draws[..., :2] * size, intrinsics)
        distance = ladder_distance(draws[..., 2], 0.4, 1000.0, -1.5)
        assert torch.equal(points, distance.unsqueeze(-1) * directions)


def test_camp_points_are_deterministic_per_seed() -> None:
    first = camp_frustum_points(ROOM, 300, seed=4)
    again = camp_frustum_points(ROOM, 300, generator=torch.Generator().manual_seed(4))
    assert torch.equal(first, again)
    assert not torch.equal(first, camp_frustum_points(ROOM, 300, seed=5))
    config = SamplingConfig(sampler="camp-random", num_points=300, t_near=0.4, t_far=1000.0, seed=4)
    assert torch.equal(sample_proxy_points(ROOM, config), first)


def test_published_configuration() -> None:
    assert (CAMP_SAMPLING.sampler, CAMP_SAMPLING.num_points) == ("camp-random", 5000)
    assert (CAMP_SAMPLING.t_near, CAMP_SAMPLING.t_far, CAMP_SAMPLING.ladder_p) == (0.4, 1000.0, -1.5)
    pre = compute_preconditioner(ROOM, sampling=CAMP_SAMPLING)
    assert int(pre.num_valid[0]) == 5000  # every point lies inside the image
    # The far distance of CamP is not a contracted radius: the volume samplers keep rejecting t_far >= 2.
    with pytest.raises(ValueError, match="^t_far must"):
        SamplingConfig(sampler="frolov", t_far=1000.0).validate()


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"t_near": 0.0}, "t_near"),
        ({"t_near": 2.0, "t_far": 1.0}, "t_far"),
        ({"t_far": math.inf}, "t_far"),
        ({"ladder_p": 0.5}, "ladder_p"),
        ({"ladder_p": 0.0}, "ladder_p"),
    ],
)
def test_bad_camp_sampling_names_the_parameter(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=rf"^{name} must"):
        SamplingConfig(sampler="camp-random", **kwargs).validate()
    arguments = {"t_near": 0.4, "t_far": 1000.0, "ladder_p": -1.5, **kwargs}
    with pytest.raises(ValueError, match=rf"^{name} must"):
        camp_frustum_points(ROOM, 10, **arguments)


def test_bad_num_points_names_the_parameter() -> None:
    with pytest.raises(ValueError, match="^num_points must"):
        camp_frustum_points(ROOM, 0)
