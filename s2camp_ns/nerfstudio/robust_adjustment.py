"""An SfM model's 3D points re-adjusted with a robust loss: the fixed points the track prior's anchor is fitted to.

Why. The anchor (``core.track_fit``) is a camera-only fit against fixed points, so the cameras can be no better than
the points. COLMAP's mapper ends with a global bundle adjustment in plain least squares (Ceres' trivial loss): every
observation within the mapper's reprojection threshold (4 px by default) counts with its square, and a few mismatched
or poorly localised keypoints hold the points, and through them the cameras, away from where the other observations
put them (``benchmarks/sfm.py``, ``local_refinement_check``). The image tracks (``image_tracks``) are adjusted with a
Cauchy loss of scale ``core.track_fit.LOSS_SCALE_PX``; the scene's own model gets the same adjustment here, once per
model, before its points become the anchor's.

What. ``pycolmap.bundle_adjustment`` of the whole model (every registered image: the held-out ones are evidence
about the points too) with Ceres' Cauchy loss of scale ``LOSS_SCALE_PX``; poses and points free, the intrinsics held
at the model's. Only the points are kept. Holding the intrinsics leaves them to the anchor's own test
(``fit_anchor`` keeps the given intrinsics unless the tracks call for others): points adjusted with a refitted focal
length would carry it into that test as if it were evidence, and a camera-only fit cannot weigh the points' share of
it. A bundle adjustment with free points has a similarity gauge that the solver may move along, so the adjusted
points are mapped back into the model's world by the similarity that best maps the adjusted camera centres onto the
model's (``core.alignment.umeyama``): the points stay in the frame of the given cameras, which the data parser
normalized, and the anchor moves each camera only by what the robust loss changes. The cameras are then fitted to
these points by ``core.track_fit`` in the refiner's own parametrization, with its test on the intrinsics; a camera-only
fit with the same loss at the adjusted points lands where the joint adjustment put that camera.

Cache. The adjustment takes minutes on a model of hundreds of images and a million observations on a CPU of a few
cores, and every process that loads the scene asks for it (training, each rank of a multi-device run, evaluation,
rendering, export). Its points are kept in the user's cache folder (``track_cache.user_cache_folder`` of
``CACHE_KIND``), one ``<key>.npz`` per model, the key a hash of the model's files and of this recipe (``RECIPE``), so
an edited model gets a new entry and the scene folder is never written; processes that ask at once build it once
(``track_cache.entry_lock``). Where the cache folder cannot be written the points are adjusted in memory, with a note.
An entry that does not read back (a damaged file: zip's CRC, the arrays' names, shapes and finiteness) is never used:
a notice names it (``track_cache.notice_damaged``) and the points are adjusted again and the entry rewritten.

Measured against the tracks' points as SfM left them: docs/DESIGN-NOTES.md sec. 8 and the regime and splat
benchmarks' ``sfm`` rows.
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

from s2camp_ns.colmap_log import colmap_log_to
from s2camp_ns.core.alignment import MIN_CAMERAS_FOR_ALIGNMENT, umeyama
from s2camp_ns.core.track_fit import LOSS_SCALE_PX
from s2camp_ns.nerfstudio.colmap_model import model_file
from s2camp_ns.nerfstudio.track_cache import (
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
"""Start-up notes (the adjustment takes seconds to minutes on large models): on stderr, as the data parser's."""


def cauchy_adjustment_options(**fields) -> pycolmap.BundleAdjustmentOptions:
    """pycolmap's bundle adjustment options ``fields`` with Ceres' Cauchy loss of scale ``LOSS_SCALE_PX``: the loss of
    every bundle adjustment of tracks here (this module's, the image tracks'), the anchor fit's own, so that the
    anchor weighs the observations as the adjustments that placed their points did."""
    options = pycolmap.BundleAdjustmentOptions(**fields)
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = LOSS_SCALE_PX
    return options


def robustly_adjusted_points(model: Path) -> dict[int, np.ndarray]:
    """The 3D points of the COLMAP model folder ``model`` (cameras, images, points3D; .bin or .txt) after a robust
    bundle adjustment (module docstring), by point id, in the model's world; from the cache when an earlier process
    adjusted the same model (module docstring, Cache), and kept in memory per folder and file times, so the data
    parser's splits share one adjustment. A model with fewer than ``MIN_CAMERAS_FOR_ALIGNMENT`` registered images has
    no similarity to map back with and keeps its points (a note says so)."""
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
    """The points of a cache entry; ``DamagedEntryError`` saying why when it does not read back as written."""
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
    """Write the points to ``entry`` through a temporary file renamed into place: a reader never sees half a file."""
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
