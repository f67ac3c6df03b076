"""Keypoint refinement against the images (``tracks.keypoint_refinement``) on tracks made from a generated scene's
images (SIFT, matched and triangulated with the true cameras, not refined): the refined keypoints of a track agree with
each other; an image whose patches cannot be aligned keeps its detected keypoints; the caches know whether their
keypoints were refined.

Agreement is measured without the refinement's code: each track's point triangulated (linear, DLT) from its keypoints
through the true cameras, and the RMS distance of the keypoints from its projections.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image


@pytest.fixture(scope="module")
def textured_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """24 views of 320x240 of the generated scene, with tracks made from its images, detected keypoints, in
    ``tracks/`` (read-only)."""
    from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene
    from s2camp_ns.tracks.image_tracks import image_tracks

    folder = tmp_path_factory.mktemp("refinement") / "scene"
    make_scene(MakeSceneConfig(output_dir=folder, num_cameras=24, width=320, height=240, seed=2))
    given = pycolmap.Reconstruction(folder / "sparse" / "0")
    for point_id in list(given.point3D_ids()):
        given.delete_point3D(point_id)
    built = image_tracks(given, folder / "images", folder / "cache", refine_keypoints=False)
    assert built.model is not None, built.reason
    shutil.copytree(built.model, folder / "tracks")
    return folder


def detected_model(scene: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(scene / "tracks")


def keypoints(reconstruction: pycolmap.Reconstruction) -> dict[tuple[int, int], np.ndarray]:
    return {
        (image_id, index): np.array(point.xy)
        for image_id, image in reconstruction.images.items()
        for index, point in enumerate(image.points2D)
        if point.has_point3D()
    }


def track_disagreement(reconstruction: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> float:
    """Median over tracks of the RMS distance (px) of a track's keypoints from the projections of the point
    triangulated from them through the true cameras (undistorted by pycolmap's own camera model)."""
    spreads = []
    for point in reconstruction.points3D.values():
        rows, observed = [], []
        for element in point.track.elements:
            image = truth.images[element.image_id]
            camera = truth.cameras[image.camera_id]
            xy = reconstruction.images[element.image_id].points2D[element.point2D_idx].xy
            ray = camera.cam_from_img(np.asarray(xy, dtype=np.float64))  # normalized image coordinates
            pose = np.asarray(image.cam_from_world().matrix())
            rows += [ray[0] * pose[2] - pose[0], ray[1] * pose[2] - pose[1]]
            observed.append((camera, pose, xy))
        homogeneous = np.linalg.svd(np.asarray(rows))[2][-1]
        xyz = homogeneous[:3] / homogeneous[3]
        errors = [camera.img_from_cam(pose[:, :3] @ xyz + pose[:, 3]) - xy for camera, pose, xy in observed]
        spreads.append(float(np.sqrt(np.mean(np.square(errors)))))
    return float(np.median(spreads))


def test_refined_keypoints_agree_with_each_other_far_better_than_detected_ones(textured_scene: Path) -> None:
    from s2camp_ns.tracks.keypoint_refinement import refine_keypoints

    truth = pycolmap.Reconstruction(textured_scene / "sparse" / "0")
    reconstruction = detected_model(textured_scene)
    before = track_disagreement(reconstruction, truth)
    result = refine_keypoints(reconstruction, textured_scene / "images")
    after = track_disagreement(reconstruction, truth)
    assert result.refined > 0.8 * result.aligned, result
    assert before > 0.05 and after < 0.4 * before, (before, after)


def test_an_image_that_cannot_be_aligned_keeps_its_detected_keypoints(textured_scene: Path, tmp_path: Path) -> None:
    """One image replaced by a flat grey one (no gradient: no alignment converges or correlates): its keypoints stay
    bit for bit, and the others are still refined."""
    from s2camp_ns.tracks.keypoint_refinement import refine_keypoints

    images = tmp_path / "images"
    shutil.copytree(textured_scene / "images", images)
    reconstruction = detected_model(textured_scene)
    flat_id = sorted(reconstruction.images)[3]
    flat = images / reconstruction.images[flat_id].name
    with Image.open(flat) as picture:
        Image.new(picture.mode, picture.size, 128 if picture.mode == "L" else (128,) * len(picture.mode)).save(flat)
    detected = keypoints(reconstruction)
    result = refine_keypoints(reconstruction, images)
    refined = keypoints(reconstruction)
    kept = [key for key in detected if key[0] == flat_id]
    assert kept and all(np.array_equal(refined[key], detected[key]) for key in kept)
    moved = [key for key in detected if key[0] != flat_id and not np.array_equal(refined[key], detected[key])]
    assert result.refined == len(moved) > 0.5 * result.aligned


def test_a_missing_image_is_named(textured_scene: Path) -> None:
    from s2camp_ns.tracks.keypoint_refinement import refine_keypoints

    reconstruction = detected_model(textured_scene)
    missing = reconstruction.images[sorted(reconstruction.reg_image_ids())[0]].name
    with pytest.raises(FileNotFoundError, match=missing):
        refine_keypoints(reconstruction, Path("/nonexistent"))


def test_the_caches_know_whether_keypoints_were_refined(textured_scene: Path, tmp_path: Path) -> None:
    """The image tracks' key differs with and without refinement; the re-adjusted tracks' key also changes when an
    image changes (its refined keypoints would)."""
    from s2camp_ns.tracks import image_tracks, robust_adjustment

    model = textured_scene / "tracks"
    given = pycolmap.Reconstruction(model)
    root = textured_scene / "images"
    assert image_tracks.cache_key(given, root, True) != image_tracks.cache_key(given, root, False)
    files = [model / f"{kind}.bin" for kind in ("cameras", "images", "points3D")]
    images = tmp_path / "images"
    shutil.copytree(root, images)
    plain, refined = robust_adjustment.cache_key(files), robust_adjustment.cache_key(files, images)
    assert plain != refined
    first = images / sorted(path.name for path in images.iterdir())[0]
    first.write_bytes(first.read_bytes() + b"\0")
    assert robust_adjustment.cache_key(files, images) not in (plain, refined)


def test_sfm_tracks_are_refined_readjusted_and_cached_with_their_keypoints(
    textured_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An SfM model's tracks with the images (``robust_adjustment``): keypoints refined, every observation kept in
    order, read back bit for bit by the next process; without the images, the model's own keypoints."""
    from s2camp_ns.tracks import robust_adjustment

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    model = textured_scene / "tracks"
    robust_adjustment._cached.cache_clear()
    refined = robust_adjustment.readjusted_tracks(model, textured_scene / "images")
    detected = pycolmap.Reconstruction(model)
    assert sorted(refined.keypoints) == sorted(detected.reg_image_ids())
    moved = total = 0
    for image_id, xys in refined.keypoints.items():
        own = np.asarray([point.xy for point in detected.images[image_id].points2D])
        assert xys.shape == own.shape
        moved += int((np.abs(xys - own).max(axis=1) > 0).sum())
        total += sum(point.has_point3D() for point in detected.images[image_id].points2D)
    assert moved > 0.5 * total
    robust_adjustment._cached.cache_clear()  # a new process: read from the cache
    monkeypatch.setattr(pycolmap, "bundle_adjustment", lambda *args, **kwargs: pytest.fail("adjusted again"))
    again = robust_adjustment.readjusted_tracks(model, textured_scene / "images")
    assert all(np.array_equal(again.keypoints[i], refined.keypoints[i]) for i in refined.keypoints)
    assert all(np.array_equal(again.points[i], refined.points[i]) for i in refined.points)
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    robust_adjustment._cached.cache_clear()
    assert robust_adjustment.readjusted_tracks(model).keypoints == {}


def test_the_keypoints_are_refined_against_the_first_folder_holding_every_image(
    textured_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """Full-size images first, else the training images' folder (images_k); none: not refined, said once."""
    from s2camp_ns.tracks.track_evidence import keypoint_images

    model = textured_scene / "tracks"
    partial = tmp_path / "images"
    partial.mkdir()
    shutil.copy(next((textured_scene / "images").iterdir()), partial)
    assert keypoint_images(model, [partial, textured_scene / "images"]) == textured_scene / "images"
    assert keypoint_images(model, [partial, tmp_path / "images_2"]) is None
    assert "Keypoints not refined" in " ".join(capsys.readouterr().err.split())
    assert keypoint_images(tmp_path / "no model", [textured_scene / "images"]) is None
