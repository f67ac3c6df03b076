"""Track keypoints moved into the images splatfacto's data manager undistorted (``tracks.undistorted_tracks``),
checked against nerfstudio's own undistortion of an image."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.tracks import Tracks
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
from s2camp_ns.tracks.undistorted_tracks import undistorted_pixels, undistorted_track_evidence

WIDTH, HEIGHT = 200, 150


def _camera(fx, fy, cx, cy, width=WIDTH, height=HEIGHT, distortion=None) -> Cameras:
    return Cameras(
        camera_to_worlds=torch.eye(4)[None, :3], fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height,
        distortion_params=None if distortion is None else distortion[None], camera_type=CameraType.PERSPECTIVE,
    )  # fmt: skip


def test_keypoints_land_where_nerfstudios_undistortion_puts_their_image_content():
    """Four small blobs drawn at known pixels of a distorted image (radial and tangential terms; the top-left pixel's
    centre at (0.5, 0.5)); nerfstudio's data manager undistorts the image (OpenCV, half-pixel shifts, crop). Each
    blob's centroid in the undistorted image is where its keypoint must move, within 0.06 px: half a pixel of
    convention error or the crop's offset would be 0.5 px and more."""
    from nerfstudio.data.datamanagers.full_images_datamanager import _undistort_image

    distortion = torch.tensor([-0.12, 0.03, 0.0, 0.0, 0.002, -0.001])  # nerfstudio's [k1, k2, k3, k4, p1, p2]
    camera = _camera(150.0, 152.0, 101.3, 74.2, distortion=distortion)
    blobs = np.array([[30.3, 25.7], [160.6, 110.2], [100.0, 75.0], [175.4, 30.9]])
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    image = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    for x, y in blobs:
        image += np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2**2))[..., None]
    k = camera.get_intrinsics_matrices()[0].numpy().copy()
    new_k, undistorted_image, _ = _undistort_image(camera[0], distortion.numpy(), {}, image, k)
    height, width = undistorted_image.shape[:2]
    pinhole = _camera(float(new_k[0, 0]), float(new_k[1, 1]), float(new_k[0, 2]), float(new_k[1, 2]), width, height)
    index = torch.zeros(len(blobs), dtype=torch.long)
    moved = undistorted_pixels(
        torch.tensor(blobs), intrinsics_from_cameras(camera)[index], intrinsics_from_cameras(pinhole)[index]
    )
    assert float((moved - torch.tensor(blobs)).norm(dim=-1).max()) > 0.5  # the distortion moves them
    y_grid, x_grid = np.mgrid[0:height, 0:width] + 0.5
    for x, y in moved.tolist():
        weight = undistorted_image[..., 0] * ((np.abs(x_grid - x) < 5) & (np.abs(y_grid - y) < 5))
        centroid = ((weight * x_grid).sum() / weight.sum(), (weight * y_grid).sum() / weight.sum())
        assert centroid == pytest.approx((x, y), abs=0.06)


def test_the_evidence_keeps_its_points_and_cameras_and_moves_each_images_keypoints_with_its_own_cameras():
    distortion = torch.tensor([-0.12, 0.03, 0.0, 0.0, 0.0, 0.0])
    distorted = _camera(150.0, 150.0, 100.0, 75.0, distortion=distortion)
    two = intrinsics_from_cameras(distorted)[torch.tensor([0, 0])]
    undistorted = intrinsics_from_cameras(_camera(140.0, 140.0, 99.0, 74.0))[torch.tensor([0, 0])]
    undistorted.fx[1], undistorted.fy[1], undistorted.cx[1], undistorted.cy[1] = 145.0, 146.0, 98.0, 73.0
    pixels = torch.tensor([[20.0, 30.0], [150.0, 100.0], [60.0, 70.0]], dtype=torch.float64)
    tracks = Tracks(
        points=torch.rand(2, 3, dtype=torch.float64), image=torch.tensor([0, 1, 1]), point=torch.tensor([0, 1, 0]),
        pixels=pixels,
    )  # fmt: skip
    c2w = torch.eye(3, 4, dtype=torch.float64)[None].repeat(2, 1, 1)
    evidence = undistorted_track_evidence(TrackEvidence(tracks, c2w, 2.5), two, undistorted)
    assert evidence.c2w is c2w and evidence.world_scale == 2.5 and evidence.tracks.points is tracks.points
    assert torch.equal(evidence.tracks.image, tracks.image) and torch.equal(evidence.tracks.point, tracks.point)
    # Undistorted tangents by hand: r (1 + k1 r^2 + k2 r^4) = r_d, solved by bisection, for each pixel.
    for row, (u, v) in enumerate(pixels.tolist()):
        a_d, b_d = (u - 100.0) / 150.0, (v - 75.0) / 150.0
        r_d = (a_d**2 + b_d**2) ** 0.5
        low, high = 0.0, 2.0 * r_d
        for _ in range(200):
            r = 0.5 * (low + high)
            low, high = (r, high) if r * (1 - 0.12 * r**2 + 0.03 * r**4) < r_d else (low, r)
        a, b = a_d * r / r_d, b_d * r / r_d
        fx, fy, cx, cy = ((140.0, 140.0, 99.0, 74.0), (145.0, 146.0, 98.0, 73.0))[int(tracks.image[row])]
        expected = torch.tensor([fx * a + cx, fy * b + cy], dtype=torch.float64)
        torch.testing.assert_close(evidence.tracks.pixels[row], expected, atol=1e-6, rtol=0)
