"""Structure from motion on a generated scene (pycolmap SIFT, exhaustive matching, incremental mapping).

``run_sfm`` writes a scene folder that ``ns-train`` reads like the generated one: the same ``images/`` and
``images_2/`` (symbolic links) and ``sparse/0`` = the SfM model, whose image names are the truth's. One shared camera
(``CameraMode.SINGLE``) of the chosen COLMAP model. COLMAP's log lines go to ``sfm.log`` in the output folder.

``focal_prior`` plays the EXIF focal length a real capture carries: the mapper starts from that factor times the true
focal length instead of COLMAP's guess for images without EXIF (1.2 x max(W, H), twice the generated wide scene's
true focal length). From that guess SfM of the wide scene ends several times further from the truth in rotation,
centres and focal length than from an EXIF-like prior 5% off (measured in docs/benchmarks/recovery.md, tier 3, "What
the SfM table shows").

``local_refinement_check`` asks whether SfM's error is something local refinement can remove: bundle adjustment with
the true camera model from SfM's result, and SfM's tracks reprojected under SfM's and under the true cameras.

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
from s2camp_ns.core.validation import check_choice, check_range
from s2camp_ns.tracks.colmap_log import colmap_log_to

SFM_CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV")
"""Shared camera models of the SfM start (both map onto S2CamP's intrinsics; OPENCV's p1, p2 are zeroed)."""


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


def initial_camera_params(camera_model: str, focal: float, width: int, height: int) -> str:
    """COLMAP's ``camera_params`` string for a start at ``focal`` (pixels), principal point at the image centre and
    no distortion, in the parameter order of ``camera_model``."""
    cx, cy = width / 2.0, height / 2.0
    values = {
        "SIMPLE_RADIAL": (focal, cx, cy, 0.0),
        "OPENCV": (focal, focal, cx, cy, 0.0, 0.0, 0.0, 0.0),
    }[camera_model]
    return ",".join(repr(float(value)) for value in values)


def run_sfm(
    scene: Path,
    output: Path,
    camera_model: str = "SIMPLE_RADIAL",
    check: SfmCheck = SfmCheck(),
    focal_prior: float | None = None,
) -> SfmResult:
    """SfM on ``scene/images`` into ``output`` (module docstring); compared with ``scene/sparse/0``. ``focal_prior``:
    the mapper's initial focal length as a factor of the true one (None: COLMAP's guess without EXIF)."""
    import pycolmap

    check_choice("camera_model", camera_model, SFM_CAMERA_MODELS)
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
    reader = pycolmap.ImageReaderOptions(camera_model=camera_model)
    if focal_prior is not None:
        camera = next(iter(truth.cameras.values()))
        reader.camera_params = initial_camera_params(
            camera_model, focal_prior * camera.focal_length_x, camera.width, camera.height
        )
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
    if camera_model == "OPENCV":
        for camera in best.cameras.values():  # S2CamP refines radial k1, k2 only; p1, p2 were free in the mapper
            params = camera.params.copy()
            params[6:8] = 0.0
            camera.params = params
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


LOCAL_REFINEMENT_ITERATIONS = 1000
"""Iteration cap of the diagnostic bundle adjustment (every tolerance zero: it stops when no step lowers the cost)."""


def triangulated_reprojection_errors(sfm, reference) -> np.ndarray:
    """Reprojection error (px) of every observation of ``sfm``'s SIFT tracks under ``reference``'s cameras (matched by
    image name), each 3D point triangulated from its track by linear least squares (DLT) with those cameras."""
    camera_and_pose = {
        image.name: (reference.cameras[image.camera_id], np.asarray(image.cam_from_world().matrix()))
        for image in reference.images.values()
    }
    errors = []
    for point in sfm.points3D.values():
        rows, observations = [], []
        for element in point.track.elements:
            image = sfm.images[element.image_id]
            pixel = np.asarray(image.points2D[element.point2D_idx].xy, dtype=np.float64)
            camera, pose = camera_and_pose[image.name]
            ray = np.asarray(camera.cam_from_img(pixel))
            rows += [ray[0] * pose[2] - pose[0], ray[1] * pose[2] - pose[1]]
            observations.append((pixel, pose, camera))
        homogeneous = np.linalg.svd(np.stack(rows))[2][-1]
        position = homogeneous[:3] / homogeneous[3]
        for pixel, pose, camera in observations:
            projected = np.asarray(camera.img_from_cam(pose[:, :3] @ position + pose[:, 3]))
            errors.append(float(np.linalg.norm(projected - pixel)))
    return np.asarray(errors)


def _with_camera_model(reconstruction, model: str):
    """A copy of ``reconstruction`` whose SIMPLE_RADIAL cameras become ``model`` = RADIAL (k becomes k1, k2 = 0); any
    other camera is kept (OPENCV already has RADIAL's k1, k2)."""
    import pycolmap

    copy = pycolmap.Reconstruction(reconstruction)
    for camera_id, camera in copy.cameras.items():
        if (camera.model.name, model) != ("SIMPLE_RADIAL", "RADIAL"):
            continue
        params = [*camera.params, 0.0]
        copy.cameras[camera_id] = pycolmap.Camera(
            model=model, width=camera.width, height=camera.height, params=params, camera_id=camera_id
        )
    return copy


def local_refinement_check(scene: Path, sfm_scene: Path, check: SfmCheck = SfmCheck()) -> dict[str, float]:
    """Can local refinement reach the truth from SfM's cameras? Bundle adjustment of the SfM model with the true
    camera model (RADIAL for a SIMPLE_RADIAL start; an OPENCV start keeps its model, which contains RADIAL), no
    tolerance, until no step lowers the cost, and its errors against the truth; beside them the median and
    root-mean-square reprojection errors of SfM's tracks under SfM's cameras and under the true ones (points
    triangulated for both). Bundle adjustment minimizes the squared errors, so a few tracks the true cameras cannot
    fit (mismatched or poorly localised keypoints) can hold SfM's cameras away from the truth although the truth fits
    most observations better."""
    import pycolmap

    truth = pycolmap.Reconstruction(scene / "sparse" / "0")
    sfm = pycolmap.Reconstruction(sfm_scene / "sparse" / "0")
    adjusted = _with_camera_model(sfm, next(iter(truth.cameras.values())).model.name)
    options = pycolmap.BundleAdjustmentOptions()
    solver = options.ceres.solver_options
    solver.max_num_iterations = LOCAL_REFINEMENT_ITERATIONS
    solver.function_tolerance = solver.gradient_tolerance = solver.parameter_tolerance = 0.0
    with colmap_log_to(sfm_scene / "sfm.log"):
        pycolmap.bundle_adjustment(adjusted, options)
    after = compare_with_truth(sfm_scene, adjusted, truth, 1, check)
    errors = {"sfm": triangulated_reprojection_errors(sfm, sfm), "truth": triangulated_reprojection_errors(sfm, truth)}
    return {
        **{f"{name}_reprojection_median_px": float(np.median(value)) for name, value in errors.items()},
        **{f"{name}_reprojection_rms_px": float(np.sqrt(np.mean(value**2))) for name, value in errors.items()},
        "ba_rot_err_mean": after.rot_err_mean,
        "ba_centre_err_mean": after.centre_err_mean,
        "ba_focal": after.focal,
    }
