"""The SfM tracks of a COLMAP model, for ``core.tracks``: each training image's observations of the model's 3D points.

Points stay in COLMAP's world; the data parser maps the training cameras back to it
(``colmap_world.c2w_to_colmap_world``). Keypoints are in the pixels of the model's cameras (top-left pixel centre at
(0.5, 0.5)) and are scaled to the training images by each image's per-axis size ratio, as the data parser scales the
intrinsics (``scene_formats.fit_intrinsics_to_images``), not by 1 / k: a rounded ``images_k`` folder would otherwise
disagree with the cameras by up to half a pixel. Observations without a 3D point (id -1) are dropped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.tracks import Tracks
from s2camp_ns.data.colmap_files import model_file, read_model_file
from s2camp_ns.tracks.robust_adjustment import ReadjustedTracks


def pixel_scale_of(
    width: Tensor, height: Tensor, model_size: Float[Tensor, "n 2"] | list[tuple[int, int]]
) -> Float[Tensor, "n 2"]:
    """Per-image (sx, sy) [n, 2] from the model's camera size (``model_size``: width, height) to the training size
    (``width``, ``height``): the factor from COLMAP's keypoints to the training pixels."""
    size = torch.as_tensor(model_size, dtype=torch.float64).reshape(-1, 2)
    trained = torch.stack([width.reshape(-1).double().cpu(), height.reshape(-1).double().cpu()], dim=-1)
    if trained.shape != size.shape:
        n, m = trained.shape[0], size.shape[0]
        raise ValueError(f"model_size must hold one (width, height) per camera ({n}), got {m}")
    if bool((size <= 0).any()):
        raise ValueError(f"model_size must be positive pixel sizes, got minimum {float(size.min()):g}")
    return trained / size


MAX_SFM_TRACK_RMS_PX = 10.0
"""Largest median over a model's images of each image's reprojection RMS against its own tracks (px of the model's
cameras): above COLMAP's 4 px filter, far below keypoints and cameras at different scales."""


def check_sfm_track_rms(
    rms_px: Float[Tensor, " n"], width: Tensor, model_width: Tensor, images_file: Path, fallback: str
) -> None:
    """ValueError (naming ``images_file`` and ``fallback``, how to train without the tracks) when the median of
    ``rms_px`` (at the training ``width``, NaN: no tracks) exceeds ``MAX_SFM_TRACK_RMS_PX`` at ``model_width``."""
    rms = torch.as_tensor(rms_px, dtype=torch.float64).reshape(-1)
    to_model = torch.as_tensor(model_width, dtype=torch.float64).reshape(-1) / width.reshape(-1).double().cpu()
    at_model = (rms.cpu() * to_model)[torch.isfinite(rms.cpu())]
    if at_model.numel() == 0:
        return
    median, worst = float(at_model.median()), float(at_model.max())
    if median <= MAX_SFM_TRACK_RMS_PX:
        return
    raise ValueError(
        f"{images_file}: the model's own cameras miss their tracks by {median:.4g} px (median over "
        f"{at_model.numel()} images; worst {worst:.4g} px, in the pixels of the model's cameras), far more than SfM "
        f"leaves (at most {MAX_SFM_TRACK_RMS_PX:g} px): check that the keypoints and the cameras are at the same "
        f"scale (a cameras file rescaled by hand after resizing the images keeps the keypoints at the old size) and "
        f"that images.bin belongs to these cameras; to train without this model's tracks, {fallback}"
    )


def read_colmap_tracks(
    model: Path,
    names: list[str],
    image_size: Float[Tensor, "n 2"] | None = None,
    adjusted: ReadjustedTracks | None = None,
) -> Tracks:
    """The tracks of the COLMAP model folder ``model`` seen by the images ``names`` (image i is ``names[i]``; a missing
    name is a ValueError). ``image_size`` [n, 2]: scale keypoints to these sizes (None: the model's pixels).
    ``adjusted``: point positions and keypoints in place of the model's (``robust_adjustment``)."""
    images_file = model_file(model, "images")
    images = {image.name: image for image in read_model_file(images_file, "images").values()}
    points3d = read_model_file(model_file(model, "points3D"), "points3D")
    scale: Tensor | float = 1.0
    if image_size is not None:
        cameras = read_model_file(model_file(model, "cameras"), "cameras")
        missing = [name for name in names if name not in images]
        if missing:
            raise ValueError(f"{images_file} holds no image named '{missing[0]}' (a training image of the scene)")
        sizes = [(cameras[images[name].camera_id].width, cameras[images[name].camera_id].height) for name in names]
        size = torch.as_tensor(image_size, dtype=torch.float64).reshape(-1, 2)
        scale = pixel_scale_of(size[:, 0], size[:, 1], sizes)
    return tracks_of_images(images, points3d, names, scale, images_file, adjusted)


def tracks_of_images(
    images: dict,
    points3d: dict,
    names: list[str],
    pixel_scale: Float[Tensor, "n 2"] | float,
    images_file: Path,
    adjusted: ReadjustedTracks | None = None,
) -> Tracks:
    """``read_colmap_tracks`` on a model already read: ``images`` by name, ``points3d`` by id, ``pixel_scale`` [n, 2]
    or scalar; ``images_file`` names the source in errors; ``adjusted`` as ``read_colmap_tracks``'s."""
    scale = torch.as_tensor(pixel_scale, dtype=torch.float64)
    scale = scale.expand(len(names), 2) if scale.ndim == 0 else scale.reshape(-1, 2)
    if scale.shape[0] != len(names):
        raise ValueError(f"pixel_scale must hold one (sx, sy) per image ({len(names)}), got {scale.shape[0]}")
    ids = np.fromiter(points3d.keys(), dtype=np.int64, count=len(points3d))
    positions = {int(i): points3d[int(i)].xyz for i in ids} if adjusted is None else adjusted.points
    keypoints = {} if adjusted is None else adjusted.keypoints
    xyz = np.stack([positions[int(i)] for i in ids]) if len(ids) else np.zeros((0, 3))
    row_of = {int(point_id): row for row, point_id in enumerate(ids)}
    image_index, point_index, pixels = [], [], []
    for index, name in enumerate(names):
        image = images.get(name)
        if image is None:
            raise ValueError(f"{images_file} holds no image named '{name}' (a training image of the scene)")
        xys = keypoints.get(image.id, image.xys)
        keep = [(row_of[int(p)], xy) for p, xy in zip(image.point3D_ids, xys, strict=True) if int(p) in row_of]
        image_index += [index] * len(keep)
        point_index += [row for row, _ in keep]
        pixels += [xy for _, xy in keep]
    image = torch.as_tensor(image_index, dtype=torch.long)
    observed = torch.as_tensor(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))  # [O, 2] in the model's pixels
    return Tracks(
        points=torch.as_tensor(xyz, dtype=torch.float64),
        image=image,
        point=torch.as_tensor(point_index, dtype=torch.long),
        pixels=observed * scale[image],
    )


__all__ = ["MAX_SFM_TRACK_RMS_PX", "check_sfm_track_rms", "pixel_scale_of", "read_colmap_tracks", "tracks_of_images"]
