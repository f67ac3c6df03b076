"""The anchor's fit (``core.track_fit``) against pycolmap's bundle adjustment where the two do the same job: every 3D
point fixed, the same Cauchy loss and scale, the poses free (and one focal length of a SIMPLE_RADIAL camera). pycolmap
is the independent reference: it makes the observations (its own projection) and fits them with Ceres; and, with the
plain loss, it shows what the robust loss buys against a few wrong matches."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pycolmap
import pytest
import torch

from s2camp_ns.core import track_fit
from s2camp_ns.core.camera import se3_exp
from s2camp_ns.core.colmap_camera_models import intrinsics_from_colmap
from s2camp_ns.core.perturbation import look_at_rotation
from s2camp_ns.core.track_fit import fit_cameras_to_tracks
from s2camp_ns.core.tracks import Tracks

WIDTH, HEIGHT = 640, 480
NUM_IMAGES = 6
RADIUS = 3.0
"""Distance of the cameras from the scene's centre: the scene's size for the centres' tolerance."""
NOISE_PX = 0.5
OUTLIERS_PER_IMAGE = 3
ROTATION_TOLERANCE = 1e-8
"""Radians between our and pycolmap's rotation of each camera."""
CENTRE_TOLERANCE = 1e-8 * RADIUS
"""Scene units between our and pycolmap's centre of each camera."""
FOCAL_TOLERANCE_PX = 1e-6
"""Pixels between our and pycolmap's focal length."""


@dataclass(frozen=True)
class _Scene:
    model: str
    params: list[float]
    points: np.ndarray  # [P, 3]
    truth: np.ndarray  # [N, 3, 4] OpenCV c2w
    given: np.ndarray  # [N, 3, 4] the truth perturbed: where both fits start
    image: np.ndarray  # [O] observing image
    point: np.ndarray  # [O] observed point
    pixels: np.ndarray  # [O, 2] pycolmap's projection of the truth, Gaussian noise and a few outliers added
    outlier: np.ndarray  # [O] the observations moved 50-200 px


def _ring(n: int) -> np.ndarray:
    angle = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    eye = torch.stack([RADIUS * angle.cos(), RADIUS * angle.sin(), 0.5 + 0.2 * angle], dim=-1)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
    return torch.cat([look_at_rotation(eye, torch.zeros_like(eye), up), eye[:, :, None]], dim=-1).numpy()


def _scene(model: str, params: list[float], seed: int = 0) -> _Scene:
    """Random points seen by a ring of cameras (one shared COLMAP camera), observed through pycolmap's projection."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.8, 0.8, (300, 3))
    truth = _ring(NUM_IMAGES)
    camera = pycolmap.Camera(model=model, width=WIDTH, height=HEIGHT, params=params)
    image, point, pixels = [], [], []
    for i in range(NUM_IMAGES):
        local = (points - truth[i, :, 3]) @ truth[i, :, :3]
        uv = camera.img_from_cam(local)
        inside = (local[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < WIDTH) & (uv[:, 1] > 0) & (uv[:, 1] < HEIGHT)
        seen = np.flatnonzero(inside)
        image.append(np.full(seen.shape, i))
        point.append(seen)
        pixels.append(uv[seen] + rng.normal(0.0, NOISE_PX, (seen.size, 2)))
    image, point, pixels = np.concatenate(image), np.concatenate(point), np.concatenate(pixels)
    outlier = np.zeros(image.shape, dtype=bool)
    for i in range(NUM_IMAGES):
        outlier[rng.choice(np.flatnonzero(image == i), OUTLIERS_PER_IMAGE, replace=False)] = True
    angle = rng.uniform(0.0, 2 * math.pi, outlier.sum())
    pixels[outlier] += rng.uniform(50.0, 200.0, outlier.sum())[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    twist = torch.as_tensor(rng.normal(0.0, 1.0, (NUM_IMAGES, 6)) * [0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
    given = _moved(torch.as_tensor(truth), twist).numpy()
    return _Scene(model, params, points, truth, given, image, point, pixels, outlier)


def _moved(c2w: torch.Tensor, twist: torch.Tensor) -> torch.Tensor:
    """c2w exp(xi), the camera optimizer's pose update."""
    motion = se3_exp(twist)
    return torch.cat([c2w[:, :, :3] @ motion[:, :, :3], c2w[:, :, 3:] + c2w[:, :, :3] @ motion[:, :, 3:]], dim=-1)


def _ours(scene: _Scene, params: list[float], free: tuple[int, ...], outliers: bool = True):
    """Our fit from the given cameras with the intrinsics ``params``: refined c2w [N, 3, 4] and the fit."""
    keep = np.ones_like(scene.outlier) if outliers else ~scene.outlier
    tracks = Tracks(
        torch.as_tensor(scene.points),
        torch.as_tensor(scene.image[keep]),
        torch.as_tensor(scene.point[keep]),
        torch.as_tensor(scene.pixels[keep]),
    )
    intrinsics = intrinsics_from_colmap(scene.model, params, WIDTH, HEIGHT)[torch.zeros(NUM_IMAGES, dtype=torch.long)]
    given = torch.as_tensor(scene.given)
    fit = fit_cameras_to_tracks(tracks, given, intrinsics, free, torch.zeros(NUM_IMAGES, dtype=torch.long))
    return _moved(given, fit.deltas[:, :6]).numpy(), fit


def _pycolmap(scene: _Scene, params: list[float], refine_focal: bool, loss: pycolmap.LossFunctionType):
    """pycolmap's bundle adjustment from the given cameras, every point constant: refined c2w [N, 3, 4], camera."""
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model=scene.model, width=WIDTH, height=HEIGHT, params=params, camera_id=1)
    reconstruction.add_camera_with_trivial_rig(camera)
    track_of: dict[int, list[tuple[int, int]]] = {}
    for i in range(NUM_IMAGES):
        rows = np.flatnonzero(scene.image == i)
        rotation = scene.given[i, :, :3].T
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ scene.given[i, :, 3])
        image = pycolmap.Image(name=f"{i}.png", keypoints=scene.pixels[rows], camera_id=1, image_id=i + 1)
        reconstruction.add_image_with_trivial_frame(image, pose)
        for index, row in enumerate(rows):
            track_of.setdefault(int(scene.point[row]), []).append((i + 1, index))
    config = pycolmap.BundleAdjustmentConfig()
    for i in range(NUM_IMAGES):
        config.add_image(i + 1)
    for point, elements in sorted(track_of.items()):
        track = pycolmap.Track()
        for image_id, index in elements:
            track.add_element(image_id, index)
        config.add_constant_point(reconstruction.add_point3D(scene.points[point], track))
    if not refine_focal:
        config.set_constant_cam_intrinsics(1)
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=refine_focal, refine_principal_point=False, refine_extra_params=False, print_summary=False
    )
    options.ceres.loss_function_type = loss
    options.ceres.loss_function_scale = track_fit.LOSS_SCALE_PX
    solver = options.ceres.solver_options
    solver.function_tolerance, solver.gradient_tolerance, solver.parameter_tolerance = 1e-15, 1e-15, 1e-15
    solver.max_num_iterations = 500
    summary = pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    assert summary.is_solution_usable()
    c2w = []
    for i in range(NUM_IMAGES):
        world_to_camera = np.asarray(reconstruction.images[i + 1].cam_from_world().matrix())
        rotation = world_to_camera[:, :3].T
        c2w.append(np.concatenate([rotation, -rotation @ world_to_camera[:, 3:]], axis=1))
    return np.stack(c2w), reconstruction.cameras[1]


def _rotation_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between the rotations of the c2w matrices a and b [N, 3, 4], accurate when small."""
    relative = a[:, :, :3].transpose(0, 2, 1) @ b[:, :, :3]
    skew = relative - relative.transpose(0, 2, 1)
    axis = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=-1) / 2.0
    return np.arctan2(np.linalg.norm(axis, axis=-1), (np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0)


def _centre_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a[:, :, 3] - b[:, :, 3], axis=-1)


OPENCV = [500.0, 490.0, 322.0, 236.0, -0.05, 0.01, 0.001, -0.0005]  # fx, fy, cx, cy, k1, k2, p1, p2
SIMPLE_RADIAL = [480.0, 318.0, 243.0, -0.04]  # f, cx, cy, k


def test_the_bundle_adjustments_of_tracks_use_the_anchor_fits_cauchy_loss() -> None:
    from s2camp_ns.tracks.robust_adjustment import cauchy_adjustment_options

    options = cauchy_adjustment_options(refine_focal_length=False, refine_principal_point=False)
    assert options.ceres.loss_function_type == pycolmap.LossFunctionType.CAUCHY
    assert options.ceres.loss_function_scale == track_fit.LOSS_SCALE_PX == 1.0
    assert (options.refine_focal_length, options.refine_principal_point) == (False, False)
    assert options.refine_extra_params  # fields not given keep pycolmap's defaults


def test_robust_pose_fit_agrees_with_pycolmaps_bundle_adjustment() -> None:
    scene = _scene("OPENCV", OPENCV)
    ours, fit = _ours(scene, OPENCV, tuple(range(6)))
    reference, camera = _pycolmap(scene, OPENCV, refine_focal=False, loss=pycolmap.LossFunctionType.CAUCHY)
    assert np.allclose(camera.params, OPENCV, rtol=0, atol=0)  # held by both
    assert _rotation_error(scene.given, reference).min() > 1e-3  # both moved the cameras, from the same start
    assert _rotation_error(ours, reference).max() < ROTATION_TOLERANCE
    assert _centre_error(ours, reference).max() < CENTRE_TOLERANCE
    assert float(fit.observations.sum()) == scene.image.size  # every observation counts, outliers too


def test_robust_pose_and_focal_fit_agrees_with_pycolmaps_bundle_adjustment() -> None:
    # A SIMPLE_* camera has one focal length, our layout's focal column (added to fx and fy); the given one is 2% off.
    scene = _scene("SIMPLE_RADIAL", SIMPLE_RADIAL, seed=1)
    given = [SIMPLE_RADIAL[0] * 1.02, *SIMPLE_RADIAL[1:]]
    ours, fit = _ours(scene, given, tuple(range(7)))
    reference, camera = _pycolmap(scene, given, refine_focal=True, loss=pycolmap.LossFunctionType.CAUCHY)
    assert np.allclose(camera.params[1:], given[1:], rtol=0, atol=0)  # principal point and k held
    assert abs(camera.params[0] - given[0]) > 5.0  # pycolmap did refit the focal length
    assert float((given[0] + fit.deltas[:, 6] - camera.params[0]).abs().max()) < FOCAL_TOLERANCE_PX
    assert _rotation_error(ours, reference).max() < ROTATION_TOLERANCE
    assert _centre_error(ours, reference).max() < CENTRE_TOLERANCE


@pytest.mark.parametrize("seed", [0, 2])
def test_wrong_matches_barely_move_the_robust_fit_and_pull_a_plain_one(seed: int) -> None:
    scene = _scene("OPENCV", OPENCV, seed=seed)
    noise_only, _ = _ours(scene, OPENCV, tuple(range(6)), outliers=False)
    robust, _ = _ours(scene, OPENCV, tuple(range(6)))
    plain, _ = _pycolmap(scene, OPENCV, refine_focal=False, loss=pycolmap.LossFunctionType.TRIVIAL)
    baseline = _rotation_error(noise_only, scene.truth).max(), _centre_error(noise_only, scene.truth).max()
    errors = {
        "robust": (_rotation_error(robust, scene.truth).max(), _centre_error(robust, scene.truth).max()),
        "plain": (_rotation_error(plain, scene.truth).max(), _centre_error(plain, scene.truth).max()),
    }
    assert errors["robust"][0] < 3.0 * baseline[0] and errors["robust"][1] < 3.0 * baseline[1]
    # Three matches 50-200 px off among an image's 300 pull plain least squares (pycolmap's, the same problem with
    # the trivial loss) an order of magnitude further than the keypoint noise does.
    assert errors["plain"][0] > 8.0 * baseline[0] and errors["plain"][1] > 8.0 * baseline[1]
