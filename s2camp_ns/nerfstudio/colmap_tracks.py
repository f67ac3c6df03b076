"""The SfM tracks of a COLMAP model, for ``core.tracks``: each training image's observations of the model's 3D points.

Points stay in COLMAP's world frame; the dataparser maps the training cameras back to that frame
(``colmap_world.c2w_to_colmap_world``) before measuring, so nerfstudio's normalization never touches the points.
Observed pixels are COLMAP's (full resolution, top-left pixel centre at (0.5, 0.5)) divided by the downscale factor
of the image folder the cameras describe. Observations without a 3D point (point3D_id -1) are not part of a track.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from s2camp_ns.core.tracks import Tracks
from s2camp_ns.nerfstudio.colmap_model import model_file, read_model_file


def read_colmap_tracks(model: Path, names: list[str], downscale_factor: int = 1) -> Tracks:
    """The tracks of COLMAP model folder ``model`` seen by the images ``names`` (image ``i`` of the result is
    ``names[i]``; a name the model lacks is a ValueError naming it and the images file)."""
    images_file = model_file(model, "images")
    images = {image.name: image for image in read_model_file(images_file, "images").values()}
    points3d = read_model_file(model_file(model, "points3D"), "points3D")
    return tracks_of_images(images, points3d, names, downscale_factor, images_file)


def tracks_of_images(
    images: dict, points3d: dict, names: list[str], downscale_factor: int, images_file: Path
) -> Tracks:
    """``read_colmap_tracks`` on a model already read: ``images`` by name, ``points3d`` by id (``images_file`` names
    the source in errors)."""
    ids = np.fromiter(points3d.keys(), dtype=np.int64, count=len(points3d))
    xyz = np.stack([points3d[int(i)].xyz for i in ids]) if len(ids) else np.zeros((0, 3))
    row_of = {int(point_id): row for row, point_id in enumerate(ids)}
    image_index, point_index, pixels = [], [], []
    for index, name in enumerate(names):
        image = images.get(name)
        if image is None:
            raise ValueError(f"{images_file} holds no image named '{name}' (a training image of the scene)")
        keep = [(row_of[int(p)], xy) for p, xy in zip(image.point3D_ids, image.xys, strict=True) if int(p) in row_of]
        image_index += [index] * len(keep)
        point_index += [row for row, _ in keep]
        pixels += [xy for _, xy in keep]
    return Tracks(
        points=torch.as_tensor(xyz, dtype=torch.float64),
        image=torch.as_tensor(image_index, dtype=torch.long),
        point=torch.as_tensor(point_index, dtype=torch.long),
        pixels=torch.as_tensor(np.asarray(pixels, dtype=np.float64).reshape(-1, 2)) / float(downscale_factor),
    )


__all__ = ["read_colmap_tracks", "tracks_of_images"]
