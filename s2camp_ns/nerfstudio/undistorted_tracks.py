"""Track keypoints moved into the images a full-image data manager undistorted (splatfacto's).

splatfacto's data manager undistorts every distorted training image once (OpenCV's ``undistort`` to the new pinhole K
of ``getOptimalNewCameraMatrix`` at alpha 0, cropped to its valid region; the principal point shifted by half a pixel
around OpenCV's call so that K stays in nerfstudio's convention, the top-left pixel's centre at (0.5, 0.5)) and writes
that K into the training cameras. The SfM keypoints are the distorted images' pixels. Each keypoint p of image i moves
to where the undistortion puts its ray:

    (a, b) = unproject(p; K_i, distortion_i)        (the undistorted tangents x / z, y / z, ``core.unprojection``)
    p'     = (f'_x a + c'_x, f'_y b + c'_y)          (K'_i, the undistorted image's pinhole camera)

Both sides are in the same pixel convention, so the half-pixel shifts cancel: the map is the undistortion's own, the
crop included. An observation whose ray the distorted camera cannot unproject (a fisheye pixel at 90 degrees or more)
is dropped.
"""

from __future__ import annotations

import dataclasses

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.tracks import Tracks
from s2camp_ns.core.unprojection import unproject


def undistorted_pixels(
    pixels: Float[Tensor, "o 2"], distorted: Intrinsics, undistorted: Intrinsics
) -> Float[Tensor, "o 2"]:
    """The module docstring's map, one camera per pixel (``distorted`` and ``undistorted`` hold o cameras); NaN where
    the ray cannot be unprojected."""
    tangents = unproject(pixels.to(torch.float64)[:, None, :], distorted.to(dtype=torch.float64))[:, 0]  # [o, 2]
    pinhole = undistorted.to(dtype=torch.float64)
    u = pinhole.fx * tangents[:, 0] + pinhole.cx
    v = pinhole.fy * tangents[:, 1] + pinhole.cy
    return torch.stack([u, v], dim=-1)


def undistorted_track_evidence(
    evidence: TrackEvidence, distorted: Intrinsics, undistorted: Intrinsics
) -> TrackEvidence:
    """``evidence`` with its keypoints in the undistorted images (module docstring): ``distorted`` the training
    cameras' intrinsics as the data parser gave them, ``undistorted`` the pinhole intrinsics the data manager wrote
    (one per training image each). Points and cameras are unchanged."""
    tracks = evidence.tracks
    image = tracks.image.to(torch.long)
    moved = undistorted_pixels(tracks.pixels, distorted[image], undistorted[image])  # [o, 2]
    keep = torch.isfinite(moved).all(dim=-1)
    kept = Tracks(
        points=tracks.points,
        image=tracks.image[keep],
        point=tracks.point[keep],
        pixels=moved[keep].to(tracks.pixels.dtype),
    )
    return dataclasses.replace(evidence, tracks=kept)


__all__ = ["undistorted_pixels", "undistorted_track_evidence"]
