"""Tracks made from a scene's own images, for scenes that carry none (phone exports, hand-made or converted
transforms.json files), so that the track prior anchors their cameras as it anchors SfM's (``core.track_fit``).

Without tracks the photometric loss alone determines a camera's focal length to 1-3 px of 114 in the regime real runs
train in, from every start (docs/DESIGN-NOTES.md sec. 15), and a camera's focal length and forward motion trade
against each other. Keypoint tracks determine both: on the regime scene (49 training images of 320x240) the adjustment
below ends 0.07 degrees and 0.4 px (of 228) from the true cameras, from the phone-pose start and from the true cameras
alike, closer than pycolmap's own SfM (0.115 degrees, 0.8 px; docs/DESIGN-NOTES.md sec. 16).

The recipe (pycolmap, on the CPU; COLMAP's log in ``colmap.log`` of the cache folder):

1. SIFT features of the full-size images (longest side at most ``MAX_IMAGE_SIZE``), one COLMAP camera per physical
   camera holding the given intrinsics.
2. Matches, geometrically verified, between every pair of images up to ``EXHAUSTIVE_LIMIT`` images, else between each
   image and its ``NEIGHBOURS`` nearest given camera centres among the cameras that look within 90 degrees of it.
3. Points triangulated with the given cameras (COLMAP's point triangulator with its default filters, which drop
   observations more than 4 px off), then ``REFINEMENT_ROUNDS`` rounds of a bundle adjustment of points, poses,
   focal lengths and distortion (the principal point stays) followed by a new triangulation with the adjusted
   cameras, and a last bundle adjustment: the points are those of the adjusted cameras.
4. A similarity (Umeyama on the camera centres, ``core.alignment``) maps the adjusted reconstruction onto the given
   cameras: images do not fix the world's position, orientation and scale, so the tracks keep the given ones.

The result is a COLMAP model (cameras, images, points3D) in the world of the given cameras. The track prior reads its
points and observations like those of an SfM model and measures each camera against them (``fit_anchor``): the
adjusted cameras become the anchor, each image's reprojection RMS its radius.

Cache. The model is built once per set of images and given cameras, in ``<cache>/<key>``: the key hashes the recipe
(``RECIPE_VERSION``, pycolmap's version), each image's name, size and modification time and the given cameras
(intrinsics and poses, every bit). Later runs read it (COLMAP's matcher verifies pairs on several threads, so two
builds can differ in their last digits; every run of one cache reads the same tracks). A build writes into a temporary
sibling folder and renames it at the end, so processes that build at once never read half a model, and nothing in
the cache is ever overwritten. The feature database is deleted once the model is written.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import torch

from s2camp_ns.colmap_log import colmap_log_to
from s2camp_ns.core.alignment import MIN_CAMERAS_FOR_ALIGNMENT, rotation_angle, umeyama
from s2camp_ns.core.track_fit import MIN_OBSERVATIONS

RECIPE_VERSION = 2
"""Part of the cache key: raise it when the recipe changes, so older caches are not read."""
MAX_IMAGE_SIZE = 1600
"""Longest image side SIFT sees (px; larger images are downsampled for extraction, keypoints are in full-size
pixels): phone photos of 4000 px hold 6x its pixels, keypoints the track prior does not need."""
EXHAUSTIVE_LIMIT = 100
"""Up to this many images every pair is matched (4950 pairs); beyond it, each image with its ``NEIGHBOURS``."""
NEIGHBOURS = 30
"""Images matched with each image beyond ``EXHAUSTIVE_LIMIT``: its nearest given camera centres among the cameras
whose optical axes are within 90 degrees of its own."""
REFINEMENT_ROUNDS = 3
"""Rounds of bundle adjustment and re-triangulation. On the regime scene, from cameras 0.94 degrees and 4.6 px (2%)
off, the rotation error after each round was 0.079, 0.072, 0.072 degrees and stayed there for three more; the first
triangulation keeps observations up to COLMAP's 4 px of the wrong cameras, the later ones refit the tracks to the
adjusted cameras (4846 points, then 3553)."""
LOSS_SCALE_PX = 1.0
"""Scale (px) of the bundle adjustment's Cauchy loss: residuals beyond it count less than squared, so a few wrong
matches do not pull the cameras. Against plain least squares, measured (24 images of 240x180 and the regime scene
of 56 images of 320x240, from noisy and from true cameras): rotation errors 0.28-0.30 against 0.52-0.56 degrees and
0.07 against 0.13-0.16, focal length errors no larger."""
COLMAP_SEED = 0
"""COLMAP's random seed (RANSAC of the geometric verification)."""
RESULT_FILE = "result.json"
"""Written last into a cache folder: the summary, or why no tracks could be made."""
MIN_TRACKED_FRACTION = 0.5
"""Fraction of the images that must see at least ``MIN_OBSERVATIONS`` tracked points (the least the anchor fit uses,
``core.track_fit``) for the tracks to be used. Below it the bundle adjustment rests on a handful of points and moves
cameras anywhere: 16 images of 160x120 gave 14 points, and the adjustment turned a camera by 62 degrees and halved
the focal length."""
MAX_ROTATION_CHANGE_DEG = 10.0
"""Largest median rotation (degrees) between the adjusted and the given cameras. Phone poses are off by about a degree
and SfM's by a tenth; beyond ten the images and the given cameras describe different scenes (or the matches are
wrong), and neither can anchor the other."""
MAX_CENTRE_CHANGE = 0.25
"""Largest median distance between the adjusted and the given camera centres after the similarity, as a fraction of
the given centres' spread (RMS distance to their centroid); the phone-pose start: 2%."""


@dataclass(frozen=True)
class ImageTracks:
    """The model folder of ``image_tracks`` (None when no tracks could be made, with ``reason``) and a one-line summary
    of what it holds."""

    model: Path | None
    summary: str = ""
    reason: str | None = None


def cache_key(given: pycolmap.Reconstruction, image_root: Path) -> str:
    """The cache folder name of ``given``'s images in ``image_root`` (module docstring, Cache)."""
    images = sorted(given.images.values(), key=lambda image: image.name)
    record = {
        "recipe": RECIPE_VERSION,
        "pycolmap": pycolmap.__version__,
        "images": [],
        "cameras": [
            [camera_id, camera.model.name, camera.width, camera.height, [float(v) for v in camera.params]]
            for camera_id, camera in sorted(given.cameras.items())
        ],
    }
    for image in images:
        stat = (image_root / image.name).stat()
        pose = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        record["images"].append([image.name, stat.st_size, stat.st_mtime_ns, image.camera_id, pose.ravel().tolist()])
    return hashlib.sha256(json.dumps(record).encode("utf8")).hexdigest()[:20]


def image_tracks(given: pycolmap.Reconstruction, image_root: Path, cache: Path) -> ImageTracks:
    """Tracks of the images of ``given`` (names relative to ``image_root``, the given cameras and poses; no points),
    from the cache folder ``cache`` or built there (module docstring)."""
    missing = sorted(image.name for image in given.images.values() if not (image_root / image.name).is_file())
    if missing:
        raise FileNotFoundError(
            f"image '{image_root / missing[0]}' does not exist ({len(missing)} of {given.num_images()} images "
            "missing): tracks are made from the full-size images"
        )
    if given.num_images() < MIN_CAMERAS_FOR_ALIGNMENT:
        reason = f"{given.num_images()} images: tracks need at least {MIN_CAMERAS_FOR_ALIGNMENT}"
        return ImageTracks(None, reason=reason)
    final = cache / cache_key(given, image_root)
    if (final / RESULT_FILE).is_file():
        return _cached(final)
    try:
        cache.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".building", dir=cache))
    except OSError as error:
        raise OSError(
            f"cannot write the image tracks' cache folder {cache} ({error}); choose a writable one with the data "
            "parser's --image-tracks-cache (ns-train s2camp --data D s2camp-data --image-tracks-cache DIR)"
        ) from error
    try:
        reconstruction, reason = _build(given, image_root, work)
        result = {"reason": reason}
        if reason is None:
            result["summary"] = _summary(given, reconstruction)
            reconstruction.write_binary(work)
        (work / RESULT_FILE).write_text(json.dumps(result), encoding="utf8")
        (work / "database.db").unlink(missing_ok=True)
        shutil.rmtree(work / "triangulated", ignore_errors=True)
        try:
            os.rename(work, final)
        except OSError:  # another process finished the same build first: keep its folder
            if not (final / RESULT_FILE).is_file():
                raise
            shutil.rmtree(work)
        return _cached(final)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise


def _cached(folder: Path) -> ImageTracks:
    """The ``ImageTracks`` of a finished cache folder: its model, or why there is none (a failed build is cached too,
    so that every run does not repeat it)."""
    result = json.loads((folder / RESULT_FILE).read_text(encoding="utf8"))
    if result["reason"] is not None:
        return ImageTracks(None, reason=f"{result['reason']} (COLMAP's log: {folder / 'colmap.log'})")
    return ImageTracks(folder, result["summary"])


def _build(given: pycolmap.Reconstruction, image_root: Path, work: Path) -> tuple[pycolmap.Reconstruction, str | None]:
    """The adjusted, aligned reconstruction (module docstring, steps 1-4) and why it cannot anchor the cameras (None
    when it can)."""
    database = work / "database.db"
    log = work / "colmap.log"
    pycolmap.set_random_seed(COLMAP_SEED)
    by_camera: dict[int, list[str]] = {}
    for image in sorted(given.images.values(), key=lambda image: image.name):
        by_camera.setdefault(image.camera_id, []).append(image.name)
    extraction = pycolmap.FeatureExtractionOptions(max_image_size=MAX_IMAGE_SIZE)
    with colmap_log_to(log):
        for camera_id, names in sorted(by_camera.items()):
            camera = given.cameras[camera_id]
            reader = pycolmap.ImageReaderOptions(
                camera_model=camera.model.name, camera_params=",".join(repr(float(v)) for v in camera.params)
            )
            pycolmap.extract_features(
                database, image_root, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
            )  # fmt: skip
        if given.num_images() <= EXHAUSTIVE_LIMIT:
            pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        else:
            pairs = work / "pairs.txt"
            pairs.write_text("".join(f"{a} {b}\n" for a, b in neighbour_pairs(given)), encoding="utf8")
            pycolmap.match_image_pairs(
                database, pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs),
                device=pycolmap.Device.cpu,
            )  # fmt: skip
    reconstruction = _given_with_database_ids(given, database)
    unread = sorted(
        {image.name for image in given.images.values()} - {image.name for image in reconstruction.images.values()}
    )
    if unread:  # COLMAP skips an image it cannot decode; every training image must be in the model
        return (
            reconstruction,
            f"COLMAP could not read {len(unread)} of {given.num_images()} images (first: '{unread[0]}')",
        )
    adjustment = pycolmap.BundleAdjustmentOptions(refine_principal_point=False)
    adjustment.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    adjustment.ceres.loss_function_scale = LOSS_SCALE_PX
    with colmap_log_to(log):
        reconstruction = pycolmap.triangulate_points(reconstruction, database, image_root, work / "triangulated")
        for _ in range(REFINEMENT_ROUNDS):
            if reconstruction.num_points3D() == 0:
                break
            pycolmap.bundle_adjustment(reconstruction, adjustment)
            reconstruction = pycolmap.triangulate_points(reconstruction, database, image_root, work / "triangulated")
        if reconstruction.num_points3D() > 0:
            pycolmap.bundle_adjustment(reconstruction, adjustment)
    if reconstruction.num_points3D() == 0:
        return reconstruction, "no point could be triangulated from the images' matched features"
    _align_to_given(reconstruction, given)
    return reconstruction, _implausible(given, reconstruction)


def _implausible(given: pycolmap.Reconstruction, reconstruction: pycolmap.Reconstruction) -> str | None:
    """Why the adjusted ``reconstruction`` cannot anchor the given cameras (too few tracks, or cameras moved beyond
    ``MAX_ROTATION_CHANGE_DEG`` / ``MAX_CENTRE_CHANGE``), or None when it can."""
    tracked = sum(image.num_points3D >= MIN_OBSERVATIONS for image in reconstruction.images.values())
    if tracked < MIN_TRACKED_FRACTION * reconstruction.num_images():
        return (
            f"only {tracked} of {reconstruction.num_images()} images see at least {MIN_OBSERVATIONS} tracked points "
            f"({reconstruction.num_points3D()} points in all); at least {MIN_TRACKED_FRACTION:.0%} must"
        )
    turned, moved = _camera_changes(given, reconstruction)
    if float(turned.median()) > MAX_ROTATION_CHANGE_DEG:
        return (
            f"the images' tracks turn the cameras by {float(turned.median()):.1f} degrees (median) from the given "
            f"ones, more than {MAX_ROTATION_CHANGE_DEG:g}: the images and the cameras disagree"
        )
    if float(moved.median()) > MAX_CENTRE_CHANGE:
        return (
            f"the images' tracks move the camera centres by {float(moved.median()):.0%} of their spread (median) from "
            f"the given ones, more than {MAX_CENTRE_CHANGE:.0%}: the images and the cameras disagree"
        )
    return None


def _given_with_database_ids(given: pycolmap.Reconstruction, database: Path) -> pycolmap.Reconstruction:
    """``given``'s cameras and poses under the camera, rig, frame and image ids the feature extractor gave them in
    ``database`` (COLMAP's triangulator matches the two by id)."""
    db = pycolmap.Database.open(database)
    try:
        stored = {image.name: image for image in db.read_all_images()}
    finally:
        db.close()
    given_by_name = {image.name: image for image in given.images.values()}
    reconstruction = pycolmap.Reconstruction()
    added: set[int] = set()
    for name, stored_image in sorted(stored.items(), key=lambda item: item[1].image_id):
        image = given_by_name[name]
        if stored_image.camera_id not in added:
            camera = copy.copy(given.cameras[image.camera_id])
            camera.camera_id = stored_image.camera_id
            reconstruction.add_camera_with_trivial_rig(camera)
            added.add(stored_image.camera_id)
        posed = pycolmap.Image(name=name, camera_id=stored_image.camera_id, image_id=stored_image.image_id)
        reconstruction.add_image_with_trivial_frame(posed, image.cam_from_world())
    return reconstruction


def neighbour_pairs(given: pycolmap.Reconstruction) -> list[tuple[str, str]]:
    """Image pairs to match beyond ``EXHAUSTIVE_LIMIT`` images: each image with its ``NEIGHBOURS`` nearest camera
    centres among the cameras whose optical axes are within 90 degrees of its own (each pair once, sorted)."""
    names, centres, rotations = _poses(given)
    axes = rotations[:, 2, :]
    distance = torch.cdist(centres, centres)
    facing = axes @ axes.T > 0.0
    distance[~facing] = float("inf")
    distance.fill_diagonal_(float("inf"))
    count = min(NEIGHBOURS, len(names) - 1)
    nearest = distance.topk(count, dim=1, largest=False)
    pairs = set()
    for i in range(len(names)):
        for value, j in zip(nearest.values[i].tolist(), nearest.indices[i].tolist(), strict=True):
            if value != float("inf"):
                pairs.add(tuple(sorted((names[i], names[j]))))
    return sorted(pairs)


def _poses(reconstruction: pycolmap.Reconstruction, names: list[str] | None = None):
    """Image names (sorted unless given), camera centres [N, 3] and world-to-camera rotations [N, 3, 3] (float64; row
    2 of a rotation is the camera's optical axis in the world)."""
    by_name = {image.name: image for image in reconstruction.images.values()}
    names = sorted(by_name) if names is None else names
    matrices = torch.tensor(
        np.stack([np.asarray(by_name[name].cam_from_world().matrix()) for name in names]), dtype=torch.float64
    )
    rotations = matrices[:, :, :3]
    centres = -(rotations.transpose(1, 2) @ matrices[:, :, 3:]).squeeze(-1)
    return names, centres, rotations


def _align_to_given(reconstruction: pycolmap.Reconstruction, given: pycolmap.Reconstruction) -> None:
    """Move ``reconstruction`` (points and cameras) by the similarity that best maps its camera centres onto the
    given ones (module docstring, step 4)."""
    names, centres, _ = _poses(reconstruction)
    _, given_centres, _ = _poses(given, names)
    similarity = umeyama(centres, given_centres)
    reconstruction.transform(
        pycolmap.Sim3d(
            similarity.scale,
            pycolmap.Rotation3d(similarity.rotation.numpy()),
            similarity.translation.numpy(),
        )
    )


def _camera_changes(
    given: pycolmap.Reconstruction, reconstruction: pycolmap.Reconstruction
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image: the rotation (degrees) between the adjusted and the given camera, and the distance between their
    centres as a fraction of the given centres' spread."""
    names, centres, rotations = _poses(reconstruction)
    _, given_centres, given_rotations = _poses(given, names)
    spread = float((given_centres - given_centres.mean(dim=0)).square().sum(dim=1).mean().sqrt())
    moved = (centres - given_centres).norm(dim=1) / max(spread, 1e-12)
    turned = torch.rad2deg(rotation_angle(rotations, given_rotations))  # the same angle as between the c2w rotations
    return turned, moved


def _summary(given: pycolmap.Reconstruction, reconstruction: pycolmap.Reconstruction) -> str:
    """Points, observations, reprojection error and how far the adjusted cameras lie from the given ones."""
    turned, moved = _camera_changes(given, reconstruction)
    observations = sum(point.track.length() for point in reconstruction.points3D.values())
    given_camera = {image.name: given.cameras[image.camera_id] for image in given.images.values()}
    first_image = {image.camera_id: image.name for image in reconstruction.images.values()}
    focal = [
        f"{given_camera[first_image[camera_id]].mean_focal_length():.1f} -> {camera.mean_focal_length():.1f} px"
        for camera_id, camera in sorted(reconstruction.cameras.items())
    ]
    return (
        f"{reconstruction.num_points3D()} points, {observations} observations, mean reprojection error "
        f"{reconstruction.compute_mean_reprojection_error():.2f} px; adjusted cameras from the given ones: rotation "
        f"median {float(turned.median()):.3f} deg (max {float(turned.max()):.3f}), centre median "
        f"{float(moved.median()):.2%} of the cameras' spread (max {float(moved.max()):.2%})"
        + f", focal length {', '.join(focal)}"
    )


__all__ = [
    "EXHAUSTIVE_LIMIT",
    "MAX_IMAGE_SIZE",
    "NEIGHBOURS",
    "RECIPE_VERSION",
    "REFINEMENT_ROUNDS",
    "ImageTracks",
    "cache_key",
    "image_tracks",
    "neighbour_pairs",
]
