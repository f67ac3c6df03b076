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

SFM_THREADS = 1
"""One thread and a fixed seed: COLMAP's multi-threaded mapper registers images in a run-dependent order (two runs of
one 24-image scene registered different numbers of images); with both, the SfM start is bit-identical from run to
run (docs/SPLAT.md sec. 6)."""
SFM_SEED = 0
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
    """Limits a reconstruction must meet to count as a successful scene."""

    max_centre_error: float = 0.1
    """Largest camera-centre error after similarity alignment, as a fraction of the ring radius. Loose enough for an
    inaccurate but consistent reconstruction (the wide scene mapped from COLMAP's focal-length guess without EXIF
    stays below it in every camera), tight enough to reject a broken one (a mirrored or folded ring is off by ~100%).
    The centre errors of both starts: docs/benchmarks/recovery.md, tier 3."""
    max_rotation_error: float = 0.1
    """Largest rotation error after alignment (rad, about 6 degrees), above the worst camera of the wide scene mapped
    from COLMAP's guess (docs/benchmarks/recovery.md, tier 3)."""


@dataclass
class SfmResult:
    """One SfM run on one scene, compared with the truth."""

    scene: Path
    """The SfM scene folder (images/, images_2/, sparse/0)."""
    registered: int
    images: int
    models: int
    points: int
    rot_err_max: float
    """Largest rotation error after alignment (rad)."""
    centre_err_max: float
    """Largest centre error after alignment, in the truth's world units."""
    rot_err_mean: float
    centre_err_mean: float
    focal: float
    """SfM's shared focal length (full-resolution px)."""
    true_focal: float
    failure: str | None
    """Why the reconstruction is not usable (None: it is)."""


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
        pycolmap.extract_features(
            database,
            images,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=pycolmap.FeatureExtractionOptions(num_threads=SFM_THREADS),
            device=pycolmap.Device.cpu,
        )
        pycolmap.match_exhaustive(
            database,
            matching_options=pycolmap.FeatureMatchingOptions(num_threads=SFM_THREADS),
            device=pycolmap.Device.cpu,
        )
        models = pycolmap.incremental_mapping(database, images, work / "sparse", options=_mapping_options())
    if not models:
        return _failed(output, truth, "incremental mapping produced no model")
    best = max(models.values(), key=lambda model: model.num_reg_images())
    sparse = output / "sparse" / "0"
    sparse.mkdir(parents=True)
    best.write_binary(sparse)
    for extra in ("rigs.bin", "frames.bin"):  # the mip-NeRF 360 layout has three files
        (sparse / extra).unlink(missing_ok=True)
    return compare_with_truth(output, best, truth, len(models), check)


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


def compare_with_truth(output: Path, sfm, truth, models: int, check: SfmCheck) -> SfmResult:
    """Registration and similarity-aligned centre / rotation errors of ``sfm`` against ``truth``."""
    names = sorted(image.name for image in truth.images.values())
    registered = sorted(image.name for image in sfm.images.values() if image.has_pose)
    failure = None
    if registered != names:
        missing = sorted(set(names) - set(registered))
        failure = f"{len(registered)} of {len(names)} images registered (missing e.g. {missing[:3]})"
    elif len(sfm.cameras) != 1:
        failure = f"{len(sfm.cameras)} cameras instead of one shared camera"
    if failure is not None:
        return _failed(output, truth, failure, registered=len(registered), models=models, points=sfm.num_points3D())
    sfm_centres, sfm_rotations = _centres_and_rotations(sfm, names)
    true_centres, true_rotations = _centres_and_rotations(truth, names)
    similarity = umeyama(sfm_centres, true_centres)
    aligned_centres = similarity.apply_to_points(sfm_centres)
    centre_errors = (aligned_centres - true_centres).norm(dim=1)
    rotation_errors = rotation_angle(similarity.rotation @ sfm_rotations, true_rotations)
    radius = float((true_centres[:, :2] - true_centres[:, :2].mean(dim=0)).norm(dim=1).mean())
    if float(centre_errors.max()) > check.max_centre_error * radius:
        failure = (
            f"camera centre error {float(centre_errors.max()):.3g} after alignment exceeds "
            f"{check.max_centre_error:g} x ring radius {radius:.3g}"
        )
    elif float(rotation_errors.max()) > check.max_rotation_error:
        failure = f"rotation error {float(rotation_errors.max()):.3g} rad exceeds {check.max_rotation_error:g} rad"
    return SfmResult(
        scene=output,
        registered=len(registered),
        images=len(names),
        models=models,
        points=sfm.num_points3D(),
        rot_err_max=float(rotation_errors.max()),
        centre_err_max=float(centre_errors.max()),
        rot_err_mean=float(rotation_errors.mean()),
        centre_err_mean=float(centre_errors.mean()),
        focal=_focal(sfm),
        true_focal=_focal(truth),
        failure=failure,
    )


def _failed(output: Path, truth, failure: str, registered: int = 0, models: int = 0, points: int = 0) -> SfmResult:
    nan = float("nan")
    return SfmResult(
        scene=output,
        registered=registered,
        images=truth.num_images(),
        models=models,
        points=points,
        rot_err_max=nan,
        centre_err_max=nan,
        rot_err_mean=nan,
        centre_err_mean=nan,
        focal=nan,
        true_focal=_focal(truth),
        failure=failure,
    )
