"""A COLMAP reconstruction read back as arrays, to compare the models the export writes with their cameras."""

from __future__ import annotations

import numpy as np
import pycolmap

from s2camp_ns.core.colmap_camera_models import colmap_to_values
from s2camp_ns.data.colmap_writer import DISTORTION


def reconstruction_to_arrays(reconstruction: pycolmap.Reconstruction) -> dict[str, np.ndarray | list[str]]:
    """OpenCV c2w [N, 3, 4], names, models, and fx, fy, cx, cy, k1, k2, k3, k4, p1, p2 (``core.camera`` meaning),
    width, height of a reconstruction, by image id."""
    keys = ("names", "models", "c2w", "fx", "fy", "cx", "cy", *DISTORTION, "width", "height")
    out: dict[str, list] = {key: [] for key in keys}
    for image_id in sorted(reconstruction.images):
        image = reconstruction.images[image_id]
        camera = reconstruction.cameras[image.camera_id]
        w2c = image.cam_from_world().matrix()
        rotation = w2c[:, :3].T
        out["names"].append(image.name)
        out["c2w"].append(np.concatenate([rotation, (-rotation @ w2c[:, 3])[:, None]], axis=1))
        model = camera.model.name
        try:
            values = colmap_to_values(model, camera.params)
        except ValueError as error:
            raise ValueError(f"camera {image.camera_id}: {error}") from error
        out["models"].append(model)
        for key in ("fx", "fy", "cx", "cy", *DISTORTION):
            out[key].append(values[key])
        out["width"].append(camera.width)
        out["height"].append(camera.height)
    return {
        key: (value if key in ("names", "models") else np.asarray(value, dtype=np.float64))
        for key, value in out.items()
    }
