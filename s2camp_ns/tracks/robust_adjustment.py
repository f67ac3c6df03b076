"""An SfM model's 3D points re-adjusted with a robust loss: the fixed points the track prior's anchor is fitted to.

The anchor (``core.track_fit``) fits cameras to fixed points, and COLMAP's last bundle adjustment is plain least
squares, which a few bad keypoints pull. Here a bundle adjustment of the whole model with Ceres' Cauchy loss
(``LOSS_SCALE_PX``), poses and points free, intrinsics held; only the points are kept, mapped back into the model's
world by the similarity from the adjusted camera centres to the model's (``core.alignment.umeyama``).

The points are cached in ``<key>.npz`` in the user's cache folder (``CACHE_KIND``; the key hashes the model files and
``RECIPE``), built once among processes (``track_cache``); in memory where the folder cannot be written.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import time
import zipfile
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
from s2camp_ns.tracks.track_cache import (
    DamagedEntryError,
    entry_lock,
    hash_file,
    notice_damaged,
    user_cache_folder,
    write_error,
)

RECIPE = 1
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


def robustly_adjusted_points(model: Path) -> dict[int, np.ndarray]:
    """The 3D points [3] by id of the COLMAP model folder ``model`` after the robust adjustment, in the model's world;
    cached on disk and in memory (per folder and file times). A model of fewer than ``MIN_CAMERAS_FOR_ALIGNMENT``
    registered images keeps its points."""
    files = [model_file(model, kind) for kind in ("cameras", "images", "points3D")]
    return _cached(tuple((str(path.resolve()), path.stat().st_mtime_ns) for path in files))


@lru_cache(maxsize=4)
def _cached(files: tuple[tuple[str, int], ...]) -> dict[int, np.ndarray]:
    folder = Path(files[0][0]).parent
    cache = user_cache_folder(CACHE_KIND)
    error = write_error(cache)
    if error is not None:
        LOG.print(f"[dim]Track prior: the cache folder {cache} cannot be written ({error}); adjusting in memory")
        return _adjusted(folder)
    entry = cache / f"{cache_key([Path(path) for path, _ in files])}.npz"
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
        points = _adjusted(folder)
        _write(entry, points)
    return points


def cache_key(files: list[Path]) -> str:
    """The cache entry's name: a hash of ``RECIPE`` and of the model files' names and contents."""
    digest = hashlib.sha256(f"{RECIPE} {LOSS_SCALE_PX!r}".encode())
    for path in files:
        digest.update(path.name.encode() + b"\0")
        hash_file(digest, path)
    return digest.hexdigest()[:24]


def _read(entry: Path) -> dict[int, np.ndarray]:
    """The points of a cache entry; ``DamagedEntryError`` when it does not read back as written."""
    try:
        with np.load(entry) as stored:
            ids, xyz = stored["ids"], stored["xyz"]  # [m], [m, 3]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise DamagedEntryError(f"{type(error).__name__}: {error}") from error
    shaped = ids.ndim == 1 and ids.dtype == np.int64 and xyz.shape == (len(ids), 3) and xyz.dtype == np.float64
    if not shaped or not np.isfinite(xyz).all():
        raise DamagedEntryError(
            f"expected int64 ids [m] and finite float64 xyz [m, 3], found {ids.dtype} ids {list(ids.shape)} and "
            f"{xyz.dtype} xyz {list(xyz.shape)}" + ("" if np.isfinite(xyz).all() else " with NaN or infinite values")
        )
    return {int(point_id): xyz[row] for row, point_id in enumerate(ids)}


def _write(entry: Path, points: dict[int, np.ndarray]) -> None:
    """Write the points to ``entry`` through a temporary file renamed into place."""
    ids = np.fromiter(points, dtype=np.int64, count=len(points))
    xyz = np.stack([points[int(i)] for i in ids]) if len(ids) else np.zeros((0, 3))
    handle, temporary = tempfile.mkstemp(prefix=f".{entry.stem}.", suffix=".npz", dir=entry.parent)
    try:
        with os.fdopen(handle, "wb") as output:
            np.savez(output, ids=ids, xyz=xyz.astype(np.float64))
        os.replace(temporary, entry)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise


def _adjusted(folder: Path) -> dict[int, np.ndarray]:
    reconstruction = pycolmap.Reconstruction(folder)
    given = {point_id: np.asarray(point.xyz, dtype=np.float64) for point_id, point in reconstruction.points3D.items()}
    image_ids = sorted(reconstruction.reg_image_ids())
    if not given:
        return given
    if len(image_ids) < MIN_CAMERAS_FOR_ALIGNMENT:
        LOG.print(f"[dim]Track prior: {folder} registers {len(image_ids)} image(s); its points are kept as they are")
        return given
    centres_before = _centres(reconstruction, image_ids)  # [n, 3]
    LOG.print(
        f"[dim]Track prior: re-adjusting the {len(given)} points of {folder} with a robust loss (Cauchy, "
        f"{LOSS_SCALE_PX:g} px; pycolmap bundle adjustment of {len(image_ids)} images)..."
    )
    options = cauchy_adjustment_options(
        refine_focal_length=False, refine_principal_point=False, refine_extra_params=False, print_summary=False
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
    return {point_id: mapped[row] for row, point_id in enumerate(ids)}


def _centres(reconstruction: pycolmap.Reconstruction, image_ids: list[int]) -> Float[Tensor, "n 3"]:
    centres = [np.asarray(reconstruction.images[i].projection_center(), dtype=np.float64) for i in image_ids]
    return torch.as_tensor(np.stack(centres))


__all__ = ["cauchy_adjustment_options", "robustly_adjusted_points"]
