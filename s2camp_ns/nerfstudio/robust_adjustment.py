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

Measured against the tracks' points as SfM left them: docs/DESIGN-NOTES.md sec. 8 and the regime and splat
benchmarks' ``sfm`` rows.
"""

from __future__ import annotations

import tempfile
import time
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

LOG = Console(stderr=True, width=120)
"""Start-up notes (the adjustment takes seconds to minutes on large models): on stderr, as the data parser's."""


def robustly_adjusted_points(model: Path) -> dict[int, np.ndarray]:
    """The 3D points of the COLMAP model folder ``model`` (cameras, images, points3D; .bin or .txt) after a robust
    bundle adjustment (module docstring), by point id, in the model's world; cached per folder and file times, so the
    data parser's splits share one adjustment. A model with fewer than ``MIN_CAMERAS_FOR_ALIGNMENT`` registered images
    has no similarity to map back with and keeps its points (a note says so)."""
    files = [model_file(model, kind) for kind in ("cameras", "images", "points3D")]
    key = tuple((str(path.resolve()), path.stat().st_mtime_ns) for path in files)
    return _adjusted(key)


@lru_cache(maxsize=4)
def _adjusted(key: tuple[tuple[str, int], ...]) -> dict[int, np.ndarray]:
    folder = Path(key[0][0]).parent
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
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False, refine_principal_point=False, refine_extra_params=False, print_summary=False
    )
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = LOSS_SCALE_PX
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


__all__ = ["robustly_adjusted_points"]
