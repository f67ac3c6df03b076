"""``s2camp-make-scene``: write a small synthetic scene in the mip-NeRF 360 layout with known cameras.

Output (``output_dir``)::

    images/            full-resolution images (PNG by default)
    images_2/          the same images at half resolution (exact 2x2 box downsample)
    sparse/0/          COLMAP model written by pycolmap: cameras.bin, images.bin, points3D.bin
    scene_info.json    ground-truth cameras and the generator config

Rays go through the COLMAP camera model itself (``cam_from_img``): the images agree exactly with the written
intrinsics. Every 3D point is a visible surface point tracked in every image that sees it unoccluded.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap
import torch
import tyro
from PIL import Image as PILImage

from s2camp_bench.scene import procedural
from s2camp_ns import __version__
from s2camp_ns.core.camera import CAMERA_MODEL_PROJECTION, Intrinsics, pixel_to_ray_direction
from s2camp_ns.core.colmap_camera_models import SUPPORTED_COLMAP_MODELS, values_to_colmap
from s2camp_ns.core.distortion import check_distortion_monotonic
from s2camp_ns.core.validation import check_choice, check_range

FOV_PRESETS = {"narrow": 52.0, "wide": 80.0}
"""Horizontal field of view in degrees ("narrow": mip-NeRF 360's room)."""

_OUTPUTS = ("images", "images_2", "sparse", "poses_bounds.npy", "scene_info.json")
"""What a scene folder may hold from an earlier generation (poses_bounds.npy: written by earlier versions)."""

CameraModelName = Literal[
    "auto", "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"
]
FISHEYE_MAX_ANGLE = 85.0
"""Largest angle (degrees) off the axis of a generated fisheye image: pycolmap's unprojection stops at 90."""
_COEFFICIENTS = ("k1", "k2", "k3", "k4", "p1", "p2")
"""The distortion coefficients of ``MakeSceneConfig``."""


@dataclass
class MakeSceneConfig:
    """Synthetic mip-NeRF 360-style scene: a ring of cameras around textured objects on a ground plane."""

    output_dir: Path = Path("scenes/synthetic")
    """Where to write the scene (an existing directory only if empty or holding a generated scene)."""
    num_cameras: int = 24
    """Number of images (cameras on a ring looking at the centre)."""
    width: int = 160
    """Full-resolution image width in pixels (even: images_2 is an exact 2x2 downsample)."""
    height: int = 120
    """Full-resolution image height in pixels (even)."""
    fov: Literal["narrow", "wide"] = "narrow"
    """Field-of-view preset used when ``focal`` is not given: narrow = 52 deg horizontal, wide = 80 deg."""
    focal: float | None = None
    """Focal length in full-resolution pixels (fx = fy); overrides ``fov``."""
    principal_point: tuple[float, float] | None = None
    """(cx, cy) in full-resolution pixels; default: the image centre."""
    k1: float = -0.02
    """Radial distortion k1 (normalized image coordinates); k1 = k2 = 0 writes a PINHOLE camera."""
    k2: float = 0.005
    """Radial distortion k2."""
    camera_model: CameraModelName = "auto"
    """COLMAP camera model; auto = RADIAL, or PINHOLE when k1 = k2 = 0. Coefficients the model lacks must be 0;
    OPENCV_FISHEYE takes the focal length from ``fov`` as an equidistant lens (theta = r / f)."""
    k3: float = 0.0
    """Radial k3 (FULL_OPENCV's r^6 term, OPENCV_FISHEYE's theta^7 term)."""
    k4: float = 0.0
    """OPENCV_FISHEYE's k4 (theta^9 term)."""
    p1: float = 0.0
    """Tangential p1 (OPENCV, FULL_OPENCV)."""
    p2: float = 0.0
    """Tangential p2 (OPENCV, FULL_OPENCV)."""
    ring_radius: float = 4.0
    """Distance of the cameras from the vertical axis through the scene centre."""
    ring_height: float = 1.3
    """Mean camera height above the ground plane."""
    height_jitter: float = 0.25
    """Camera heights vary uniformly by +- this much (seeded), so the centres are not coplanar."""
    supersample: int = 2
    """Ray samples per pixel along each axis (box-filtered), against aliasing of the fine textures."""
    points_per_image: int = 200
    """Candidate 3D points sampled from each image's visible surfaces (kept if seen by >= 2 images)."""
    seed: int = 0
    """Seed for camera jitter, texture noise and point sampling."""
    image_format: Literal["png", "jpg"] = "png"
    """Image file format (JPG as the real dataset's files)."""


def validate(config: MakeSceneConfig) -> tuple[float, float, float]:
    """Check the config; return (focal, cx, cy) in full-resolution pixels."""
    for name in ("num_cameras", "width", "height", "supersample", "points_per_image", "seed"):
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{name} must be an integer, got {value!r}")
    check_range("num_cameras", config.num_cameras, low=2)
    for name in ("width", "height"):
        value = getattr(config, name)
        check_range(name, value, low=8, high=8192)
        if value % 2:
            raise ValueError(f"{name} must be even (images_2 is an exact 2x2 downsample), got {value}")
    check_choice("fov", config.fov, tuple(FOV_PRESETS))
    check_choice("image_format", config.image_format, ("png", "jpg"))
    check_choice("camera_model", config.camera_model, ("auto", *SUPPORTED_COLMAP_MODELS))
    fisheye = config.camera_model == "OPENCV_FISHEYE"
    if config.focal is None and fisheye:
        focal = 0.5 * config.width / (math.radians(FOV_PRESETS[config.fov]) / 2.0)
    elif config.focal is None:
        focal = 0.5 * config.width / math.tan(math.radians(FOV_PRESETS[config.fov]) / 2.0)
    else:
        check_range("focal", config.focal, low=0.0, low_inclusive=False)
        focal = float(config.focal)
    cx, cy = (config.width / 2.0, config.height / 2.0) if config.principal_point is None else config.principal_point
    check_range("principal_point[0] (cx)", cx, low=0.0, high=config.width, low_inclusive=False, high_inclusive=False)
    check_range("principal_point[1] (cy)", cy, low=0.0, high=config.height, low_inclusive=False, high_inclusive=False)
    for name in _COEFFICIENTS:
        check_range(name, getattr(config, name), low=-1.0, high=1.0)
    # The camera model's rule: the distortion must not fold back inside the image.
    pinhole = dict(fx=focal, fy=focal, cx=cx, cy=cy, width=config.width, height=config.height)
    coefficients = {name: getattr(config, name) for name in _COEFFICIENTS}
    model = "fisheye" if fisheye else "perspective"
    intrinsics = Intrinsics.create(**pinhole, **coefficients, model=model, validate=False)
    check_distortion_monotonic(intrinsics)
    if fisheye:
        corners = np.array([[0.0, 0.0], [config.width, 0.0], [0.0, config.height], [config.width, config.height]])
        z = pixel_to_ray_direction(torch.as_tensor(corners)[None], intrinsics)[0, :, 2]
        widest = math.degrees(math.acos(float(z.min())))
        check_range("fisheye corner angle (degrees; lower the fov or raise the focal)", widest, high=FISHEYE_MAX_ANGLE)
    check_range(
        "ring_radius", config.ring_radius, low=procedural.SCENE_RADIUS + 0.7, high=procedural.BACKGROUND_RADIUS / 4
    )
    check_range("ring_height", config.ring_height, low=0.2, high=procedural.BACKGROUND_RADIUS / 4)
    check_range("height_jitter", config.height_jitter, low=0.0, high=0.5 * config.ring_height)
    check_range("supersample", config.supersample, low=1, high=8)
    check_range("points_per_image", config.points_per_image, low=1)
    check_range("seed", config.seed, low=0)
    return focal, float(cx), float(cy)


def make_camera(config: MakeSceneConfig) -> pycolmap.Camera:
    """The shared full-resolution COLMAP camera (``camera_model``; auto: RADIAL with distortion, else PINHOLE)."""
    focal, cx, cy = validate(config)
    model = config.camera_model
    if model == "auto":
        model = "PINHOLE" if config.k1 == 0.0 and config.k2 == 0.0 else "RADIAL"
    values = dict(fx=focal, fy=focal, cx=cx, cy=cy, **{n: getattr(config, n) for n in _COEFFICIENTS})
    params = values_to_colmap(model, values, CAMERA_MODEL_PROJECTION[model])
    return pycolmap.Camera(model=model, width=config.width, height=config.height, params=params, camera_id=1)


def ring_poses(config: MakeSceneConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """World-to-camera 3x4 matrices (OpenCV axes: x right, y down, z forward) on a jittered ring."""
    n = config.num_cameras
    azimuths = 2.0 * np.pi * (np.arange(n) + rng.uniform(-0.25, 0.25, n)) / n
    heights = config.ring_height + rng.uniform(-config.height_jitter, config.height_jitter, n)
    poses = []
    for azimuth, height in zip(azimuths, heights, strict=True):
        centre = np.array([config.ring_radius * np.cos(azimuth), config.ring_radius * np.sin(azimuth), height])
        target = procedural.LOOK_AT + rng.uniform(-0.1, 0.1, 3)
        forward = (target - centre) / np.linalg.norm(target - centre)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])  # rows: camera axes in world coordinates
        poses.append(np.concatenate([rotation, -(rotation @ centre)[:, None]], axis=1))
    return poses


def _pixel_rays(
    camera: pycolmap.Camera, cam_from_world: np.ndarray, pixels: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World-frame origins and unit directions of the rays through continuous pixel positions [M, 2]."""
    normalized = camera.cam_from_img(pixels)
    if not np.isfinite(normalized).all():
        raise RuntimeError("pycolmap could not unproject some pixels; the distortion is too strong")
    directions = np.concatenate([normalized, np.ones((len(normalized), 1))], axis=1)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    rotation, translation = cam_from_world[:, :3], cam_from_world[:, 3]
    centre = -rotation.T @ translation
    return np.broadcast_to(centre, directions.shape), directions @ rotation


def render_image(config: MakeSceneConfig, camera: pycolmap.Camera, cam_from_world: np.ndarray) -> np.ndarray:
    """Full-resolution float image [H, W, 3] in [0, 1], box-filtered over supersample x supersample rays."""
    s, w, h = config.supersample, config.width, config.height
    u = (np.arange(w * s) + 0.5) / s
    v = (np.arange(h * s) + 0.5) / s
    pixels = np.stack(np.meshgrid(u, v, indexing="xy"), axis=-1).reshape(-1, 2)
    origins, directions = _pixel_rays(camera, cam_from_world, pixels)
    colour, _ = procedural.trace(origins, directions, config.seed)
    return colour.reshape(h, s, w, s, 3).mean(axis=(1, 3))


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)


def _save(image: np.ndarray, path: Path, image_format: str) -> None:
    if image_format == "jpg":
        PILImage.fromarray(_to_uint8(image)).save(path, quality=95)
    else:
        PILImage.fromarray(_to_uint8(image)).save(path)


def sample_points(
    config: MakeSceneConfig, camera: pycolmap.Camera, poses: list[np.ndarray], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, list[list[tuple[int, np.ndarray]]]]:
    """Visible surface points seen by >= 2 images: xyz [P, 3], rgb uint8 [P, 3] and per point its track, a list of
    (image index, observed pixel [2]). RuntimeError if an image sees none of them."""
    candidates, surfaces = [], []
    for pose in poses:
        pixels = rng.uniform([0.0, 0.0], [config.width, config.height], (config.points_per_image, 2))
        origins, directions = _pixel_rays(camera, pose, pixels)
        hits = procedural.intersect(origins, directions)
        candidates.append(hits.points(origins, directions))
        surfaces.append(hits)
    xyz = np.concatenate(candidates)
    observations: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(len(xyz))]
    for index, pose in enumerate(poses):
        rotation, translation = pose[:, :3], pose[:, 3]
        centre = -rotation.T @ translation
        in_camera = xyz @ rotation.T + translation
        pixels = camera.img_from_cam(in_camera)  # NaN behind the camera
        inside = (in_camera[:, 2] > 1e-6) & np.isfinite(pixels).all(axis=1)
        inside &= (pixels[:, 0] >= 0.0) & (pixels[:, 0] < config.width)
        inside &= (pixels[:, 1] >= 0.0) & (pixels[:, 1] < config.height)
        candidates_idx = np.flatnonzero(inside)
        offsets = xyz[candidates_idx] - centre
        distance = np.linalg.norm(offsets, axis=1)
        first = procedural.intersect(np.broadcast_to(centre, offsets.shape), offsets / distance[:, None]).t
        visible = first >= distance * (1.0 - 1e-6) - 1e-6
        for point in candidates_idx[visible]:
            observations[point].append((index, pixels[point]))
    keep = np.array([i for i, obs in enumerate(observations) if len(obs) >= 2], dtype=np.int64)
    seen = {index for i in keep for index, _ in observations[i]}
    if len(seen) < len(poses):
        raise RuntimeError(f"image {min(set(range(len(poses))) - seen)} sees no 3D point; raise points_per_image")
    hits = procedural.Hits(
        *(np.concatenate([getattr(h, f) for h in surfaces])[keep] for f in ("t", "material", "normal"))
    )
    rgb = _to_uint8(procedural.shade(xyz[keep], hits, config.seed))
    return xyz[keep], rgb, [observations[i] for i in keep]


def _prepare_output(output_dir: Path) -> None:
    if output_dir.exists():
        if not output_dir.is_dir():
            raise ValueError(f"output_dir must be a directory, got the file {output_dir}")
        if any(output_dir.iterdir()) and not (output_dir / "scene_info.json").exists():
            raise ValueError(
                f"output_dir {output_dir} is not empty and holds no generated scene (no scene_info.json); "
                "allowed: a new or empty directory, or one written by s2camp-make-scene"
            )
        for name in _OUTPUTS:
            target = output_dir / name
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
    for sub in ("images", "images_2", "sparse/0"):
        (output_dir / sub).mkdir(parents=True, exist_ok=True)


def config_record(config: MakeSceneConfig) -> dict:
    """``config`` as ``scene_info.json`` records it (paths as strings, tuples as JSON lists)."""
    record = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(config).items()}
    return json.loads(json.dumps(record))


def _write_images(
    config: MakeSceneConfig, camera: pycolmap.Camera, names: list[str], poses: list[np.ndarray], output_dir: Path,
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Render each image at its pose into ``images/`` and its 2x2 box-averaged half into ``images_2/``;
    ``progress(done, total)`` after each image."""
    for done, (name, pose) in enumerate(zip(names, poses, strict=True), start=1):
        image = render_image(config, camera, pose)
        _save(image, output_dir / "images" / name, config.image_format)
        half = image.reshape(config.height // 2, 2, config.width // 2, 2, 3).mean(axis=(1, 3))
        _save(half, output_dir / "images_2" / name, config.image_format)
        if progress is not None:
            progress(done, len(names))


def _write_sparse(
    camera: pycolmap.Camera, names: list[str], poses: list[np.ndarray], xyz: np.ndarray, rgb: np.ndarray,
    tracks: list[list[tuple[int, np.ndarray]]], output_dir: Path,
) -> None:
    """The binary COLMAP model (cameras, images with keypoints, points3D with tracks) in ``sparse/0``, image ids 1..n
    in ``names`` order."""
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(camera)
    keypoints: list[list[np.ndarray]] = [[] for _ in poses]
    elements: list[list[tuple[int, int]]] = []
    for track in tracks:
        elements.append([])
        for index, pixel in track:
            elements[-1].append((index + 1, len(keypoints[index])))
            keypoints[index].append(pixel)
    for index, (name, pose) in enumerate(zip(names, poses, strict=True)):
        image = pycolmap.Image(
            name=name, keypoints=np.asarray(keypoints[index], dtype=np.float64).reshape(-1, 2),
            camera_id=camera.camera_id, image_id=index + 1,
        )
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pose))
    for point, colour, track in zip(xyz, rgb, elements, strict=True):
        track_elements = [pycolmap.TrackElement(image_id, point2d) for image_id, point2d in track]
        reconstruction.add_point3D(point, pycolmap.Track(track_elements), colour)
    sparse = output_dir / "sparse" / "0"
    reconstruction.write_binary(sparse)
    for extra in ("rigs.bin", "frames.bin"):  # newer COLMAP extras; the mip-NeRF 360 layout has three files
        (sparse / extra).unlink(missing_ok=True)


def _scene_info(
    config: MakeSceneConfig, camera: pycolmap.Camera, names: list[str], poses: list[np.ndarray], num_points: int
) -> dict:
    """The ``scene_info.json`` record: generator, config, camera (COLMAP model and parameters, pinhole and distortion
    values), images and their world-to-camera poses (COLMAP's pixel convention: pixel (i, j) centred at (i + 0.5,
    j + 0.5))."""
    coefficients = {name: getattr(config, name) for name in _COEFFICIENTS}
    pinhole = dict(fx=camera.focal_length_x, fy=camera.focal_length_y, cx=camera.principal_point_x,
                   cy=camera.principal_point_y)  # fmt: skip
    images = [{"image_id": i + 1, "name": name, "cam_from_world": pose.tolist()} for i, (name, pose) in
              enumerate(zip(names, poses, strict=True))]  # fmt: skip
    return {
        "generator": "s2camp_bench.scene.make_scene", "version": __version__, "config": config_record(config),
        "camera": {"model": camera.model.name, "width": camera.width, "height": camera.height,
                   "params": camera.params.tolist(), **pinhole, **coefficients},
        "images": images, "num_points3D": num_points,
    }  # fmt: skip


def make_scene(config: MakeSceneConfig, progress: Callable[[int, int], None] | None = None) -> Path:
    """Generate the scene of ``config`` and return its directory; ``progress(done, total)`` after each image."""
    camera = make_camera(config)
    output_dir = Path(config.output_dir)
    _prepare_output(output_dir)
    rng = np.random.default_rng(config.seed)
    poses = ring_poses(config, rng)
    suffix = "png" if config.image_format == "png" else "jpg"
    names = [f"frame_{i:05d}.{suffix}" for i in range(config.num_cameras)]
    _write_images(config, camera, names, poses, output_dir, progress)
    xyz, rgb, tracks = sample_points(config, camera, poses, rng)
    _write_sparse(camera, names, poses, xyz, rgb, tracks, output_dir)
    info = _scene_info(config, camera, names, poses, len(xyz))
    (output_dir / "scene_info.json").write_text(json.dumps(info, indent=2) + "\n")
    return output_dir


def entrypoint() -> None:
    """Console script ``s2camp-make-scene``."""
    config = tyro.cli(MakeSceneConfig)
    start = time.perf_counter()
    try:
        output_dir = make_scene(config, lambda done, total: print(f"rendered {done}/{total}", end="\r", flush=True))
    except ValueError as error:
        raise SystemExit(f"s2camp-make-scene: {error}") from None
    info = json.loads((output_dir / "scene_info.json").read_text())
    print(
        f"wrote {output_dir}: {config.num_cameras} images {config.width}x{config.height} (+ images_2), "
        f"{info['camera']['model']} camera {info['camera']['params']}, {info['num_points3D']} 3D points "
        f"in {time.perf_counter() - start:.1f} s"
    )


if __name__ == "__main__":
    entrypoint()
