"""nerfstudio cameras to a COLMAP reconstruction (pycolmap): the model ``s2camp-export-cameras`` writes
(``nerfstudio_to_reconstruction``: nerfstudio's normalization undone, OpenGL axes flipped to OpenCV) and the one the
image tracks are made with. Distortion is written in COLMAP's meaning (``core.colmap_camera_models``); nerfstudio's
perspective k4 (r^8) has no COLMAP counterpart and is refused; skew is dropped.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap
import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from s2camp_ns.core.colmap_camera_models import colmap_model_for, values_to_colmap
from s2camp_ns.core.tracks import Tracks, index_in_image
from s2camp_ns.data.camera_conversion import projection_of
from s2camp_ns.data.colmap_world import c2w_to_colmap_world

CameraModel = Literal["auto", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"]
CAMERA_MODELS: tuple[str, ...] = ("auto", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def _as_numpy(name: str, value, n: int) -> np.ndarray:
    array = np.asarray(value.detach().cpu().double() if isinstance(value, Tensor) else value, dtype=np.float64)
    array = np.broadcast_to(array.reshape(-1) if array.size == n else array, (n,)).copy()
    if not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite, got {array[~np.isfinite(array)][0]}")
    return array


def cameras_to_reconstruction(
    c2w_opencv: Float[Tensor, "n 3 4"] | np.ndarray,
    fx,
    fy,
    cx,
    cy,
    width,
    height,
    image_names: list[str],
    k1=0.0,
    k2=0.0,
    camera_model: CameraModel = "auto",
    points_xyz: np.ndarray | None = None,
    points_rgb: np.ndarray | None = None,
    k3=0.0,
    k4=0.0,
    p1=0.0,
    p2=0.0,
    projection: str = "perspective",
    camera_ids: Sequence[int] | None = None,
    tracks: Tracks | None = None,
) -> pycolmap.Reconstruction:
    """COLMAP reconstruction from OpenCV camera-to-world poses [N, 3, 4] and intrinsics (px; scalars or length N):
    one COLMAP camera per distinct ``camera_ids`` entry (their images' intrinsics must agree), or per image when None.
    ``tracks`` (pixels in these cameras) become the images' keypoints and points with their tracks (black: see
    ``Reconstruction.extract_colors_for_all_images``); else ``points_xyz`` are added without tracks.

    Distortion means what it means in ``core.camera`` for ``projection`` ("perspective" or "fisheye"). ``camera_model``
    auto picks the simplest model that holds every camera: OPENCV_FISHEYE for fisheye, else RADIAL, OPENCV or
    FULL_OPENCV. Raises ValueError for invalid input.
    """
    c2w = _checked_poses(c2w_opencv, image_names)
    n = c2w.shape[0]
    given = dict(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, k1=k1, k2=k2, k3=k3, k4=k4, p1=p1, p2=p2)
    per_camera = _checked_intrinsics(given, n)
    camera_model = _resolved_model(camera_model, per_camera, projection)
    groups = list(range(n)) if camera_ids is None else [int(c) for c in camera_ids]
    if len(groups) != n:
        raise ValueError(f"camera_ids must have {n} entries (one per image), got {len(groups)}")
    reconstruction = pycolmap.Reconstruction()
    keypoints = None if tracks is None else _keypoints(tracks, n)
    _add_cameras_and_images(reconstruction, c2w, per_camera, groups, image_names, camera_model, projection, keypoints)
    if tracks is not None:
        _add_tracks(reconstruction, tracks, n)
    elif points_xyz is not None:
        _add_points(reconstruction, points_xyz, points_rgb)
    return reconstruction


def _keypoints(tracks: Tracks, n: int) -> list[np.ndarray]:
    """Per image [m_i, 2], its observations' pixels in observation order (keypoint j of image i: its j-th,
    ``core.tracks.index_in_image``)."""
    tracks.validate(n)
    image = tracks.image.cpu().numpy()
    pixels = tracks.pixels.detach().cpu().double().numpy()[np.argsort(image, kind="stable")]
    return np.split(pixels, np.cumsum(np.bincount(image, minlength=n))[:-1])


def _add_tracks(reconstruction: pycolmap.Reconstruction, tracks: Tracks, n: int) -> None:
    """Points 1.. in ``tracks.points`` order, each with its observations as track elements (image i + 1, its keypoint
    index ``core.tracks.index_in_image``, as ``_keypoints`` placed it)."""
    image = tracks.image.cpu().long()
    keypoint = index_in_image(image, n)[0].numpy()
    image, point = image.numpy(), tracks.point.cpu().numpy()
    order = np.argsort(point, kind="stable")
    starts = np.searchsorted(point[order], np.arange(tracks.points.shape[0] + 1))
    xyz = tracks.points.detach().cpu().double().numpy()
    black = np.zeros(3, dtype=np.uint8)
    for index in range(xyz.shape[0]):
        rows = order[starts[index] : starts[index + 1]]
        elements = [pycolmap.TrackElement(int(image[r]) + 1, int(keypoint[r])) for r in rows]
        reconstruction.add_point3D(xyz[index], pycolmap.Track(elements), black)


def _checked_poses(c2w_opencv: Float[Tensor, "n 3 4"] | np.ndarray, image_names: list[str]) -> np.ndarray:
    """``c2w_opencv`` as float64 numpy [N, 3, 4]; ValueError unless ``image_names`` holds N unique names."""
    c2w = np.asarray(
        c2w_opencv.detach().cpu().double() if isinstance(c2w_opencv, Tensor) else c2w_opencv, dtype=np.float64
    )
    if c2w.ndim != 3 or c2w.shape[1:] != (3, 4):
        raise ValueError(f"c2w_opencv must have shape [N, 3, 4], got {c2w.shape}")
    n = c2w.shape[0]
    if len(image_names) != n:
        raise ValueError(f"image_names must have {n} entries (one per camera), got {len(image_names)}")
    first: dict[str, int] = {}
    for i, name in enumerate(image_names):
        if name in first:
            raise ValueError(f"image_names must be unique: '{name}' names images {first[name]} and {i}")
        first[name] = i
    return c2w


def _checked_intrinsics(given: dict, n: int) -> list[dict[str, float]]:
    """Per image, ``given``'s values (scalars or length ``n``) as floats; ValueError unless finite and fx, fy, width,
    height positive."""
    values = {name: _as_numpy(name, v, n) for name, v in given.items()}
    for name in ("fx", "fy", "width", "height"):
        if (values[name] <= 0).any():
            raise ValueError(f"{name} must lie in (0, inf), got {values[name][values[name] <= 0][0]:g}")
    return [{name: float(array[i]) for name, array in values.items()} for i in range(n)]


def _resolved_model(camera_model: str, per_camera: list[dict[str, float]], projection: str) -> str:
    """``camera_model``, checked, or for "auto" the simplest COLMAP model that holds every camera."""
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {', '.join(map(repr, CAMERA_MODELS))}, got {camera_model!r}")
    if camera_model == "auto":
        order = ("RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
        camera_model = max((colmap_model_for(v, projection) for v in per_camera), key=order.index)
    return camera_model


def _add_cameras_and_images(
    reconstruction: pycolmap.Reconstruction,
    c2w: np.ndarray,
    per_camera: list[dict[str, float]],
    groups: list[int],
    image_names: list[str],
    camera_model: str,
    projection: str,
    keypoints: list[np.ndarray] | None = None,
) -> None:
    """One COLMAP camera per distinct ``groups`` entry (ids 1.. in first-seen order; its images' intrinsics must
    agree, else ValueError) and image i + 1 posed by ``c2w[i]``, with ``keypoints[i]``."""
    n = len(per_camera)
    colmap_id: dict[int, int] = {}
    for i in range(n):
        v = per_camera[i]
        if groups[i] in colmap_id:
            first = per_camera[next(j for j in range(n) if groups[j] == groups[i])]
            differs = [name for name in v if not math.isclose(v[name], first[name], rel_tol=1e-6, abs_tol=1e-9)]
            if differs:
                raise ValueError(
                    f"image {i} ({image_names[i]}) shares physical camera {groups[i]} but its {differs[0]} is "
                    f"{v[differs[0]]:.8g}, not {first[differs[0]]:.8g}: shared intrinsics must agree"
                )
        else:
            colmap_id[groups[i]] = len(colmap_id) + 1
            try:
                params = values_to_colmap(camera_model, v, projection)
            except ValueError as error:
                raise ValueError(f"camera_model {camera_model}: camera {i} ({image_names[i]}): {error}") from error
            camera = pycolmap.Camera(
                model=camera_model,
                width=round(v["width"]),
                height=round(v["height"]),
                params=params,
                camera_id=colmap_id[groups[i]],
            )
            reconstruction.add_camera_with_trivial_rig(camera)
        points2d = np.zeros((0, 2)) if keypoints is None else keypoints[i]
        image = pycolmap.Image(name=image_names[i], keypoints=points2d, camera_id=colmap_id[groups[i]], image_id=i + 1)
        reconstruction.add_image_with_trivial_frame(image, _cam_from_world(c2w[i], i, image_names[i]))


def _cam_from_world(c2w: np.ndarray, i: int, name: str) -> pycolmap.Rigid3d:
    """COLMAP's world-to-camera of the OpenCV camera-to-world [3, 4] of camera ``i`` (image ``name``)."""
    rotation = c2w[:, :3]
    if abs(np.linalg.det(rotation) - 1.0) > 1e-4:
        raise ValueError(
            f"camera {i} ({name}) has a rotation with det {np.linalg.det(rotation):.6g}, "
            "expected a proper rotation (det 1)"
        )
    # Re-orthonormalize: nerfstudio's float32 poses are slightly off, and COLMAP stores quaternions.
    u, _, vt = np.linalg.svd(rotation)
    rotation = u @ vt
    world_from_cam_t = c2w[:, 3]
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation.T), -rotation.T @ world_from_cam_t)


def _add_points(reconstruction: pycolmap.Reconstruction, points_xyz: np.ndarray, points_rgb: np.ndarray | None) -> None:
    """Sparse points (xyz [M, 3], rgb [M, 3] or black) without tracks."""
    xyz = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.zeros_like(xyz, dtype=np.uint8) if points_rgb is None else np.asarray(points_rgb, dtype=np.uint8)
    for point, colour in zip(xyz, rgb.reshape(-1, 3), strict=True):
        reconstruction.add_point3D(point, pycolmap.Track(), colour)


def _column(tensor: Tensor | None, n: int, index: int | None = None) -> np.ndarray:
    if tensor is None:
        return np.zeros(n)
    array = tensor.detach().cpu().double().numpy()
    return (array[:, index] if index is not None else array.reshape(n, -1)[:, 0]).astype(np.float64)


def nerfstudio_to_reconstruction(
    cameras: Cameras,
    dataparser_transform: Tensor,
    dataparser_scale: float,
    image_names: list[str],
    full_image_size: Tensor | None = None,
    points_xyz: np.ndarray | None = None,
    points_rgb: np.ndarray | None = None,
    camera_model: CameraModel = "auto",
    camera_ids: Sequence[int] | None = None,
    tracks: Tracks | None = None,
) -> pycolmap.Reconstruction:
    """The COLMAP reconstruction of (refined) training cameras with nerfstudio's normalization undone (one COLMAP
    camera per ``camera_ids`` entry, or per image); intrinsics rescaled to ``full_image_size`` [N, 2] (w, h) if given.
    ``tracks``: in COLMAP's world, pixels in the cameras' images (rescaled with them)."""
    cameras = cameras.to("cpu")
    n = cameras.shape[0]
    c2w = c2w_to_colmap_world(cameras.camera_to_worlds, dataparser_transform, dataparser_scale)
    width, height = _column(cameras.width, n), _column(cameras.height, n)
    sx, sy = np.ones(n), np.ones(n)
    if full_image_size is not None:
        full = np.asarray(full_image_size, dtype=np.float64).reshape(n, 2)
        sx, sy = full[:, 0] / width, full[:, 1] / height
        width, height = full[:, 0], full[:, 1]
    if tracks is not None:
        image = tracks.image.cpu().long()
        scale = torch.from_numpy(np.stack([sx, sy], axis=-1))[image]  # [o, 2]
        tracks = dataclasses.replace(tracks, pixels=tracks.pixels.detach().cpu().double() * scale)
    # nerfstudio's [k1, k2, k3, k4, p1, p2] are core.camera's coefficients for both projections.
    distortion = {name: _column(cameras.distortion_params, n, i) for i, name in enumerate(DISTORTION)}
    return cameras_to_reconstruction(
        c2w, fx=_column(cameras.fx, n) * sx, fy=_column(cameras.fy, n) * sy, cx=_column(cameras.cx, n) * sx,
        cy=_column(cameras.cy, n) * sy, width=width, height=height, image_names=image_names, camera_model=camera_model,
        points_xyz=points_xyz, points_rgb=points_rgb, projection=projection_of(cameras), camera_ids=camera_ids,
        tracks=tracks, **distortion,
    )  # fmt: skip


def read_points(model_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """xyz [M, 3] and rgb [M, 3] of a COLMAP model's sparse points."""
    reconstruction = pycolmap.Reconstruction(str(model_path))
    ids = sorted(reconstruction.points3D)
    xyz = np.array([reconstruction.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([reconstruction.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    return xyz, rgb


__all__ = [
    "CAMERA_MODELS",
    "CameraModel",
    "cameras_to_reconstruction",
    "nerfstudio_to_reconstruction",
    "read_points",
]
