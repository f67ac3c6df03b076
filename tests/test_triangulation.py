"""``core.triangulation``: points re-triangulated in fixed cameras."""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_ns.core.camera import Intrinsics, project
from s2camp_ns.core.tracks import Tracks
from s2camp_ns.core.triangulation import retriangulated_points


def ring_cameras(n: int, radius: float = 4.0) -> torch.Tensor:
    """OpenCV camera-to-world [n, 3, 4] on a ring around the origin, each looking at it."""
    c2w = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        centre = torch.tensor([radius * math.cos(angle), radius * math.sin(angle), 0.5], dtype=torch.float64)
        forward = -centre / centre.norm()
        right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        c2w.append(torch.cat([torch.stack([right, down, forward], dim=1), centre[:, None]], dim=1))
    return torch.stack(c2w)


def observed(points: torch.Tensor, c2w: torch.Tensor, intrinsics: Intrinsics, views: int) -> Tracks:
    """Every point seen by ``views`` consecutive cameras of the ring, at its exact projection."""
    n, p = c2w.shape[0], points.shape[0]
    image = torch.stack([(torch.arange(p) + k) % n for k in range(views)], dim=1).reshape(-1)
    point = torch.arange(p).repeat_interleave(views)
    points_cam = (points[point] - c2w[image, :, 3])[:, None, :] @ c2w[image, :, :3]
    pixels, margin = project(points_cam, intrinsics[image])
    assert bool((margin > 0).all())
    return Tracks(points, image, point, pixels[:, 0])


@pytest.mark.parametrize("model", ["perspective", "fisheye"])
def test_exact_observations_recover_the_points(model: str):
    """From points moved by about 5 cm, the exact observations through distorted cameras give the points back."""
    generator = torch.Generator().manual_seed(0)
    c2w = ring_cameras(8)
    intrinsics = Intrinsics.create(300.0, 310.0, 320.0, 240.0, 640, 480, k1=-0.08, k2=0.01, model=model)
    intrinsics = Intrinsics.from_tensors(intrinsics.tensors().expand(8, -1), model=model)
    truth = torch.rand(60, 3, generator=generator, dtype=torch.float64) - 0.5
    tracks = observed(truth, c2w, intrinsics, views=3)
    start = truth + 0.05 * torch.randn(truth.shape, generator=generator, dtype=torch.float64)
    moved = Tracks(start, tracks.image, tracks.point, tracks.pixels)
    result = retriangulated_points(moved, c2w, intrinsics)
    assert float((result - truth).norm(dim=-1).max()) < 1e-7
    assert float((start - truth).norm(dim=-1).min()) > 1e-3  # the start was off


def test_noisy_observations_never_raise_a_points_cost():
    """With noisy pixels each point ends at a cost no higher than it started with, and most fall."""
    generator = torch.Generator().manual_seed(1)
    c2w = ring_cameras(10)
    intrinsics = Intrinsics.from_tensors(
        Intrinsics.create(300.0, 300.0, 320.0, 240.0, 640, 480).tensors().expand(10, -1)
    )
    truth = torch.rand(80, 3, generator=generator, dtype=torch.float64) - 0.5
    exact = observed(truth, c2w, intrinsics, views=4)
    noisy = exact.pixels + torch.randn(exact.pixels.shape, generator=generator, dtype=torch.float64)
    tracks = Tracks(truth, exact.image, exact.point, noisy)

    def cost(points: torch.Tensor) -> torch.Tensor:
        points_cam = (points[tracks.point] - c2w[tracks.image, :, 3])[:, None, :] @ c2w[tracks.image, :, :3]
        pixels, _ = project(points_cam, intrinsics[tracks.image])
        squared = (pixels[:, 0] - noisy).square().sum(dim=-1)
        return torch.zeros(80, dtype=torch.float64).index_add_(0, tracks.point, squared)

    before, after = cost(truth), cost(retriangulated_points(tracks, c2w, intrinsics))
    assert bool((after <= before * (1 + 1e-12)).all())
    assert int((after < 0.9 * before).sum()) > 60
