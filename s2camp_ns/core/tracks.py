"""Reprojection error of a scene's SfM tracks under given cameras, in pixels.

A track is a 3D point with the images that observe it and where. Each observation's point is projected through its
image's camera (paper eq. 2, distortion included) and compared with the observed pixel; the RMS over an image's
observations is its reprojection error. It is invariant to a similarity of points and cameras together.
Observations behind the camera or beyond a fisheye's fold are left out; an image with none left gets NaN. Cameras
are OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, project


@dataclass(frozen=True)
class Tracks:
    """3D points and their observations, pixels in COLMAP's convention (top-left pixel centre at (0.5, 0.5))."""

    points: Float[Tensor, "p 3"]
    """World points."""
    image: Int[Tensor, " o"]
    """Observing image of each observation (0 .. n - 1)."""
    point: Int[Tensor, " o"]
    """Observed point of each observation (row of ``points``)."""
    pixels: Float[Tensor, "o 2"]
    """Observed pixel (u, v) of each observation."""

    def validate(self, num_images: int) -> None:
        o = self.image.shape[0]
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"tracks.points must have shape [P, 3], got {tuple(self.points.shape)}")
        if self.image.shape != (o,) or self.point.shape != (o,) or self.pixels.shape != (o, 2):
            raise ValueError(
                f"tracks.image, tracks.point and tracks.pixels must have shapes [O], [O], [O, 2]; got "
                f"{tuple(self.image.shape)}, {tuple(self.point.shape)}, {tuple(self.pixels.shape)}"
            )
        if o and (int(self.image.min()) < 0 or int(self.image.max()) >= num_images):
            raise ValueError(f"tracks.image must index the {num_images} cameras, got values in "
                             f"[{int(self.image.min())}, {int(self.image.max())}]")  # fmt: skip
        if o and (int(self.point.min()) < 0 or int(self.point.max()) >= self.points.shape[0]):
            raise ValueError(f"tracks.point must index the {self.points.shape[0]} points, got values in "
                             f"[{int(self.point.min())}, {int(self.point.max())}]")  # fmt: skip


def track_reprojection_rms(tracks: Tracks, c2w: Float[Tensor, "n 3 4"], intrinsics: Intrinsics) -> Float[Tensor, " n"]:
    """Reprojection RMS (px) per image, float64 on ``c2w``'s device; NaN for an image with no valid observation."""
    n = c2w.shape[0]
    if c2w.ndim != 3 or c2w.shape[1:] != (3, 4):
        raise ValueError(f"c2w must have shape [N, 3, 4], got {tuple(c2w.shape)}")
    if intrinsics.num_cameras != n:
        raise ValueError(f"intrinsics must describe the {n} cameras of c2w, got {intrinsics.num_cameras}")
    tracks.validate(n)
    device = c2w.device
    c2w = c2w.to(torch.float64)
    image = tracks.image.to(device)
    points = tracks.points.to(device=device, dtype=torch.float64)[tracks.point.to(device)]
    rotation, centre = c2w[image, :, :3], c2w[image, :, 3]
    # R^T (x - c), [O, 1, 3] for ``project``'s [n, l, 3].
    points_cam = (points - centre)[:, None, :] @ rotation
    pixels, margin = project(points_cam, intrinsics.to(device=device, dtype=torch.float64)[image])
    squared = (pixels[:, 0] - tracks.pixels.to(device=device, dtype=torch.float64)).square().sum(dim=-1)
    return per_image_rms(squared, (margin[:, 0] > 0).to(torch.float64), image, n)


def index_in_image(image: Int[Tensor, " o"], num_images: int) -> tuple[Int[Tensor, " o"], int]:
    """Each observation's index among its image's observations, in observation order ([o], on ``image``'s device:
    its keypoint index in a COLMAP image, or its slot in a per-camera [n, l, ...] batch), and the largest count l."""
    count = torch.bincount(image, minlength=num_images)
    order = torch.argsort(image, stable=True)
    first = (torch.cumsum(count, 0) - count)[image[order]]  # where each observation's image begins in ``order``
    index = torch.empty_like(image)
    index[order] = torch.arange(image.shape[0], device=image.device) - first
    return index, int(count.max()) if num_images else 0


def per_image_rms(
    squared: Float[Tensor, " o"], weight: Float[Tensor, " o"], image: Int[Tensor, " o"], num_images: int
) -> Float[Tensor, " n"]:
    """Per image, the RMS of ``squared`` pixel distances weighted by ``weight`` (1 valid, 0 left out); NaN for none."""
    total = torch.zeros(num_images, dtype=squared.dtype, device=squared.device).index_add_(0, image, squared * weight)
    count = torch.zeros(num_images, dtype=squared.dtype, device=squared.device).index_add_(0, image, weight)
    rms = (total / count.clamp(min=1.0)).sqrt()
    return torch.where(count > 0, rms, torch.full_like(rms, float("nan")))


__all__ = ["Tracks", "index_in_image", "per_image_rms", "track_reprojection_rms"]
