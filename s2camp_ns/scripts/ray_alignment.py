"""Test-time alignment's renderer for ray (nerfacto) models: each step renders ``rays`` seeded random pixels of
every view in one forward pass; full images in chunks of ``chunk`` rays.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, pixel_to_ray_direction
from s2camp_ns.scripts.alignment_camera import HeldOutView, scale_focal, twisted_c2w


def camera_rays(
    c2w_gl: Float[Tensor, "3 4"],
    intrinsics: Intrinsics,
    pixels: Float[Tensor, "r 2"],
    twist: Float[Tensor, 6],
    log_focal: Float[Tensor, ""],
    device: torch.device | str,
) -> RayBundle:
    """float32 rays through ``pixels`` of the camera c2w exp(twist), focal lengths scaled by exp(log_focal), with the
    camera's distortion; differentiable in ``twist`` and ``log_focal``."""
    scaled = scale_focal(intrinsics.to(dtype=torch.float64), torch.exp(log_focal))
    directions_cam = pixel_to_ray_direction(pixels.double()[None], scaled)[0]
    c2w = twisted_c2w(c2w_gl, twist)
    directions = directions_cam @ c2w[:, :3].T
    count = pixels.shape[0]
    # nerfstudio's directions_norm: |(a, b, 1)| = 1 / d_z for perspective cameras, 1 for fisheye ones (unit rays).
    norm = torch.ones_like(directions_cam[:, 2:3]) if scaled.is_fisheye else 1.0 / directions_cam[:, 2:3]
    return RayBundle(
        origins=c2w[:, 3].expand(count, 3).to(device=device, dtype=torch.float32),
        directions=directions.to(device=device, dtype=torch.float32),
        pixel_area=(1.0 / (scaled.fx * scaled.fy)).detach().expand(count, 1).to(device=device, dtype=torch.float32),
        camera_indices=torch.zeros(count, 1, dtype=torch.long, device=device),
        metadata={"directions_norm": norm.to(device=device, dtype=torch.float32)},
    )


def pixel_grid(width: int, height: int) -> Float[Tensor, "hw 2"]:
    """Centres (x + 0.5, y + 0.5) of every pixel, row by row."""
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    return torch.stack([xs, ys], dim=-1).reshape(-1, 2).double() + 0.5


def concatenate_rays(bundles: list[RayBundle]) -> RayBundle:
    """The rays of several bundles in one RayBundle."""
    if len(bundles) == 1:
        return bundles[0]
    return RayBundle(
        origins=torch.cat([b.origins for b in bundles]),
        directions=torch.cat([b.directions for b in bundles]),
        pixel_area=torch.cat([b.pixel_area for b in bundles]),
        camera_indices=torch.cat([b.camera_indices for b in bundles]),
        metadata={key: torch.cat([b.metadata[key] for b in bundles]) for key in bundles[0].metadata},
    )


class RayRenderer:
    """Renders held-out views of a ray model through (twist, log focal): random pixels per step, full images."""

    def __init__(self, model, rays: int, chunk: int) -> None:
        self.model = model
        self.rays = rays
        self.chunk = chunk

    def step_colours(
        self,
        views: list[HeldOutView],
        targets: list[Float[Tensor, "h w 3"]],
        twists: list[Tensor],
        log_focals: list[Tensor],
        generators: list[torch.Generator],
    ) -> list[tuple[Tensor, Tensor]]:
        """(predicted, target) colours [rays, 3] of each view; differentiable in the variables."""
        grids = [pixel_grid(target.shape[1], target.shape[0]) for target in targets]
        chosen = [
            torch.randint(0, grid.shape[0], (self.rays,), generator=generator)
            for grid, generator in zip(grids, generators, strict=True)
        ]
        bundles = [
            camera_rays(view.c2w_gl, view.intrinsics, grid[pick], twist, log_focal, self.model.device)
            for view, grid, pick, twist, log_focal in zip(views, grids, chosen, twists, log_focals, strict=True)
        ]
        predicted = self.model(concatenate_rays(bundles))["rgb"].float().cpu().split(self.rays)
        return [
            (colours, target.reshape(-1, 3)[pick])
            for colours, target, pick in zip(predicted, targets, chosen, strict=True)
        ]

    @torch.no_grad()
    def image(self, view: HeldOutView, width: int, height: int, twist: Tensor, log_focal: Tensor) -> Tensor:
        """The full image [height, width, 3] (float32, CPU) through the view's camera moved by (twist, log_focal)."""
        pixels = pixel_grid(width, height)
        colours = []
        for start in range(0, pixels.shape[0], self.chunk):
            rays = camera_rays(
                view.c2w_gl, view.intrinsics, pixels[start : start + self.chunk], twist, log_focal, self.model.device
            )
            colours.append(self.model(rays)["rgb"].float().cpu())
        return torch.cat(colours, dim=0).reshape(height, width, 3)
