"""The SfM check of recovery tier 3 (benchmarks/s2camp_bench/sfm.py) on models derived from a generated scene's true cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from s2camp_bench.sfm import (
    SfmCheck,
    _with_camera_model,
    compare_with_truth,
    initial_camera_params,
    local_refinement_check,
    run_sfm,
    triangulated_reprojection_errors,
)

RING_RADIUS = 4.0  # MakeSceneConfig's default


def _truth(scene: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(scene / "sparse" / "0"))


def _moved(scene: Path) -> pycolmap.Reconstruction:
    """The truth in another world frame (what SfM returns at best: its gauge is arbitrary)."""
    model = _truth(scene)
    rotation = pycolmap.Rotation3d(np.array([0.2, 0.1, -0.4, 0.8]) / np.linalg.norm([0.2, 0.1, -0.4, 0.8]))
    model.transform(pycolmap.Sim3d(0.3, rotation, np.array([1.0, 2.0, -3.0])))
    return model


def test_truth_in_another_frame_passes_with_zero_errors(tiny_scene: Path, tmp_path: Path):
    result = compare_with_truth(tmp_path, _moved(tiny_scene), _truth(tiny_scene), 1, SfmCheck())
    assert result.failure is None
    assert result.registered == result.images == 12
    assert result.centre_err_max < 1e-9 and result.rot_err_max < 1e-9
    assert result.focal == pytest.approx(result.true_focal)


def test_missing_image_fails(tiny_scene: Path, tmp_path: Path):
    sfm = _moved(tiny_scene)
    sfm.deregister_frame(next(iter(sfm.frames)))
    result = compare_with_truth(tmp_path, sfm, _truth(tiny_scene), 1, SfmCheck())
    assert result.failure is not None and "11 of 12 images registered" in result.failure


def test_displaced_camera_fails_the_centre_check(tiny_scene: Path, tmp_path: Path):
    sfm = _truth(tiny_scene)
    image = next(iter(sfm.images.values()))
    pose = image.cam_from_world()
    # Move one centre by 0.2 x the ring radius along the camera's x axis (t = -R c).
    moved = pycolmap.Rigid3d(pose.rotation, pose.translation - np.array([0.2 * RING_RADIUS, 0.0, 0.0]))
    sfm.frames[image.frame_id].rig_from_world = moved
    result = compare_with_truth(tmp_path, sfm, _truth(tiny_scene), 1, SfmCheck())
    assert result.failure is not None and "camera centre error" in result.failure
    loose = compare_with_truth(tmp_path, sfm, _truth(tiny_scene), 1, SfmCheck(max_centre_error=0.5))
    assert loose.failure is None and 0.05 * RING_RADIUS < loose.centre_err_max < 0.2 * RING_RADIUS


def test_initial_camera_params_follow_each_model_s_parameter_order():
    assert initial_camera_params("SIMPLE_RADIAL", 190.0, 320, 240) == "190.0,160.0,120.0,0.0"
    assert initial_camera_params("OPENCV", 95.5, 161, 120) == "95.5,95.5,80.5,60.0,0.0,0.0,0.0,0.0"


def test_a_focal_prior_outside_its_range_is_refused_before_anything_runs(tiny_scene: Path, tmp_path: Path):
    with pytest.raises(ValueError, match="focal_prior"):
        run_sfm(tiny_scene, tmp_path / "sfm", focal_prior=0.0)
    assert not (tmp_path / "sfm").exists()


def test_widening_simple_radial_to_radial_keeps_its_parameters_and_adds_k2_zero():
    model = pycolmap.Reconstruction()
    model.add_camera(pycolmap.Camera(model="SIMPLE_RADIAL", width=64, height=48, params=[50.0, 32.0, 24.0, -0.03]))
    widened = _with_camera_model(model, "RADIAL")
    (camera,) = widened.cameras.values()
    assert camera.model.name == "RADIAL"
    assert camera.params.tolist() == [50.0, 32.0, 24.0, -0.03, 0.0]
    assert next(iter(model.cameras.values())).model.name == "SIMPLE_RADIAL"  # the input is left alone
    opencv = pycolmap.Reconstruction()
    opencv.add_camera(pycolmap.Camera(model="OPENCV", width=64, height=48, params=[50.0, 50.0, 32.0, 24.0] + [0.0] * 4))
    (kept,) = _with_camera_model(opencv, "RADIAL").cameras.values()  # OPENCV already has RADIAL's k1, k2
    assert kept.model.name == "OPENCV" and kept.params.tolist() == [50.0, 50.0, 32.0, 24.0] + [0.0] * 4


def test_tracks_reproject_exactly_under_their_own_cameras_and_not_under_moved_ones(tiny_scene: Path):
    truth = _truth(tiny_scene)
    exact = triangulated_reprojection_errors(truth, truth)
    assert exact.shape == (truth.compute_num_observations(),)
    assert exact.max() < 1e-6  # the generated points are exact projections
    moved = _truth(tiny_scene)
    for image in list(moved.images.values())[::2]:  # every other camera turned by 0.01 rad about its y axis
        pose = image.cam_from_world()
        turn = pycolmap.Rotation3d(np.array([0.0, np.sin(0.005), 0.0, np.cos(0.005)]))
        moved.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(turn * pose.rotation, turn * pose.translation)
    # a 0.01 rad turn moves a pixel by about f x 0.01 (f ~ 50 px): triangulation spreads it over the track
    assert 0.05 < triangulated_reprojection_errors(truth, moved).mean() < 1.0


def test_local_refinement_from_the_truth_stays_at_the_truth(tiny_scene: Path, tmp_path: Path):
    sfm_scene = tmp_path / "sfm"
    (sfm_scene / "sparse" / "0").mkdir(parents=True)
    _moved(tiny_scene).write_binary(str(sfm_scene / "sparse" / "0"))
    check = local_refinement_check(tiny_scene, sfm_scene)
    for key in ("reprojection_median_px", "reprojection_rms_px"):
        assert check[f"sfm_{key}"] < 1e-6 and check[f"truth_{key}"] < 1e-6
    assert check["ba_rot_err_mean"] < 1e-6 and check["ba_centre_err_mean"] < 1e-6
    assert check["ba_focal"] == pytest.approx(next(iter(_truth(tiny_scene).cameras.values())).focal_length_x)
