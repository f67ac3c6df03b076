"""The SfM tracks of an ``ns-process-data`` scene: a transforms.json beside the COLMAP model it was written from
(``COLMAP_MODEL_OF_TRANSFORMS``, or the data parser's ``colmap_path`` relative to the json's folder).

Frames: inverting nerfstudio's normalization (``colmap_world.c2w_to_colmap_world``) gives COLMAP's world when the json
has an ``applied_transform``; without one the world is COLMAP's own or ``LEGACY_APPLIED_ROTATION`` times it, the first
that passes the check, else unknown (no tracks). Images match by name, else by the frame's ``colmap_im_id``; a frame
COLMAP did not register gets NaN.

The check: each matched camera's centre as given (before any perturbation) within ``CENTRE_TOLERANCE`` of COLMAP's,
and each COLMAP camera's size the frame's ``w`` x ``h``; otherwise no tracks, with a reason naming both files.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch
from jaxtyping import Float
from nerfstudio.data.utils.colmap_parsing_utils import qvec2rotmat
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.tracks import Tracks, track_reprojection_rms
from s2camp_ns.data.colmap_files import model_file, read_model_file
from s2camp_ns.data.transforms_file import read_transforms
from s2camp_ns.tracks.colmap_tracks import pixel_scale_of, tracks_of_images
from s2camp_ns.tracks.robust_adjustment import readjusted_tracks

COLMAP_MODEL_OF_TRANSFORMS = Path("colmap/sparse/0")
"""Where ``ns-process-data`` writes the COLMAP model, relative to the transforms.json's folder."""
LEGACY_APPLIED_ROTATION = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
"""The world rotation (of COLMAP's) that nerfstudio assumes for a json without ``applied_transform``."""
CENTRE_TOLERANCE = 0.01
"""Largest distance between a camera's centre as given and COLMAP's, as a fraction of COLMAP's centres' spread."""


@dataclass(frozen=True)
class TransformsTracks:
    """Result of ``transforms_track_rms``: the per-image RMS (px, float64 [N], NaN for unregistered images) and the
    tracks with the given cameras in the model's world (``evidence``), or None, a one-word ``cause`` and ``reason``."""

    rms: Float[Tensor, " n"] | None
    cause: str | None = None
    reason: str | None = None
    evidence: TrackEvidence | None = None


def colmap_model_of_transforms(source: Path, colmap_path: Path | None = None) -> Path:
    """The COLMAP model folder that belongs to the transforms.json ``source`` (module docstring; may not exist)."""
    return source.parent / (colmap_path if colmap_path is not None else COLMAP_MODEL_OF_TRANSFORMS)


def _has_model(folder: Path) -> bool:
    return all(model_file(folder, kind).exists() for kind in ("cameras", "images", "points3D"))


def _frames_by_read_path(source: Path, downscale_factor: int) -> dict[str, tuple[str, dict]]:
    """Every frame of ``source`` and its full-size image path, by the path nerfstudio reads at ``downscale_factor``."""
    frames = read_transforms(source)["frames"]
    data_dir = source.parent
    by_read_path = {}
    for frame in frames:
        file_path = Path(frame["file_path"])
        full = os.path.normpath(data_dir / file_path)
        downscaled = data_dir / f"images_{downscale_factor}" / file_path.name
        read = full if downscale_factor == 1 else os.path.normpath(downscaled)
        by_read_path[read] = (full, frame)
    return by_read_path


def full_size_images(source: Path, image_filenames: list[Path], downscale_factor: int) -> list[Path]:
    """The full-size image of each image nerfstudio read from the transforms.json ``source``."""
    by_read_path = _frames_by_read_path(source, downscale_factor)
    missing = [path for path in image_filenames if os.path.normpath(path) not in by_read_path]
    if missing:
        raise ValueError(f"{source} lists no frame for image '{missing[0]}'")
    return [Path(by_read_path[os.path.normpath(path)][0]) for path in image_filenames]


def image_folder_and_names(paths: list[Path]) -> tuple[Path, list[str]]:
    """The deepest folder holding every one of ``paths`` (images a transforms.json lists) and each path's name under
    it (``/``-separated): how the image tracks and the export name a transforms.json scene's images."""
    root = Path(os.path.commonpath([path.parent for path in paths]))
    return root, [path.relative_to(root).as_posix() for path in paths]


def frame_names(
    source: Path, image_filenames: list[Path], downscale_factor: int, images_path: Path
) -> list[tuple[str, int | None] | None]:
    """Per image read from ``source``: its COLMAP name (relative to ``images_path``, else the file name) and the
    frame's ``colmap_im_id`` (or None); None for an image no frame lists."""
    image_folder = os.path.normpath(source.parent / images_path)
    name_of = {}
    for read, (full, frame) in _frames_by_read_path(source, downscale_factor).items():
        relative = Path(os.path.relpath(full, image_folder))
        name = Path(full).name if relative.parts[0] == ".." else relative.as_posix()
        image_id = frame.get("colmap_im_id")
        name_of[read] = (name, int(image_id) if isinstance(image_id, int) else None)
    return [name_of.get(os.path.normpath(path)) for path in image_filenames]


def _registered_name(frame: tuple[str, int | None] | None, images_by_id: dict, names: set[str]) -> str | None:
    """The COLMAP image name of a frame: by name, else by ``colmap_im_id``; None when the model has neither."""
    if frame is None:
        return None
    name, image_id = frame
    if name in names:
        return name
    return images_by_id[image_id].name if image_id in images_by_id else None


def _world_from_json(c2w: Float[Tensor, "n 3 4"], rotation: Float[Tensor, "3 3"]) -> Float[Tensor, "n 3 4"]:
    """Camera-to-world [n, 3, 4] (float64) in COLMAP's world; json world = ``rotation`` @ COLMAP world."""
    return rotation.T @ c2w.to(torch.float64)


def _colmap_centres(images: dict) -> dict[str, Tensor]:
    """COLMAP's camera centre -R^T t (float64 [3]) of every image, by name."""
    centres = {}
    for image in images.values():
        rotation = torch.tensor(qvec2rotmat(image.qvec), dtype=torch.float64)
        centres[image.name] = -rotation.T @ torch.tensor(image.tvec, dtype=torch.float64)
    return centres


def _disagreement(
    names: list[str],
    given_centres: Tensor,
    colmap_centres: dict[str, Tensor],
    sizes: list[tuple[int, int]],
    colmap_sizes: list[tuple[int, int]],
) -> str | None:
    """What makes the given cameras not COLMAP's (module docstring, the check), or None when they agree."""
    for name, size, colmap_size in zip(names, sizes, colmap_sizes, strict=True):
        if tuple(size) != tuple(colmap_size):
            return (
                f"image '{name}' is declared {size[0]}x{size[1]} but its COLMAP camera is "
                f"{colmap_size[0]}x{colmap_size[1]}"
            )
    every = torch.stack(list(colmap_centres.values()))
    spread = float((every - every.mean(dim=0)).square().sum(dim=-1).mean().sqrt())
    tolerance = CENTRE_TOLERANCE * spread
    distance = torch.linalg.norm(given_centres - torch.stack([colmap_centres[name] for name in names]), dim=-1)
    far = distance > tolerance
    if not bool(far.any()):
        return None
    worst = int(distance.argmax())
    return (
        f"{int(far.sum())} of {len(names)} cameras are not where COLMAP has them; the farthest, '{names[worst]}', is "
        f"{float(distance[worst]):.4g} from COLMAP's centre (tolerance {tolerance:.4g}: {CENTRE_TOLERANCE:g} of the "
        f"camera centres' spread {spread:.4g}, in COLMAP's units)"
    )


def transforms_track_rms(
    source: Path,
    model: Path,
    image_filenames: list[Path],
    declared_sizes: list[tuple[int, int]],
    downscale_factor: int,
    images_path: Path,
    c2w_given: Float[Tensor, "n 3 4"],
    c2w_reference: Float[Tensor, "n 3 4"],
    intrinsics: Intrinsics,
    world_scale: float = 1.0,
    image_root: Path | None = None,
) -> TransformsTracks:
    """Each image's track reprojection RMS for the transforms.json ``source`` against the COLMAP model ``model``.

    ``c2w_given``: the cameras to measure (after any perturbation); ``c2w_reference``: as the json gives them; both
    OpenCV camera-to-world [n, 3, 4] in the un-normalized world (``colmap_world.c2w_to_colmap_world``).
    ``declared_sizes``: full-size ``w``, ``h``; ``world_scale``: ``dataparser_scale``; ``image_root``: the model's
    images, its keypoints refined against them (``robust_adjustment``; None: not refined). ``rms`` None, with the
    reason, when the model is missing or the cameras fail the check (module docstring).
    """
    if not _has_model(model):
        return TransformsTracks(None, "no-model", f"no COLMAP model with points (cameras, images, points3D) in {model}")
    meta = read_transforms(source)
    if "applied_scale" in meta:
        reason = f"{source} has an applied_scale, which COLMAP's frame does not undo"
        return TransformsTracks(None, "applied-scale", reason)
    images_file = model_file(model, "images")
    images_by_id = read_model_file(images_file, "images")
    images = {image.name: image for image in images_by_id.values()}
    cameras = read_model_file(model_file(model, "cameras"), "cameras")
    frames = frame_names(source, image_filenames, downscale_factor, images_path)
    registered = set(images)
    names = [_registered_name(frame, images_by_id, registered) for frame in frames]
    matched = [i for i, name in enumerate(names) if name is not None]
    if not matched:
        return TransformsTracks(None, "unregistered", f"none of the images of {source} is registered in {images_file}")
    matched_names = [names[i] for i in matched]
    index = torch.tensor(matched, dtype=torch.long)
    colmap_centres = _colmap_centres(images)
    sizes = [declared_sizes[i] for i in matched]
    colmap_sizes = [(cameras[images[name].camera_id].width, cameras[images[name].camera_id].height)
                    for name in matched_names]  # fmt: skip
    # The candidate worlds of the json, as rotations of COLMAP's (module docstring, Frames).
    if "applied_transform" in meta:
        worlds = {"applied_transform": torch.eye(3, dtype=torch.float64)}  # already undone by nerfstudio
    else:
        worlds = {"colmap": torch.eye(3, dtype=torch.float64), "legacy": LEGACY_APPLIED_ROTATION}
    problems = {}
    for world, rotation in worlds.items():
        reference = _world_from_json(c2w_reference[index], rotation)
        problems[world] = _disagreement(matched_names, reference[:, :, 3], colmap_centres, sizes, colmap_sizes)
        if problems[world] is None:
            break
    else:
        if "applied_transform" not in meta:
            return TransformsTracks(
                None,
                "unknown-frame",
                f"{source} has no applied_transform and its cameras are in neither COLMAP's frame of {images_file} "
                f"({problems['colmap']}) nor nerfstudio's legacy one: the frame is unknown",
            )
        return TransformsTracks(
            None,
            "disagree",
            f"the cameras of {source} disagree with {images_file}: {problems['applied_transform']}; the "
            "transforms.json was edited or belongs to another reconstruction",
        )
    points3d = read_model_file(model_file(model, "points3D"), "points3D")
    # Keypoints into the training images' pixels by each image's per-axis ratio (colmap_tracks).
    scale = pixel_scale_of(intrinsics.width[index], intrinsics.height[index], colmap_sizes)
    tracks = tracks_of_images(images, points3d, matched_names, scale, images_file)
    rms = torch.full((len(names),), float("nan"), dtype=torch.float64)
    given = _world_from_json(c2w_given, rotation)
    rms[index] = track_reprojection_rms(tracks, given[index], intrinsics[index])
    # Tracks by training image for the anchor fit, points re-adjusted (robust_adjustment); the RMS above is a check.
    readjusted = readjusted_tracks(model, image_root)
    adjusted = tracks_of_images(images, points3d, matched_names, scale, images_file, readjusted)
    all_images = Tracks(adjusted.points, index[adjusted.image], adjusted.point, adjusted.pixels)
    return TransformsTracks(rms, evidence=TrackEvidence(all_images, given, world_scale))


__all__ = [
    "CENTRE_TOLERANCE",
    "COLMAP_MODEL_OF_TRANSFORMS",
    "TransformsTracks",
    "colmap_model_of_transforms",
    "frame_names",
    "full_size_images",
    "image_folder_and_names",
    "transforms_track_rms",
]
