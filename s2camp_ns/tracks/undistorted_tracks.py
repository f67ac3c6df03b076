"""Track keypoints moved into the images a full-image data manager undistorted (splatfacto's).

splatfacto undistorts each distorted training image to the pinhole K' of OpenCV's ``getOptimalNewCameraMatrix``
(alpha 0, cropped) and writes K' into the training cameras. Each keypoint p of image i moves where its ray goes:

    (a, b) = unproject(p; K_i, distortion_i)        (tangents x / z, y / z, ``core.camera``)
    p'     = (f'_x a + c'_x, f'_y b + c'_y)

Both in nerfstudio's pixel convention, so the map is the undistortion's own. Observations that cannot be unprojected
(a fisheye pixel at 90 degrees or more) are dropped.
"""

from __future__ import annotations

import dataclasses

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, unproject
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.tracks import Tracks


def undistorted_pixels(
    pixels: Float[Tensor, "o 2"], distorted: Intrinsics, undistorted: Intrinsics
) -> Float[Tensor, "o 2"]:
    """The module docstring's map [o, 2], one camera per pixel in ``distorted`` and ``undistorted``; NaN where the
    ray cannot be unprojected."""
    tangents = unproject(pixels.to(torch.float64)[:, None, :], distorted.to(dtype=torch.float64))[:, 0]  # [o, 2]
    pinhole = undistorted.to(dtype=torch.float64)
    u = pinhole.fx * tangents[:, 0] + pinhole.cx
    v = pinhole.fy * tangents[:, 1] + pinhole.cy
    return torch.stack([u, v], dim=-1)


def undistorted_track_evidence(
    evidence: TrackEvidence, distorted: Intrinsics, undistorted: Intrinsics
) -> TrackEvidence:
    """``evidence`` with its keypoints in the undistorted images: ``distorted`` the intrinsics the data parser gave,
    ``undistorted`` those the data manager wrote (one per training image each)."""
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
