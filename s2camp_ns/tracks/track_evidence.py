"""The track prior's evidence for a split's images, as the cameras are given (after any perturbation): each image's
reprojection RMS against its tracks (``metadata["track_rms_px"]``, ``core.tracks``) and the tracks with the cameras in
the tracks' world (``metadata["track_evidence"]``, ``core.track_fit.TrackEvidence``).

Sources, in order (``track_evidence``): the scene's own tracks (a COLMAP scene's points, or the model ns-process-data
leaves beside a transforms.json), checked by ``colmap_tracks.check_sfm_track_rms``; else, for the training split,
tracks made from the images (``image_track_evidence``). Perturbed cameras never get the scene's own tracks.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from rich.console import Console
from rich.markup import escape
from torch import Tensor

from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.tracks import track_reprojection_rms
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
from s2camp_ns.data.camera_fields import physical_camera_means
from s2camp_ns.data.colmap_files import model_file, read_model_file
from s2camp_ns.data.colmap_scene import has_points
from s2camp_ns.data.colmap_world import c2w_to_colmap_world
from s2camp_ns.data.colmap_writer import nerfstudio_to_reconstruction
from s2camp_ns.data.scene_config import SceneConfig
from s2camp_ns.data.scene_formats import ParsedSplit
from s2camp_ns.data.transforms_scene import transforms_declared_sizes
from s2camp_ns.tracks.colmap_tracks import check_sfm_track_rms, read_colmap_tracks
from s2camp_ns.tracks.image_tracks import image_tracks
from s2camp_ns.tracks.robust_adjustment import readjusted_tracks
from s2camp_ns.tracks.transforms_tracks import (
    colmap_model_of_transforms,
    full_size_images,
    image_folder_and_names,
    transforms_track_rms,
)

Evidence = tuple[Float[Tensor, " n"], TrackEvidence]
"""``track_rms_px`` (float64 [N], NaN for an image without tracks) and ``track_evidence``."""

IMAGE_TRACKS_CACHE = Path("s2camp_image_tracks")
"""The image tracks' default cache folder, in the scene folder (``track_cache``)."""
LOG = Console(stderr=True, width=120)
"""The data parser's notes (why a scene has no track prior), on stderr."""
_SHOWN: set[tuple] = set()
"""Keys of the notes already shown (the data parser runs once per split)."""
SFM_TRACKS_FALLBACK = "pass s2camp-data --image-tracks always (tracks made from the images) or --tracks False"
"""What to do instead, named when the scene's own model is refused (``check_sfm_track_rms``)."""


def _show_once(key: tuple, message: str) -> None:
    if key not in _SHOWN:
        _SHOWN.add(key)
        LOG.print(message)


def track_evidence(
    config: SceneConfig,
    data_format: str,
    source: Path,
    cameras: Cameras,
    outputs: DataparserOutputs,
    parsed: ParsedSplit,
    split: str,
    perturbed: bool,
    *,
    camera_ids: Int[Tensor, " n"],
) -> Evidence | None:
    """The evidence of the split's ``cameras`` (perturbed or not; ``outputs`` holds the unperturbed ones), or None (no
    track prior). ``camera_ids`` [N]: each image's physical camera, as the refiner groups them."""
    # The scene's own tracks were made with the unperturbed cameras: a prior on them would lead perturbed cameras
    # back to the reference the evaluation compares with.
    if perturbed and config.tracks:
        note_perturbed_tracks(config, source)
    evidence = None
    if config.tracks and config.image_tracks != "always" and not perturbed:
        evidence = scene_track_evidence(config, data_format, source, cameras, outputs, parsed)
    made = config.tracks and config.image_tracks != "never" and evidence is None
    if made and split == "train":  # only the training cameras are refined
        evidence = image_track_evidence(config, data_format, source, cameras, outputs, parsed, camera_ids)
    return evidence


def note_perturbed_tracks(config: SceneConfig, source: Path) -> None:
    """Say, once, which evidence the perturbed cameras' track prior gets (``track_evidence``)."""
    if config.image_tracks == "never":
        evidence = "no track prior (image_tracks never)"
    else:
        evidence = "tracks made from the images with the perturbed cameras (image_tracks)"
    _show_once(
        (source.resolve(), "perturbed-tracks"),
        f"[bold yellow]Perturbed cameras: the scene's own tracks were made with the unperturbed cameras and are "
        f"not used; the track prior gets {evidence}",
    )


def scene_track_evidence(
    config: SceneConfig,
    data_format: str,
    source: Path,
    cameras: Cameras,
    outputs: DataparserOutputs,
    parsed: ParsedSplit,
) -> Evidence | None:
    """The evidence of the scene's own tracks, or None; ValueError from ``check_sfm_track_rms``."""
    if data_format == "colmap":
        if not (config.load_3D_points and has_points(source)):
            return None
        images = None
        if config.refine_keypoints:
            full = Path(config.data) / config.images_path  # else the training images' folder, images_k
            k = parsed.downscale_factor
            images = keypoint_images(source, [full] + ([full.with_name(f"{full.name}_{k}")] if k > 1 else []))
        evidence = colmap_track_evidence(cameras, source, parsed.image_names, outputs, image_root=images)
        model = source
    else:
        evidence = transforms_track_evidence(config, source, cameras, outputs, parsed.downscale_factor)
        model = colmap_model_of_transforms(source, config.colmap_path)
    if evidence is not None:  # the scene's own tracks under its given cameras
        model_width = parsed.full_image_size[:, 0]
        rms = evidence[0]
        check_sfm_track_rms(rms, cameras.width, model_width, model_file(model, "images"), SFM_TRACKS_FALLBACK)
    return evidence


def keypoint_images(model: Path, folders: list[Path]) -> Path | None:
    """The first of ``folders`` that holds every registered image of the COLMAP model ``model`` (by name): the images
    its keypoints are refined against (``keypoint_refinement``, at whatever size they are there); None, said once,
    when none does, or None when there is no model (the caller says why)."""
    images_file = model_file(model, "images")
    if not images_file.is_file():
        return None
    names = [image.name for image in read_model_file(images_file, "images").values()]
    for folder in folders:
        if all((folder / name).is_file() for name in names):
            return folder
    missing = next(name for name in names if not (folders[0] / name).is_file())
    _show_once(
        (model.resolve(), "keypoint-images"),
        f"[bold yellow]Keypoints not refined: '{escape(str(folders[0] / missing))}' does not exist (nor do the images "
        f"of {model} in {', '.join(escape(str(folder)) for folder in folders[1:]) or 'another folder'})",
    )
    return None


def colmap_track_evidence(
    cameras: Cameras,
    model: Path,
    names: list[str],
    outputs: DataparserOutputs,
    readjust: bool = True,
    image_root: Path | None = None,
) -> Evidence:
    """Reprojection RMS (px, float64 [N]) of the COLMAP model's tracks under ``cameras`` (normalized; image i is the
    model's ``names[i]``), in COLMAP's world, against the model's own points; and the tracks with the cameras in that
    world, re-adjusted (``robust_adjustment``, keypoints refined against the images under ``image_root`` unless it is
    None) unless ``readjust`` is False (a model adjusted so already)."""
    # Keypoints from the model's camera size to the training images' (a rounded images_k folder included).
    size = torch.stack([cameras.width.reshape(-1), cameras.height.reshape(-1)], dim=-1)
    tracks = read_colmap_tracks(model, names, image_size=size)
    scale = float(outputs.dataparser_scale)
    c2w = c2w_to_colmap_world(cameras.camera_to_worlds, outputs.dataparser_transform, scale)
    rms = track_reprojection_rms(tracks, c2w, intrinsics_from_cameras(cameras))
    if readjust:
        tracks = read_colmap_tracks(model, names, image_size=size, adjusted=readjusted_tracks(model, image_root))
    return rms, TrackEvidence(tracks, c2w, scale)


def transforms_track_evidence(
    config: SceneConfig, source: Path, cameras: Cameras, outputs: DataparserOutputs, downscale_factor: int
) -> Evidence | None:
    """The evidence of a transforms.json scene from the COLMAP model beside it (``transforms_tracks``); None, with the
    reason shown once, when there is none."""
    model = colmap_model_of_transforms(source, config.colmap_path)
    k = downscale_factor
    sizes = transforms_declared_sizes(source, k)
    scale = float(outputs.dataparser_scale)
    result = transforms_track_rms(
        source, model, outputs.image_filenames, [sizes[os.path.normpath(p)] for p in outputs.image_filenames], k,
        config.images_path,
        c2w_given=c2w_to_colmap_world(cameras.camera_to_worlds, outputs.dataparser_transform, scale),
        c2w_reference=c2w_to_colmap_world(outputs.cameras.camera_to_worlds, outputs.dataparser_transform, scale),
        intrinsics=intrinsics_from_cameras(cameras), world_scale=scale,
        image_root=keypoint_images(model, [source.parent / config.images_path]) if config.refine_keypoints else None,
    )  # fmt: skip
    if result.rms is None or result.evidence is None:
        # A transforms.json that disagrees with its COLMAP model is a warning; a scene without one is normal.
        style = "bold yellow" if result.cause == "disagree" else "dim"
        _show_once((source.resolve(), result.cause), f"[{style}]No SfM tracks: {escape(result.reason)}")
        return None
    return result.rms, result.evidence


def image_track_evidence(
    config: SceneConfig,
    data_format: str,
    source: Path,
    cameras: Cameras,
    outputs: DataparserOutputs,
    parsed: ParsedSplit,
    camera_ids: Int[Tensor, " n"],
) -> Evidence | None:
    """The evidence of tracks made from the scene's full-size images with the given ``cameras`` (``image_tracks``),
    one COLMAP camera per ``camera_ids`` entry at its images' mean intrinsics; None, with the reason shown once, when
    none could be made."""
    if data_format == "colmap":
        scene = Path(config.data)
        root, names = scene / config.images_path, parsed.image_names
    else:
        scene = source.parent
        root, names = image_folder_and_names(full_size_images(source, outputs.image_filenames, parsed.downscale_factor))
    scale = float(outputs.dataparser_scale)
    given = nerfstudio_to_reconstruction(
        physical_camera_means(cameras, camera_ids), outputs.dataparser_transform, scale, names,
        full_image_size=parsed.full_image_size, camera_ids=camera_ids.tolist(),
    )  # fmt: skip
    cache = config.image_tracks_cache or scene / IMAGE_TRACKS_CACHE
    result = image_tracks(
        given, root, cache, user_fallback=config.image_tracks_cache is None, refine_keypoints=config.refine_keypoints
    )
    if result.model is None:
        _show_once((source.resolve(), "image-tracks"), f"[bold yellow]No track prior: {escape(result.reason)}")
        return None
    _show_once(
        (result.model, "summary"),
        f"[dim]Track prior from tracks made from the images of {root} ({result.model}): {escape(result.summary)}",
    )
    # Already adjusted with the robust loss (robust_adjustment.cauchy_adjustment_options): no second adjustment.
    return colmap_track_evidence(cameras, result.model, names, outputs, readjust=False)


__all__ = [
    "IMAGE_TRACKS_CACHE",
    "colmap_track_evidence",
    "image_track_evidence",
    "keypoint_images",
    "scene_track_evidence",
    "track_evidence",
    "transforms_track_evidence",
]
