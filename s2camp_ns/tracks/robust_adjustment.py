"""An SfM model's tracks re-adjusted with a robust loss: the fixed points (and keypoints) the track prior's anchor is
fitted to.

The anchor (``core.track_fit``) fits cameras to fixed points, and COLMAP's last bundle adjustment is plain least
squares, which a few bad keypoints pull. Here, with the images, each track's keypoints are first refined against its
reference patch (``keypoint_refinement``); then a bundle adjustment of the whole model with Ceres' Cauchy loss
(``LOSS_SCALE_PX``), poses and points free, the intrinsics held, or, on refined keypoints, which pin them, adjusted too
(focal length and distortion; the principal point held); the points are kept, mapped back into the model's world by
the similarity from the adjusted camera centres to the model's (``core.alignment.umeyama``), with the keypoints.

The result is cached in ``<key>.npz`` in the user's cache folder (``CACHE_KIND``; the key hashes the model files,
``RECIPE`` and, with the images, ``KEYPOINT_RECIPE`` and each image's name, size and mtime), built once among
processes (``track_cache``); in memory where the folder cannot be written.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import time
import zipfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import pycolmap
import torch
from jaxtyping import Float
from rich.console import Console
from torch import Tensor

from s2camp_ns.core.alignment import MIN_CAMERAS_FOR_ALIGNMENT, umeyama
from s2camp_ns.core.track_fit import LOSS_SCALE_PX
from s2camp_ns.data.colmap_files import model_file
from s2camp_ns.tracks.colmap_log import colmap_log_to
from s2camp_ns.tracks.keypoint_refinement import KEYPOINT_RECIPE, refine_keypoints
from s2camp_ns.tracks.track_cache import (
    DamagedEntryError,
    entry_lock,
    hash_file,
    notice_damaged,
    user_cache_folder,
    write_error,
)

RECIPE = 2
"""Part of the cache key: raise it when the adjustment changes, so entries of the old one are not read."""
CACHE_KIND = "readjusted_points"
"""The cache's folder in the user's cache folder (``track_cache.user_cache_folder``)."""
WHAT = "Re-adjusted SfM points"
"""What the cache holds, in its notices (``track_cache``)."""
LOG = Console(stderr=True, width=120)
"""Start-up notes, on stderr."""


def cauchy_adjustment_options(**fields) -> pycolmap.BundleAdjustmentOptions:
    """pycolmap's bundle adjustment options ``fields`` with Ceres' Cauchy loss of scale ``LOSS_SCALE_PX``, the anchor
    fit's own loss: every adjustment of tracks (here and ``image_tracks``) uses it."""
    options = pycolmap.BundleAdjustmentOptions(**fields)
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = LOSS_SCALE_PX
    return options


@dataclass(frozen=True)
class ReadjustedTracks:
    """A model's tracks after the robust adjustment, in the model's world."""

    points: dict[int, np.ndarray]
    """Each 3D point [3] by id."""
    keypoints: dict[int, np.ndarray] = field(default_factory=dict)
    """Each image's keypoints [k, 2] (all of its points2D, in order; model px) by image id, refined where the
    refinement took them; empty without the images (the model's own keypoints)."""


def readjusted_tracks(model: Path, image_root: Path | None = None) -> ReadjustedTracks:
    """The tracks of the COLMAP model folder ``model`` after the robust adjustment (module docstring), the keypoints
    refined from the model's images under ``image_root`` (by name; None: not refined); cached on disk and in memory
    (per folder and file times). A model of fewer than ``MIN_CAMERAS_FOR_ALIGNMENT`` registered images keeps its
    points and keypoints."""
    files = [model_file(model, kind) for kind in ("cameras", "images", "points3D")]
    root = None if image_root is None else str(Path(image_root).resolve())
    return _cached(tuple((str(path.resolve()), path.stat().st_mtime_ns) for path in files), root)


@lru_cache(maxsize=4)
def _cached(files: tuple[tuple[str, int], ...], image_root: str | None) -> ReadjustedTracks:
    folder = Path(files[0][0]).parent
    root = None if image_root is None else Path(image_root)
    cache = user_cache_folder(CACHE_KIND)
    error = write_error(cache)
    if error is not None:
        LOG.print(f"[dim]Track prior: the cache folder {cache} cannot be written ({error}); adjusting in memory")
        return _adjusted(folder, root)
    entry = cache / f"{cache_key([Path(path) for path, _ in files], root)}.npz"
    if entry.is_file():
        try:
            return _read(entry)
        except DamagedEntryError as error:
            notice_damaged(entry, WHAT, str(error))
    with entry_lock(entry, WHAT):
        if entry.is_file():
            try:  # built by the process this one waited for
                return _read(entry)
            except DamagedEntryError:  # noticed above: adjusted again and rewritten
                pass
        tracks = _adjusted(folder, root)
        _write(entry, tracks)
    return tracks


def cache_key(files: list[Path], image_root: Path | None = None) -> str:
    """The cache entry's name: a hash of ``RECIPE`` and of the model files' names and contents; with ``image_root``,
    of ``KEYPOINT_RECIPE`` and each file's name, size and mtime there (sorted)."""
    digest = hashlib.sha256(f"{RECIPE} {LOSS_SCALE_PX!r}".encode())
    for path in files:
        digest.update(path.name.encode() + b"\0")
        hash_file(digest, path)
    if image_root is not None:
        digest.update(f"refined {KEYPOINT_RECIPE}\0".encode())
        for path in sorted(path for path in image_root.rglob("*") if path.is_file()):
            stat = path.stat()
            digest.update(f"{path.relative_to(image_root).as_posix()} {stat.st_size} {stat.st_mtime_ns}\0".encode())
    return digest.hexdigest()[:24]


def _read(entry: Path) -> ReadjustedTracks:
    """The tracks of a cache entry; ``DamagedEntryError`` when they do not read back as written."""
    try:
        with np.load(entry) as stored:
            ids, xyz = stored["ids"], stored["xyz"]  # [m], [m, 3]
            images, counts, xys = stored["keypoint_images"], stored["keypoint_counts"], stored["keypoint_xy"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise DamagedEntryError(f"{type(error).__name__}: {error}") from error
    shaped = ids.ndim == 1 and ids.dtype == np.int64 and xyz.shape == (len(ids), 3) and xyz.dtype == np.float64
    if not shaped or not np.isfinite(xyz).all():
        raise DamagedEntryError(
            f"expected int64 ids [m] and finite float64 xyz [m, 3], found {ids.dtype} ids {list(ids.shape)} and "
            f"{xyz.dtype} xyz {list(xyz.shape)}" + ("" if np.isfinite(xyz).all() else " with NaN or infinite values")
        )
    if images.shape != counts.shape or xys.shape != (int(counts.sum()), 2) or not np.isfinite(xys).all():
        raise DamagedEntryError(
            f"expected keypoint counts per image summing to finite keypoint_xy rows, found {list(images.shape)} "
            f"images, {list(counts.shape)} counts and keypoint_xy {list(xys.shape)}"
        )
    keypoints = dict(zip(images.tolist(), np.split(xys, np.cumsum(counts)[:-1]), strict=True)) if len(images) else {}
    return ReadjustedTracks({int(point_id): xyz[row] for row, point_id in enumerate(ids)}, keypoints)


def _write(entry: Path, tracks: ReadjustedTracks) -> None:
    """Write the tracks to ``entry`` through a temporary file renamed into place."""
    ids = np.fromiter(tracks.points, dtype=np.int64, count=len(tracks.points))
    xyz = np.stack([tracks.points[int(i)] for i in ids]) if len(ids) else np.zeros((0, 3))
    images = np.fromiter(tracks.keypoints, dtype=np.int64, count=len(tracks.keypoints))
    counts = np.asarray([len(tracks.keypoints[int(i)]) for i in images], dtype=np.int64)
    xys = np.concatenate([tracks.keypoints[int(i)] for i in images]) if len(images) else np.zeros((0, 2))
    handle, temporary = tempfile.mkstemp(prefix=f".{entry.stem}.", suffix=".npz", dir=entry.parent)
    try:
        with os.fdopen(handle, "wb") as output:
            np.savez(
                output, ids=ids, xyz=xyz.astype(np.float64), keypoint_images=images, keypoint_counts=counts,
                keypoint_xy=xys.astype(np.float64),
            )  # fmt: skip
        os.replace(temporary, entry)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise


def _adjusted(folder: Path, image_root: Path | None) -> ReadjustedTracks:
    reconstruction = pycolmap.Reconstruction(folder)
    given = {point_id: np.asarray(point.xyz, dtype=np.float64) for point_id, point in reconstruction.points3D.items()}
    image_ids = sorted(reconstruction.reg_image_ids())
    if not given:
        return ReadjustedTracks(given)
    if len(image_ids) < MIN_CAMERAS_FOR_ALIGNMENT:
        LOG.print(f"[dim]Track prior: {folder} registers {len(image_ids)} image(s); its points are kept as they are")
        return ReadjustedTracks(given)
    centres_before = _centres(reconstruction, image_ids)  # [n, 3]
    if image_root is not None:
        _refine(reconstruction, image_root)
    LOG.print(
        f"[dim]Track prior: re-adjusting the {len(given)} points of {folder} with a robust loss (Cauchy, "
        f"{LOSS_SCALE_PX:g} px; pycolmap bundle adjustment of {len(image_ids)} images)..."
    )
    joint = image_root is not None  # refined keypoints pin the intrinsics: adjusted with the rest
    options = cauchy_adjustment_options(
        refine_focal_length=joint, refine_principal_point=False, refine_extra_params=joint, print_summary=False
    )
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch, colmap_log_to(Path(scratch) / "colmap.log"):
        pycolmap.bundle_adjustment(reconstruction, options)
    back = umeyama(_centres(reconstruction, image_ids), centres_before)  # adjusted world -> the model's
    ids = list(given)
    xyz = torch.as_tensor(np.stack([reconstruction.points3D[i].xyz for i in ids]), dtype=torch.float64)  # [m, 3]
    mapped = back.apply_to_points(xyz).numpy()
    moved = np.linalg.norm(mapped - np.stack([given[i] for i in ids]), axis=-1)
    LOG.print(
        f"[dim]Track prior: the points moved by {np.median(moved):.3g} (median, the model's units) in "
        f"{time.perf_counter() - began:.1f} s"
    )
    keypoints = {}
    if image_root is not None:
        for image_id in image_ids:
            points2d = reconstruction.images[image_id].points2D
            keypoints[image_id] = np.asarray([point.xy for point in points2d], dtype=np.float64).reshape(-1, 2)
    return ReadjustedTracks({point_id: mapped[row] for row, point_id in enumerate(ids)}, keypoints)


def _refine(reconstruction: pycolmap.Reconstruction, image_root: Path) -> None:
    """The model's keypoints refined in place against its images (``keypoint_refinement``), with progress."""
    LOG.print(f"[dim]Track prior: refining the keypoints of the model's tracks against the images of {image_root}...")
    every = max(1, sum(point.track.length() for point in reconstruction.points3D.values()) // 10)
    shown = [0]

    def progress(done: int, total: int) -> None:
        if done - shown[0] >= every or done == total:
            shown[0] = done
            LOG.print(f"[dim]  {done}/{total} keypoints aligned")

    LOG.print(f"[dim]Track prior: {refine_keypoints(reconstruction, image_root, progress=progress).describe()}")


def _centres(reconstruction: pycolmap.Reconstruction, image_ids: list[int]) -> Float[Tensor, "n 3"]:
    centres = [np.asarray(reconstruction.images[i].projection_center(), dtype=np.float64) for i in image_ids]
    return torch.as_tensor(np.stack(centres))


__all__ = ["ReadjustedTracks", "cauchy_adjustment_options", "readjusted_tracks"]
