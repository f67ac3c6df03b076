"""Tracks made from a scene's own images, for scenes without an SfM model, so that the track prior anchors their
images as it anchors SfM's (``core.track_fit``). Recipe (pycolmap; SIFT and matching on CUDA where pycolmap has it):

1. SIFT features (longest side at most ``MAX_IMAGE_SIZE``), one COLMAP camera per physical camera at the given
   intrinsics.
2. Matches verified by RANSAC between every pair of images up to ``EXHAUSTIVE_LIMIT`` images, else the
   ``neighbour_pairs``.
3. Points triangulated with the given cameras, then ``REFINEMENT_ROUNDS`` rounds of bundle adjustment (points, poses,
   focal lengths, distortion; principal point fixed) and re-triangulation, and a last adjustment (``Thresholds``).
4. With ``refine_keypoints``: every track's keypoints aligned to its reference observation's patch
   (``keypoint_refinement``), then a last adjustment on them.
5. A similarity (Umeyama on the camera centres) maps the result onto the given poses, whose world the images do not
   fix.

The result is a COLMAP model in the world of the given poses, cached in ``<cache>/<cache_key>``: built in a
temporary sibling folder renamed when finished, each model file's SHA-256 in ``RESULT_FILE``; a damaged entry is
never used, but named and built again (``track_cache``). Two builds of one key on one machine are bit-identical.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
import torch
from rich.markup import escape

from s2camp_ns.core.alignment import MIN_CAMERAS_FOR_ALIGNMENT, rotation_angle, umeyama
from s2camp_ns.core.track_fit import MIN_OBSERVATIONS
from s2camp_ns.data.colmap_files import ColmapModelError, read_model_file
from s2camp_ns.data.image_check import decoded_sizes
from s2camp_ns.tracks.build_progress import BuildProgress, DatabaseCounter, database_count, duration_text
from s2camp_ns.tracks.colmap_log import colmap_log_to
from s2camp_ns.tracks.feature_database import given_with_database_ids, names_by_camera, number_images, open_database
from s2camp_ns.tracks.keypoint_refinement import KEYPOINT_RECIPE, refine_keypoints
from s2camp_ns.tracks.robust_adjustment import cauchy_adjustment_options
from s2camp_ns.tracks.track_cache import (
    DamagedEntryError,
    build_folder,
    discard,
    entry_lock,
    file_digest,
    notice_damaged,
    remove_stale_builds,
    user_cache_folder,
)

RECIPE_VERSION = 5
"""Part of the cache key: raise it when the recipe changes, so that older entries are not read."""
MAX_IMAGE_SIZE = 1600
"""Longest image side SIFT sees (px); larger images are downsampled for extraction, keypoints stay in full-size px."""
EXHAUSTIVE_LIMIT = 100
"""Up to this many images every pair is matched; beyond it, each image with its ``NEIGHBOURS``."""
NEIGHBOURS = 30
"""Images matched with each image beyond ``EXHAUSTIVE_LIMIT`` (``neighbour_pairs``)."""
PAIR_ROWS = 1024
"""Images whose neighbours ``neighbour_pairs`` ranks at once: memory of this many rows of all images, not a square."""
KEYPOINT_ERROR_PX = 4.0
"""Reprojection bound (px at the size SIFT sees; COLMAP's default) of the verification and of the triangulations with
adjusted poses; grown by the extraction's downsampling factor (``Thresholds``)."""
GIVEN_ANGLE_ERROR_DEG = 2.0
"""Angle (degrees) by which the given poses' rays may be off: the first triangulation admits this angle times the
focal length as reprojection error (``Thresholds``), and this angle between a track's rays."""
REFINEMENT_ROUNDS = 3
"""Rounds of bundle adjustment and re-triangulation with the adjusted poses."""
COLMAP_SEED = 0
"""COLMAP's random seed (RANSAC of the geometric verification)."""
MATCHING_THREADS = 1
"""Threads of the matching and its verification: on several, RANSAC's draws depend on which thread takes which pair,
and builds differ. The other stages keep COLMAP's threads (deterministic once ``number_images`` has run)."""
RESULT_FILE = "result.json"
"""Written last into a cache entry: the summary or the reason there are no tracks, ``stage_seconds`` and the SHA-256 of
each of the ``MODEL_FILES`` (``files``)."""
MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")
"""The model of a cache entry that holds tracks."""
STAGES_FILE = "stages.json"
"""The build's wall seconds per kind of stage, written by ``_build`` and moved into ``RESULT_FILE``."""
MIN_TRACKED_FRACTION = 0.5
"""Fraction of the images that must see at least ``MIN_OBSERVATIONS`` tracked points for the tracks to be used."""
MAX_ROTATION_CHANGE_DEG = 10.0
"""Largest median rotation (degrees) of the adjusted poses from the given ones."""
MAX_CENTRE_CHANGE = 0.25
"""Largest median distance of the adjusted camera centres from the given ones after the similarity, as a fraction of
the given centres' spread (RMS distance to their centroid)."""


@dataclass(frozen=True)
class ImageTracks:
    """The model folder of ``image_tracks`` (None when no tracks could be made, with ``reason``) and a summary."""

    model: Path | None
    summary: str = ""
    reason: str | None = None
    stage_seconds: dict[str, float] = field(default_factory=dict)
    """Wall seconds of the build that made the entry, per kind of stage (``SIFT``, ``matching``, ...)."""


def cache_key(given: pycolmap.Reconstruction, image_root: Path, refine_keypoints: bool = True) -> str:
    """The cache entry's name: a hash of ``RECIPE_VERSION``, pycolmap's version, each image's name, size, mtime and
    pose, the given cameras (every bit) and whether the keypoints are refined."""
    images = sorted(given.images.values(), key=lambda image: image.name)
    cameras = [
        [camera_id, camera.model.name, camera.width, camera.height, [float(v) for v in camera.params]]
        for camera_id, camera in sorted(given.cameras.items())
    ]
    record = {"recipe": RECIPE_VERSION, "pycolmap": pycolmap.__version__, "images": [], "cameras": cameras}
    if refine_keypoints:
        record["keypoints"] = f"refined {KEYPOINT_RECIPE}"
    for image in images:
        stat = (image_root / image.name).stat()
        pose = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        record["images"].append([image.name, stat.st_size, stat.st_mtime_ns, image.camera_id, pose.ravel().tolist()])
    return hashlib.sha256(json.dumps(record).encode("utf8")).hexdigest()[:20]


def image_tracks(
    given: pycolmap.Reconstruction,
    image_root: Path,
    cache: Path,
    user_fallback: bool = False,
    refine_keypoints: bool = True,
) -> ImageTracks:
    """Tracks of ``given``'s images (names relative to ``image_root``; given cameras and poses, no points), read from
    the folder ``cache`` or built there, once among processes (``track_cache.entry_lock``). ``user_fallback``: also
    read from, and built in where ``cache`` cannot be written, the user's cache folder; without it an unwritable
    ``cache`` raises OSError. ``refine_keypoints``: step 4 of the recipe. FileNotFoundError for a missing image."""
    missing = sorted(image.name for image in given.images.values() if not (image_root / image.name).is_file())
    if missing:
        raise FileNotFoundError(
            f"image '{image_root / missing[0]}' does not exist ({len(missing)} of {given.num_images()} images "
            "missing): tracks are made from the full-size images"
        )
    if given.num_images() < MIN_CAMERAS_FOR_ALIGNMENT:
        reason = f"{given.num_images()} images: tracks need at least {MIN_CAMERAS_FOR_ALIGNMENT}"
        return ImageTracks(None, reason=reason)
    key = cache_key(given, image_root, refine_keypoints)
    for folder in (cache, user_cache_folder()) if user_fallback else (cache,):
        if (folder / key).exists():  # read even where it cannot be written (a shipped cache)
            try:
                return _cached(folder / key)
            except DamagedEntryError as error:
                notice_damaged(folder / key, "Image tracks", str(error))
    final = build_folder(cache, user_fallback) / key
    with entry_lock(final):
        if final.exists():
            try:  # built by another process while this one waited
                return _cached(final)
            except DamagedEntryError:  # noticed above: never used, built again in its place
                discard(final)
        remove_stale_builds(final)
        decoded_sizes([image_root / image.name for image in given.images.values()], "the scene (image tracks)")
        return _store(given, image_root, final, refine_keypoints)


def _store(given: pycolmap.Reconstruction, image_root: Path, final: Path, refine_keypoints: bool) -> ImageTracks:
    """Build the cache entry ``final`` in a temporary sibling renamed to it when finished; the caller holds its
    ``entry_lock``."""
    work = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".building", dir=final.parent))
    try:
        started = time.perf_counter()
        reconstruction, reason = _build(given, image_root, work, refine_keypoints)
        result = {"reason": reason}
        stages = work / STAGES_FILE
        if stages.is_file():
            result["stage_seconds"] = json.loads(stages.read_text(encoding="utf8"))
            stages.unlink()
        if reason is None:
            result["summary"] = _summary(given, reconstruction, time.perf_counter() - started)
            reconstruction.write_binary(work)
            result["files"] = {name: file_digest(work / name) for name in MODEL_FILES}
        (work / RESULT_FILE).write_text(json.dumps(result), encoding="utf8")
        (work / "database.db").unlink(missing_ok=True)
        shutil.rmtree(work / "triangulated", ignore_errors=True)
        os.chmod(work, 0o755)  # mkdtemp's 0o700 would hide a shared or shipped cache from other users
        try:
            os.rename(work, final)
        except OSError:  # another process finished the same build first (no lock without fcntl): keep its folder
            if not (final / RESULT_FILE).is_file():
                raise
            shutil.rmtree(work)
        return _cached(final)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise


def _cached(folder: Path) -> ImageTracks:
    """The ``ImageTracks`` of a finished entry: its model, or why there is none (failed builds are cached too).
    Raises ``DamagedEntryError`` when the entry is damaged."""
    result = _result(folder)
    stage_seconds = result.get("stage_seconds", {})
    if result["reason"] is not None:
        reason = f"{result['reason']} (COLMAP's log: {folder / 'colmap.log'})"
        return ImageTracks(None, reason=reason, stage_seconds=stage_seconds)
    digests = result.get("files")
    for name, kind in zip(MODEL_FILES, ("cameras", "images", "points3D"), strict=True):
        if not (folder / name).is_file():
            raise DamagedEntryError(f"{name} is missing")
        if digests is None:  # an entry without digests: its files must at least read as a model
            try:
                read_model_file(folder / name, kind)
            except ColmapModelError as error:
                raise DamagedEntryError(str(error)) from error
        elif file_digest(folder / name) != digests.get(name):
            raise DamagedEntryError(f"{name} is not the file the build wrote (its SHA-256 differs)")
    return ImageTracks(folder, result["summary"], stage_seconds=stage_seconds)


def _result(folder: Path) -> dict:
    """The parsed ``RESULT_FILE`` of a cache entry; ``DamagedEntryError`` when it is missing or malformed."""
    path = folder / RESULT_FILE
    try:
        result = json.loads(path.read_text(encoding="utf8"))
    except FileNotFoundError:
        raise DamagedEntryError(f"it has no {RESULT_FILE}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DamagedEntryError(f"{RESULT_FILE} is not valid JSON ({error})") from None
    valid = isinstance(result, dict) and (result.get("reason") is None or isinstance(result["reason"], str))
    if not valid or "reason" not in result or (result["reason"] is None and not isinstance(result.get("summary"), str)):
        raise DamagedEntryError(f"{RESULT_FILE} lacks its 'reason' or 'summary'")
    return result


def _build(
    given: pycolmap.Reconstruction, image_root: Path, work: Path, refine_keypoints: bool
) -> tuple[pycolmap.Reconstruction, str | None]:
    """The adjusted, aligned reconstruction (module docstring, steps 1-5) and why it cannot anchor the cameras (None
    when it can); writes the stages' times to ``STAGES_FILE``."""
    pycolmap.set_random_seed(COLMAP_SEED)
    device, notice = feature_device()
    with BuildProgress("Image tracks built") as progress:
        sizes = sorted({f"{camera.width}x{camera.height}" for camera in given.cameras.values()})
        progress.note(
            f"Making image tracks of {given.num_images()} images ({', '.join(sizes)}) for the track prior, SIFT and "
            f"matching on the {device_name(device)}; built once, into {escape(str(work.parent))}"
        )
        if notice is not None:
            progress.note(f"[yellow]{escape(notice)}")
        built = _build_stages(given, image_root, work, device, progress, refine_keypoints)
    (work / STAGES_FILE).write_text(json.dumps(progress.seconds_by_kind()), encoding="utf8")
    return built


def _build_stages(
    given: pycolmap.Reconstruction,
    image_root: Path,
    work: Path,
    device: pycolmap.Device,
    progress: BuildProgress,
    refine_keypoints: bool,
) -> tuple[pycolmap.Reconstruction, str | None]:
    """``_build``'s steps, then the plausibility checks (``_implausible``)."""
    database = work / "database.db"
    thresholds = Thresholds.of(given)
    _extract(given, image_root, database, device, progress)
    _match(given, database, device, thresholds, progress)
    reconstruction = given_with_database_ids(given, database)
    unread = sorted(
        {image.name for image in given.images.values()} - {image.name for image in reconstruction.images.values()}
    )
    if unread:  # COLMAP skips an image it cannot decode; every training image must be in the model
        reason = f"COLMAP could not read {len(unread)} of {given.num_images()} images (first: '{unread[0]}')"
        return reconstruction, reason
    reconstruction = _triangulate_and_adjust(reconstruction, database, image_root, thresholds, progress)
    if reconstruction.num_points3D() == 0:
        return reconstruction, "no point could be triangulated from the images' matched features"
    if refine_keypoints:
        _refine_and_adjust(reconstruction, image_root, work / "colmap.log", progress)
    _align_to_given(reconstruction, given)
    return reconstruction, _implausible(given, reconstruction)


@dataclass(frozen=True)
class Thresholds:
    """A build's reprojection bounds (px of the full-size images): ``keypoint_px`` for the verification and the
    triangulations with adjusted cameras, ``given_px`` (at least ``keypoint_px``) for the first, with given cameras."""

    keypoint_px: float
    given_px: float

    @classmethod
    def of(cls, given: pycolmap.Reconstruction) -> Thresholds:
        """The bounds of ``given``'s largest image side and focal length (COLMAP takes one bound for all cameras)."""
        size = max(max(camera.width, camera.height) for camera in given.cameras.values())
        focal = max(camera.mean_focal_length() for camera in given.cameras.values())
        keypoint = KEYPOINT_ERROR_PX * max(1.0, size / MAX_IMAGE_SIZE)
        return cls(keypoint, max(keypoint, math.radians(GIVEN_ANGLE_ERROR_DEG) * focal))


CUDA_NOTICE = (
    "A CUDA device is present but the installed pycolmap has no CUDA: SIFT features and matching run on the CPU "
    "(pip install 's2camp-ns[gpu]': pycolmap-cuda12, docs/IMAGE-TRACKS.md)"
)
"""``feature_device``'s notice: the CPU build of pycolmap is the default dependency."""


def feature_device() -> tuple[pycolmap.Device, str | None]:
    """The device of SIFT and matching: CUDA where pycolmap has it and torch sees a device, else the CPU; and
    ``CUDA_NOTICE`` (else None) when a device is there but pycolmap lacks CUDA. The cache key does not name the
    device: any machine reads an entry built on another."""
    cuda = torch.cuda.is_available()
    if cuda and pycolmap.has_cuda:
        return pycolmap.Device.cuda, None
    return pycolmap.Device.cpu, CUDA_NOTICE if cuda else None


def device_name(device: pycolmap.Device) -> str:
    """``GPU`` or ``CPU``, for the build's messages."""
    return "GPU" if device == pycolmap.Device.cuda else "CPU"


def _extract(
    given: pycolmap.Reconstruction, image_root: Path, database: Path, device: pycolmap.Device, progress: BuildProgress
) -> None:
    """Step 1: SIFT features of ``given``'s images into ``database``, one COLMAP camera per given camera."""
    extraction = pycolmap.FeatureExtractionOptions(max_image_size=MAX_IMAGE_SIZE)
    number_images(given, database)
    count = DatabaseCounter(database, "keypoints", enabled=progress.live)
    with count, progress.stage("SIFT features", "SIFT", given.num_images(), "images", count) as stage:
        with colmap_log_to(database.parent / "colmap.log"):
            for camera_id, names in names_by_camera(given).items():
                camera = given.cameras[camera_id]
                reader = pycolmap.ImageReaderOptions(
                    camera_model=camera.model.name, camera_params=",".join(repr(float(v)) for v in camera.params)
                )
                pycolmap.extract_features(
                    database, image_root, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                    reader_options=reader, extraction_options=extraction, device=device,
                )  # fmt: skip
        with open_database(database) as db:
            stage.outcome = f"{db.num_keypoints()} keypoints"


def _match(
    given: pycolmap.Reconstruction,
    database: Path,
    device: pycolmap.Device,
    thresholds: Thresholds,
    progress: BuildProgress,
) -> None:
    """Step 2: matches of every pair (up to ``EXHAUSTIVE_LIMIT`` images) or the ``neighbour_pairs``, verified."""
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.max_error = thresholds.keypoint_px
    matching = pycolmap.FeatureMatchingOptions(num_threads=MATCHING_THREADS)
    count = given.num_images()
    exhaustive = count <= EXHAUSTIVE_LIMIT
    pairs = [] if exhaustive else neighbour_pairs(given)
    total = count * (count - 1) // 2 if exhaustive else len(pairs)
    done = DatabaseCounter(database, "two_view_geometries", enabled=progress.live)
    label = "matching, every pair" if exhaustive else f"matching, {NEIGHBOURS} neighbours"
    with done, progress.stage(label, "matching", total, "pairs", done) as stage:
        with colmap_log_to(database.parent / "colmap.log"):
            if exhaustive:
                pycolmap.match_exhaustive(
                    database, matching_options=matching, verification_options=verification, device=device
                )
            else:
                listed = database.parent / "pairs.txt"
                listed.write_text("".join(f"{a} {b}\n" for a, b in pairs), encoding="utf8")
                pycolmap.match_image_pairs(
                    database, matching_options=matching,
                    pairing_options=pycolmap.ImportedPairingOptions(match_list_path=listed),
                    verification_options=verification, device=device,
                )  # fmt: skip
        verified = database_count(database, "two_view_geometries", "rows > 0")
        with open_database(database) as db:
            stage.outcome = (
                f"{verified} verified ({thresholds.keypoint_px:.1f} px), {db.num_inlier_matches()} inlier matches"
            )


def _triangulate_and_adjust(
    reconstruction: pycolmap.Reconstruction,
    database: Path,
    image_root: Path,
    thresholds: Thresholds,
    progress: BuildProgress,
) -> pycolmap.Reconstruction:
    """Step 3 (module docstring); stops early when no point is left."""
    adjustment = cauchy_adjustment_options(refine_principal_point=False)
    rounds = REFINEMENT_ROUNDS + 1
    reconstruction = _triangulate(reconstruction, database, image_root, thresholds.given_px, f"1/{rounds}", progress)
    for done in range(1, rounds + 1):
        if reconstruction.num_points3D() == 0:
            break
        with progress.stage(f"bundle adjustment {done}/{rounds}", "adjustment") as stage:
            with colmap_log_to(database.parent / "colmap.log"):
                pycolmap.bundle_adjustment(reconstruction, adjustment)
            stage.outcome = f"points' reprojection error median {_median_point_error(reconstruction):.3g} px"
        if done < rounds:
            position = f"{done + 1}/{rounds}"
            reconstruction = _triangulate(
                reconstruction, database, image_root, thresholds.keypoint_px, position, progress
            )
    return reconstruction


def _refine_and_adjust(
    reconstruction: pycolmap.Reconstruction, image_root: Path, log: Path, progress: BuildProgress
) -> None:
    """Step 4: the keypoints refined against the images (``keypoint_refinement``), then a last adjustment (stage
    kinds ``keypoints`` and ``refined adjustment``: the refinement's own cost in ``ImageTracks.stage_seconds``)."""
    done = [0]

    def advance(count: int, _total: int) -> None:
        done[0] = count

    total = sum(point.track.length() - 1 for point in reconstruction.points3D.values())
    with progress.stage("keypoint refinement", "keypoints", total, "keypoints", lambda: done[0]) as stage:
        stage.outcome = refine_keypoints(reconstruction, image_root, progress=advance).describe()
    with progress.stage("bundle adjustment on the refined keypoints", "refined adjustment") as stage:
        with colmap_log_to(log):
            pycolmap.bundle_adjustment(reconstruction, cauchy_adjustment_options(refine_principal_point=False))
        stage.outcome = f"points' reprojection error median {_median_point_error(reconstruction):.3g} px"


def _median_point_error(reconstruction: pycolmap.Reconstruction) -> float:
    """Median over the points of each point's mean reprojection error (px); robust to a point sent to infinity."""
    reconstruction.update_point_3d_errors()
    return float(np.median([point.error for point in reconstruction.points3D.values()]))


def _triangulate(
    reconstruction: pycolmap.Reconstruction,
    database: Path,
    image_root: Path,
    max_error_px: float,
    position: str,
    progress: BuildProgress,
) -> pycolmap.Reconstruction:
    """New points for ``reconstruction``'s cameras, observations within ``max_error_px``; the first (``position``
    1/...) admits rays ``GIVEN_ANGLE_ERROR_DEG`` off."""
    options = pycolmap.IncrementalPipelineOptions()
    options.triangulation.merge_max_reproj_error = max_error_px
    options.triangulation.complete_max_reproj_error = max_error_px
    options.mapper.filter_max_reproj_error = max_error_px
    if position.startswith("1/"):
        options.triangulation.create_max_angle_error = GIVEN_ANGLE_ERROR_DEG
        options.triangulation.continue_max_angle_error = GIVEN_ANGLE_ERROR_DEG
    cameras = "given" if position.startswith("1/") else "adjusted"
    description = f"triangulation {position}, {cameras} cameras ({max_error_px:.1f} px)"
    with progress.stage(description, "triangulation") as stage:
        with colmap_log_to(database.parent / "colmap.log"):
            reconstruction = pycolmap.triangulate_points(
                reconstruction, database, image_root, database.parent / "triangulated", options=options
            )
        stage.outcome = (
            f"{reconstruction.num_points3D()} points, {reconstruction.compute_num_observations()} observations"
        )
    return reconstruction


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


def neighbour_pairs(given: pycolmap.Reconstruction) -> list[tuple[str, str]]:
    """Image pairs to match beyond ``EXHAUSTIVE_LIMIT`` images (sorted names, sorted list): each image with its
    ``NEIGHBOURS`` nearest images among those whose optical axes are within 90 degrees of its own, one whose axis is
    theta away counted (2 - cos theta) times as far, so that a turn on the spot ranks by how alike images face."""
    names, centres, rotations = _poses(given)
    axes = rotations[:, 2, :]
    count = min(NEIGHBOURS, len(names) - 1)
    pairs = set()
    for start in range(0, len(names), PAIR_ROWS):
        rows = torch.arange(start, min(start + PAIR_ROWS, len(names)))
        cosine = axes[rows] @ axes.T
        score = torch.cdist(centres[rows], centres, compute_mode="donot_use_mm_for_euclid_dist") * (2.0 - cosine)
        score[cosine <= 0.0] = float("inf")
        score[torch.arange(len(rows)), rows] = float("inf")
        nearest = score.topk(count, dim=1, largest=False)
        for i, values, indices in zip(rows.tolist(), nearest.values.tolist(), nearest.indices.tolist(), strict=True):
            for value, j in zip(values, indices, strict=True):
                if value != float("inf"):  # fewer than NEIGHBOURS cameras face within 90 degrees
                    pairs.add(tuple(sorted((names[i], names[j]))))
    return sorted(pairs)


def _poses(reconstruction: pycolmap.Reconstruction, names: list[str] | None = None):
    """Image names (sorted unless given), centres [N, 3] and world-to-camera rotations [N, 3, 3] (float64; row 2 is
    the optical axis in the world)."""
    by_name = {image.name: image for image in reconstruction.images.values()}
    names = sorted(by_name) if names is None else names
    matrices = torch.tensor(
        np.stack([np.asarray(by_name[name].cam_from_world().matrix()) for name in names]), dtype=torch.float64
    )
    rotations = matrices[:, :, :3]
    centres = -(rotations.transpose(1, 2) @ matrices[:, :, 3:]).squeeze(-1)
    return names, centres, rotations


def _align_to_given(reconstruction: pycolmap.Reconstruction, given: pycolmap.Reconstruction) -> None:
    """Move ``reconstruction`` by the similarity that best maps its camera centres onto ``given``'s (step 4)."""
    names, centres, _ = _poses(reconstruction)
    _, given_centres, _ = _poses(given, names)
    similarity = umeyama(centres, given_centres)
    rotation = pycolmap.Rotation3d(similarity.rotation.numpy())
    reconstruction.transform(pycolmap.Sim3d(similarity.scale, rotation, similarity.translation.numpy()))


def _camera_changes(
    given: pycolmap.Reconstruction, reconstruction: pycolmap.Reconstruction
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image [N]: rotation (degrees) from the given pose and centre distance over the given centres' spread."""
    names, centres, rotations = _poses(reconstruction)
    _, given_centres, given_rotations = _poses(given, names)
    spread = float((given_centres - given_centres.mean(dim=0)).square().sum(dim=1).mean().sqrt())
    moved = (centres - given_centres).norm(dim=1) / max(spread, 1e-12)
    turned = torch.rad2deg(rotation_angle(rotations, given_rotations))  # the same angle as between the c2w rotations
    return turned, moved


def _summary(
    given: pycolmap.Reconstruction, reconstruction: pycolmap.Reconstruction, seconds: float | None = None
) -> str:
    """One line: points, observations, reprojection error, the images' changes from the given poses and focal
    lengths and, with ``seconds``, the build's wall time and device."""
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
        + ("" if seconds is None else f"; built in {duration_text(seconds)} on the {device_name(feature_device()[0])}")
    )


__all__ = [
    "EXHAUSTIVE_LIMIT",
    "GIVEN_ANGLE_ERROR_DEG",
    "KEYPOINT_ERROR_PX",
    "MAX_IMAGE_SIZE",
    "NEIGHBOURS",
    "RECIPE_VERSION",
    "REFINEMENT_ROUNDS",
    "ImageTracks",
    "Thresholds",
    "cache_key",
    "feature_device",
    "image_tracks",
    "neighbour_pairs",
]
