"""Export with intrinsics shared per physical camera: one COLMAP camera per physical camera, read back by pycolmap."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from colmap_arrays import reconstruction_to_arrays

from s2camp_ns.data.colmap_writer import cameras_to_reconstruction


def _poses(n: int) -> np.ndarray:
    c2w = np.zeros((n, 3, 4))
    for i in range(n):
        angle = 2.0 * np.pi * i / n
        c2w[i, :, :3] = [[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]]
        c2w[i, :, 3] = [4.0 * np.sin(angle), 0.5, -4.0 * np.cos(angle)]
    return c2w


def test_images_of_one_physical_camera_share_one_colmap_camera(tmp_path) -> None:
    fx = [300.0, 410.0, 300.0, 410.0, 300.0]
    reconstruction = cameras_to_reconstruction(
        _poses(5), fx=fx, fy=fx, cx=160.0, cy=120.0, width=320, height=240, image_names=[f"{i}.png" for i in range(5)],
        k1=[-0.01, 0.02, -0.01, 0.02, -0.01], camera_ids=[4, 9, 4, 9, 4],
    )  # fmt: skip
    reconstruction.write_binary(str(tmp_path))
    loaded = pycolmap.Reconstruction(str(tmp_path))
    assert loaded.num_cameras() == 2 and loaded.num_images() == 5
    camera_of = {image.name: image.camera_id for image in loaded.images.values()}
    assert camera_of["0.png"] == camera_of["2.png"] == camera_of["4.png"] != camera_of["1.png"] == camera_of["3.png"]
    arrays = reconstruction_to_arrays(loaded)
    assert arrays["fx"].tolist() == pytest.approx(fx) and arrays["k1"][1] == pytest.approx(0.02)


def test_shared_cameras_must_agree() -> None:
    with pytest.raises(ValueError, match=r"image 2 \(2.png\) shares physical camera 0 but its fx is 301"):
        cameras_to_reconstruction(
            _poses(3), fx=[300.0, 300.0, 301.0], fy=300.0, cx=160.0, cy=120.0, width=320, height=240,
            image_names=["0.png", "1.png", "2.png"], camera_ids=[0, 0, 0],
        )  # fmt: skip
