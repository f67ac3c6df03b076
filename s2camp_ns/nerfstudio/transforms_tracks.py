"""The SfM tracks of an ``ns-process-data`` scene: a transforms.json beside the COLMAP model it was written from.

``ns-process-data`` runs COLMAP on ``<dir>/images`` and converts ``<dir>/colmap/sparse/0`` into
``<dir>/transforms.json`` (nerfstudio's ``colmap_to_json``). The model stays there, with its tracks; this module
finds it, matches its images to the scene's frames by name and checks that the transforms.json cameras are the
model's before the data parser measures each camera's track reprojection error (``core.tracks``) for the camera
optimizer's track prior.

Where the model is: ``<folder of the transforms.json>/colmap/sparse/0`` (``COLMAP_MODEL_OF_TRANSFORMS``), where
``ns-process-data`` writes it and where nerfstudio's own transforms.json parser looks for it (its ``colmap_path``);
the data parser's ``colmap_path`` option, relative to that folder, overrides it. It must hold cameras, images and
points3D (binary or text).

Frames. ``colmap_to_json`` writes each camera as ``A @ c2w`` with ``c2w`` COLMAP's camera-to-world, its camera axes
flipped to OpenGL (y and z columns negated), and ``A = applied_transform`` (rows x, z, -y of COLMAP's world: z up),
stored in the json. nerfstudio's transforms.json parser composes ``A`` into its normalization: its
``dataparser_transform`` is ``transform_matrix @ A``, so inverting the normalization (``dataparser_transform`` and
``dataparser_scale``, ``colmap_world.c2w_to_colmap_world``) gives COLMAP's world directly (the S2CamP data parser
hands nerfstudio the json file itself, so nerfstudio's guess for a json without ``applied_transform``, which it makes
only when ``colmap/sparse/0`` lies under the path it was given, never applies). Without ``applied_transform`` the
same inversion gives the json's own world. Two worlds are known for such files: COLMAP's own
(``--keep-original-world-coordinate``) and ``LEGACY_APPLIED_ROTATION`` times it (ns-process-data before it recorded
``applied_transform``); the first that passes the centre check below is used, and if neither does (a hand-made json)
the frame is unknown and there are no tracks.

Images are matched by name: a frame's image relative to the image folder (``images/frame_00001.png`` ->
``frame_00001.png``, COLMAP's image name; with a downscale factor nerfstudio reads ``images_k/<file name>``, which is
mapped back to its frame), else by the frame's ``colmap_im_id`` (``colmap_to_json`` writes it; ns-process-data
renames the frames when it reuses a model made on the original file names). A frame that COLMAP did not register
gets NaN (no prior for that camera). The centre check below guards both against a json of another model.

The check (``CENTRE_TOLERANCE``): every matched camera's centre as given, before any perturbation, mapped to
COLMAP's world, must lie within 1% of the spread of COLMAP's camera centres (their RMS distance to their centroid,
over every registered image) of the centre COLMAP has for that image, and the COLMAP camera's size must be the
frame's declared ``w`` x ``h``. The json round trip (float64 text, float32 in nerfstudio) keeps centres within about
1e-6 of the spread; a transforms.json that was edited (a camera moved) or belongs to another reconstruction misses
by far more. Then the scene gets no tracks, with a reason naming both files: a prior measured against the wrong
cameras would pin them to the wrong place.
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
from s2camp_ns.nerfstudio.colmap_model import model_file, read_model_file
from s2camp_ns.nerfstudio.colmap_tracks import pixel_scale_of, tracks_of_images
from s2camp_ns.nerfstudio.robust_adjustment import robustly_adjusted_points
from s2camp_ns.nerfstudio.transforms_file import read_transforms

COLMAP_MODEL_OF_TRANSFORMS = Path("colmap/sparse/0")
"""Where ``ns-process-data`` writes the COLMAP model, relative to the transforms.json's folder."""

LEGACY_APPLIED_ROTATION = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
"""The world rotation of transforms.json files written by ns-process-data before it recorded ``applied_transform``
(nerfstudio's transforms.json parser assumes it for such files when ``colmap/sparse/0`` exists)."""

CENTRE_TOLERANCE = 0.01
"""Largest distance between a camera's centre as given and COLMAP's, as a fraction of the RMS distance of COLMAP's
camera centres to their centroid."""


@dataclass(frozen=True)
class TransformsTracks:
    """Result of ``transforms_track_rms``: the per-camera RMS (px, float64 [N], NaN for unregistered images) and the
    tracks with the given cameras in the model's world (``evidence``: the track prior's anchor, ``core.track_fit``),
    or None and why there are no tracks (``cause``: one word per kind of reason, ``reason``: the message)."""

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
    """Every frame of the transforms.json ``source`` by the image path nerfstudio reads for it at ``downscale_factor``
    (``images_k/<file name>`` beside the json for k > 1), with its full-size image path."""
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


def frame_names(
    source: Path, image_filenames: list[Path], downscale_factor: int, images_path: Path
) -> list[tuple[str, int | None] | None]:
    """For each image nerfstudio read from ``source``: its COLMAP image name (the frame's image relative to the data
    folder's ``images_path``, else its file name) and the frame's ``colmap_im_id`` (None if absent); None for an
    image no frame lists."""
    image_folder = os.path.normpath(source.parent / images_path)
    name_of = {}
    for read, (full, frame) in _frames_by_read_path(source, downscale_factor).items():
        relative = Path(os.path.relpath(full, image_folder))
        name = Path(full).name if relative.parts[0] == ".." else relative.as_posix()
        image_id = frame.get("colmap_im_id")
        name_of[read] = (name, int(image_id) if isinstance(image_id, int) else None)
    return [name_of.get(os.path.normpath(path)) for path in image_filenames]


def _registered_name(frame: tuple[str, int | None] | None, images_by_id: dict, names: set[str]) -> str | None:
    """The COLMAP image of a frame: by name, else by the ``colmap_im_id`` that ns-process-data writes (its frames
    are renamed when it reuses a model, ``--skip-colmap``); None when the model has neither."""
    if frame is None:
        return None
    name, image_id = frame
    if name in names:
        return name
    return images_by_id[image_id].name if image_id in images_by_id else None


def _world_from_json(c2w: Float[Tensor, "n 3 4"], rotation: Float[Tensor, "3 3"]) -> Float[Tensor, "n 3 4"]:
    """Camera-to-world [n, 3, 4] (float64) in COLMAP's world of cameras given in a world that is ``rotation`` times
    COLMAP's (json world = rotation @ COLMAP world)."""
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
) -> TransformsTracks:
    """Each camera's track reprojection RMS for the transforms.json ``source`` against the COLMAP model ``model``.

    ``c2w_given`` are the cameras to measure (after any perturbation) and ``c2w_reference`` the same cameras as the
    json gives them, both OpenCV camera-to-world in the world nerfstudio's normalization came from
    (``colmap_world.c2w_to_colmap_world``); ``declared_sizes`` are the frames' full-size ``w``, ``h``; ``world_scale``
    the training frame's units per unit of that world (``dataparser_scale``). No tracks
    (``rms`` None, with the reason) when the model or its points are missing, the json has no ``applied_transform``
    and its cameras are not COLMAP's, or the cameras disagree with the model (module docstring).
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
    # The candidate worlds of the json, as rotations of COLMAP's (module docstring, "Frames").
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
    # Keypoints into the training images' pixels by each image's per-axis ratio (colmap_tracks module docstring).
    scale = pixel_scale_of(intrinsics.width[index], intrinsics.height[index], colmap_sizes)
    tracks = tracks_of_images(images, points3d, matched_names, scale, images_file)
    rms = torch.full((len(names),), float("nan"), dtype=torch.float64)
    given = _world_from_json(c2w_given, rotation)
    rms[index] = track_reprojection_rms(tracks, given[index], intrinsics[index])
    # The same tracks indexed by training image (not by registered image) for the anchor fit, their points
    # re-adjusted with a robust loss (robust_adjustment); the RMS above is against the model's own, as a check.
    adjusted = tracks_of_images(images, points3d, matched_names, scale, images_file, robustly_adjusted_points(model))
    all_images = Tracks(adjusted.points, index[adjusted.image], adjusted.point, adjusted.pixels)
    return TransformsTracks(rms, evidence=TrackEvidence(all_images, given, world_scale))


__all__ = [
    "CENTRE_TOLERANCE",
    "COLMAP_MODEL_OF_TRANSFORMS",
    "TransformsTracks",
    "colmap_model_of_transforms",
    "frame_names",
    "full_size_images",
    "transforms_track_rms",
]
