"""The SfM check of the sfm start (benchmarks/s2camp_bench/sfm.py) on models derived from a generated scene's true
cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from s2camp_bench.sfm import SfmCheck, compare_with_truth, initial_camera_params, run_sfm

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
    result = compare_with_truth(tmp_path, _moved(tiny_scene), _truth(tiny_scene), SfmCheck())
    assert result.failure is None
    assert result.registered == result.images == 12
    assert result.centre_err_max < 1e-9 and result.rot_err_max < 1e-9
    assert result.focal == pytest.approx(result.true_focal)


def test_missing_image_fails(tiny_scene: Path, tmp_path: Path):
    sfm = _moved(tiny_scene)
    sfm.deregister_frame(next(iter(sfm.frames)))
    result = compare_with_truth(tmp_path, sfm, _truth(tiny_scene), SfmCheck())
    assert result.failure is not None and "11 of 12 images registered" in result.failure


def test_displaced_camera_fails_the_centre_check(tiny_scene: Path, tmp_path: Path):
    sfm = _truth(tiny_scene)
    image = next(iter(sfm.images.values()))
    pose = image.cam_from_world()
    # Move one centre by 0.2 x the ring radius along the camera's x axis (t = -R c).
    moved = pycolmap.Rigid3d(pose.rotation, pose.translation - np.array([0.2 * RING_RADIUS, 0.0, 0.0]))
    sfm.frames[image.frame_id].rig_from_world = moved
    result = compare_with_truth(tmp_path, sfm, _truth(tiny_scene), SfmCheck())
    assert result.failure is not None and "camera centre error" in result.failure
    loose = compare_with_truth(tmp_path, sfm, _truth(tiny_scene), SfmCheck(max_centre_error=0.5))
    assert loose.failure is None and 0.05 * RING_RADIUS < loose.centre_err_max < 0.2 * RING_RADIUS


def test_initial_camera_params_are_simple_radial_s_at_the_image_centre():
    assert initial_camera_params(190.0, 320, 240) == "190.0,160.0,120.0,0.0"
    assert initial_camera_params(95.5, 161, 120) == "95.5,80.5,60.0,0.0"


def test_a_focal_prior_outside_its_range_is_refused_before_anything_runs(tiny_scene: Path, tmp_path: Path):
    with pytest.raises(ValueError, match="focal_prior"):
        run_sfm(tiny_scene, tmp_path / "sfm", focal_prior=0.0)
    assert not (tmp_path / "sfm").exists()
