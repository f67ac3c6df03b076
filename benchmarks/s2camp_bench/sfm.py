"""Structure from motion on a generated scene (pycolmap SIFT, exhaustive matching, incremental mapping).

``run_sfm`` writes a scene folder that ``ns-train`` reads like the generated one: the same ``images/`` and
``images_2/`` (symbolic links) and ``sparse/0`` = the SfM model, whose image names are the truth's. One shared
SIMPLE_RADIAL camera (``CameraMode.SINGLE``). COLMAP's log lines go to ``sfm.log`` in the output folder.

``focal_prior`` plays the EXIF focal length a real capture carries: the mapper starts from that factor times the true
focal length instead of COLMAP's guess for images without EXIF (1.2 x max(W, H), twice the generated wide scene's
true focal length). From that guess SfM of the wide scene ends several times further from the truth in rotation,
centres and focal length than from an EXIF-like prior 5% off (docs/benchmarks/recovery.md, tier 3, a record).

``compare_with_truth`` compares the SfM model with the truth (the generated scene's ``sparse/0``) after a similarity
alignment of the camera centres (Umeyama, ``s2camp_ns.core.alignment``): a reconstruction that misses images, splits
into several models, or whose centres or rotations are far from the truth is a failed scene, not a data point.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from s2camp_ns.core.alignment import rotation_angle, umeyama
from s2camp_ns.core.validation import check_range
from s2camp_ns.tracks.colmap_log import colmap_log_to

CAMERA_MODEL = "SIMPLE_RADIAL"
"""The shared camera model of the SfM start (it maps onto S2CamP's intrinsics)."""
SFM_THREADS, SFM_SEED = 1, 0
"""One thread and a fixed seed: the SfM start is then bit-identical from run to run (COLMAP's multi-threaded mapper
registers images in a run-dependent order)."""
MIN_POSE_INLIERS = 15
"""Absolute-pose inliers needed to register an image (COLMAP's default 30 is meant for megapixel images; the
generated images have a few hundred SIFT features)."""


def _mapping_options():
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions(num_threads=SFM_THREADS, random_seed=SFM_SEED)
    options.mapper.abs_pose_min_num_inliers = MIN_POSE_INLIERS
    return options


@dataclass(frozen=True)
class SfmCheck:
    """Limits a reconstruction must meet to count as a successful scene: loose enough for an inaccurate but
    consistent reconstruction (the wide scene mapped from COLMAP's focal-length guess stays below them in every
    camera, docs/benchmarks/recovery.md, tier 3), tight enough to reject a broken one (a mirrored or folded ring is off
    by about 100%)."""

    max_centre_error: float = 0.1
    """Largest camera-centre error after similarity alignment, as a fraction of the ring radius."""
    max_rotation_error: float = 0.1
    """Largest rotation error after alignment (rad, about 6 degrees)."""


@dataclass
class SfmResult:
    """One SfM run on one scene, compared with the truth (errors NaN when it failed before the comparison)."""

    scene: Path
    """The SfM scene folder (images/, images_2/, sparse/0)."""
    registered: int
    images: int
    true_focal: float
    failure: str | None = None
    """Why the reconstruction is not usable (None: it is)."""
    rot_err_max: float = math.nan
    """Largest rotation error after alignment (rad)."""
    centre_err_max: float = math.nan
    """Largest centre error after alignment, in the truth's world units."""
    rot_err_mean: float = math.nan
    centre_err_mean: float = math.nan
    focal: float = math.nan
    """SfM's shared focal length (full-resolution px)."""


def initial_camera_params(focal: float, width: int, height: int) -> str:
    """COLMAP's SIMPLE_RADIAL ``camera_params`` string for a start at ``focal`` (pixels), principal point at the
    image centre and no distortion."""
    return ",".join(repr(float(value)) for value in (focal, width / 2.0, height / 2.0, 0.0))


def run_sfm(scene: Path, output: Path, check: SfmCheck = SfmCheck(), focal_prior: float | None = None) -> SfmResult:
    """SfM on ``scene/images`` into ``output`` (module docstring); compared with ``scene/sparse/0``. ``focal_prior``:
    the mapper's initial focal length as a factor of the true one (None: COLMAP's guess without EXIF)."""
    import pycolmap

    if focal_prior is not None:
        check_range("focal_prior", focal_prior, low=0.1, high=10.0)
    if output.exists():
        shutil.rmtree(output)
    work = output / "colmap"
    work.mkdir(parents=True)
    for folder in ("images", "images_2"):
        (output / folder).symlink_to((scene / folder).resolve(), target_is_directory=True)
    database = work / "database.db"
    images = scene / "images"
    truth = pycolmap.Reconstruction(scene / "sparse" / "0")
    reader = pycolmap.ImageReaderOptions(camera_model=CAMERA_MODEL)
    if focal_prior is not None:
        camera = next(iter(truth.cameras.values()))
        reader.camera_params = initial_camera_params(focal_prior * camera.focal_length_x, camera.width, camera.height)
    with colmap_log_to(output / "sfm.log"):
        extraction = pycolmap.FeatureExtractionOptions(num_threads=SFM_THREADS)
        pycolmap.extract_features(database, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)  # fmt: skip
        matching = pycolmap.FeatureMatchingOptions(num_threads=SFM_THREADS)
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        models = pycolmap.incremental_mapping(database, images, work / "sparse", options=_mapping_options())
    if not models:
        return SfmResult(output, 0, truth.num_images(), _focal(truth), "incremental mapping produced no model")
    best = max(models.values(), key=lambda model: model.num_reg_images())
    sparse = output / "sparse" / "0"
    sparse.mkdir(parents=True)
    best.write_binary(sparse)
    for extra in ("rigs.bin", "frames.bin"):  # the mip-NeRF 360 layout has three files
        (sparse / extra).unlink(missing_ok=True)
    return compare_with_truth(output, best, truth, check)


def _centres_and_rotations(reconstruction, names: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
    by_name = {image.name: image for image in reconstruction.images.values()}
    centres, rotations = [], []
    for name in names:
        pose = by_name[name].cam_from_world()
        matrix = np.asarray(pose.matrix())
        rotations.append(matrix[:, :3].T)  # camera-to-world rotation
        centres.append(-matrix[:, :3].T @ matrix[:, 3])
    return torch.tensor(np.stack(centres)), torch.tensor(np.stack(rotations))


def _focal(reconstruction) -> float:
    camera = next(iter(reconstruction.cameras.values()))
    return float(camera.focal_length_x)


def compare_with_truth(output: Path, sfm, truth, check: SfmCheck) -> SfmResult:
    """Registration and similarity-aligned centre / rotation errors of ``sfm`` against ``truth``."""
    names = sorted(image.name for image in truth.images.values())
    registered = sorted(image.name for image in sfm.images.values() if image.has_pose)
    result = SfmResult(output, len(registered), len(names), _focal(truth))
    if registered != names:
        result.failure = f"{len(registered)} of {len(names)} images registered (missing e.g. "
        result.failure += f"{sorted(set(names) - set(registered))[:3]})"
        return result
    if len(sfm.cameras) != 1:
        result.failure = f"{len(sfm.cameras)} cameras instead of one shared camera"
        return result
    sfm_centres, sfm_rotations = _centres_and_rotations(sfm, names)
    true_centres, true_rotations = _centres_and_rotations(truth, names)
    similarity = umeyama(sfm_centres, true_centres)
    centre_errors = (similarity.apply_to_points(sfm_centres) - true_centres).norm(dim=1)
    rotation_errors = rotation_angle(similarity.rotation @ sfm_rotations, true_rotations)
    radius = float((true_centres[:, :2] - true_centres[:, :2].mean(dim=0)).norm(dim=1).mean())
    result.rot_err_max, result.centre_err_max = float(rotation_errors.max()), float(centre_errors.max())
    result.rot_err_mean, result.centre_err_mean = float(rotation_errors.mean()), float(centre_errors.mean())
    result.focal = _focal(sfm)
    if result.centre_err_max > check.max_centre_error * radius:
        result.failure = (f"camera centre error {result.centre_err_max:.3g} after alignment exceeds "
                          f"{check.max_centre_error:g} x ring radius {radius:.3g}")  # fmt: skip
    elif result.rot_err_max > check.max_rotation_error:
        result.failure = f"rotation error {result.rot_err_max:.3g} rad exceeds {check.max_rotation_error:g} rad"
    return result
