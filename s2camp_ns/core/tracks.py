"""Reprojection error of a scene's SfM tracks under given cameras: how far, in pixels, the data says each camera is
from agreeing with the 3D points it observes.

A COLMAP model stores, for every 3D point, the images that observe it and where (its track). Projecting each point
through the camera as the user gives it (paper eq. 2, with the camera's distortion) and comparing with the observed
pixel gives one residual per observation; the RMS over an image's observations is that camera's reprojection error.
For cameras straight out of SfM it is SfM's own error (keypoint noise, a fraction of a pixel); for cameras that were
changed after SfM (perturbed, or replaced by phone poses) it grows with the change. The camera optimizer's track
prior (``S2CampCameraOptimizer.apply_track_prior``) takes it as the scale of the camera moves that need no evidence.

The RMS is invariant to a similarity of the world (points and cameras together), so any frame in which points and
cameras agree will do. Observations of points behind the camera, or beyond a fisheye's fold, are left out (their
pixels are meaningless); an image with none left gets NaN. Cameras use the OpenCV convention, like the rest of
``s2camp_ns.core``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, project


@dataclass(frozen=True)
class Tracks:
    """3D points and their observations; pixels in the intrinsics' pixel convention (COLMAP's: the top-left pixel's
    centre at (0.5, 0.5))."""

    points: Float[Tensor, "p 3"]
    """World points."""
    image: Int[Tensor, " o"]
    """Observing image of each observation (0 .. n - 1, the cameras' order)."""
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
    """RMS pixel distance, per camera, between each observed pixel and its point projected through the camera
    (float64, on ``c2w``'s device); NaN for a camera with no valid observation (module docstring)."""
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
    # Camera-frame point R^T (x - c), one observation per row ([O, 1, 3] for ``project``'s [n, l, 3]).
    points_cam = (points - centre)[:, None, :] @ rotation
    pixels, margin = project(points_cam, intrinsics.to(device=device, dtype=torch.float64)[image])
    squared = (pixels[:, 0] - tracks.pixels.to(device=device, dtype=torch.float64)).square().sum(dim=-1)
    return per_image_rms(squared, (margin[:, 0] > 0).to(torch.float64), image, n)


def per_image_rms(
    squared: Float[Tensor, " o"], weight: Float[Tensor, " o"], image: Int[Tensor, " o"], num_images: int
) -> Float[Tensor, " n"]:
    """RMS over each image's observations of the squared pixel distances ``squared`` counted with ``weight`` (1: a
    valid observation, 0: left out); NaN for an image with none."""
    total = torch.zeros(num_images, dtype=squared.dtype, device=squared.device).index_add_(0, image, squared * weight)
    count = torch.zeros(num_images, dtype=squared.dtype, device=squared.device).index_add_(0, image, weight)
    rms = (total / count.clamp(min=1.0)).sqrt()
    return torch.where(count > 0, rms, torch.full_like(rms, float("nan")))


__all__ = ["Tracks", "per_image_rms", "track_reprojection_rms"]
