"""s2camp-make-scene: layout, COLMAP model, image sizes, track consistency, scene record, input validation."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from s2camp_bench.scene.make_scene import MakeSceneConfig, make_camera, make_scene, validate


def _cam_from_world(image: pycolmap.Image) -> np.ndarray:
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return pose.matrix()


def test_layout_and_camera(tiny_scene: Path, tiny_scene_config: MakeSceneConfig) -> None:
    cfg = tiny_scene_config
    assert sorted(p.name for p in (tiny_scene / "sparse" / "0").iterdir()) == [
        "cameras.bin",
        "images.bin",
        "points3D.bin",
    ]
    rec = pycolmap.Reconstruction(tiny_scene / "sparse" / "0")
    assert rec.num_cameras() == 1
    assert rec.num_images() == cfg.num_cameras
    camera = rec.cameras[1]
    focal, cx, cy = validate(cfg)
    assert camera.model.name == "RADIAL"
    assert (camera.width, camera.height) == (cfg.width, cfg.height)
    np.testing.assert_allclose(camera.params, [focal, cx, cy, cfg.k1, cfg.k2], rtol=1e-12)
    # narrow preset: 52 degrees horizontal field of view
    assert np.degrees(2 * np.arctan(cfg.width / 2 / camera.params[0])) == pytest.approx(52.0)

    names = sorted(image.name for image in rec.images.values())
    for folder, size in (("images", (cfg.width, cfg.height)), ("images_2", (cfg.width // 2, cfg.height // 2))):
        assert sorted(p.name for p in (tiny_scene / folder).iterdir()) == names
        for name in names:
            with Image.open(tiny_scene / folder / name) as img:
                assert img.size == size and img.mode == "RGB"


def test_images_are_textured_and_half_res_is_box_downsample(tiny_scene: Path) -> None:
    name = sorted(p.name for p in (tiny_scene / "images").iterdir())[0]
    full = np.asarray(Image.open(tiny_scene / "images" / name), dtype=np.float64)
    half = np.asarray(Image.open(tiny_scene / "images_2" / name), dtype=np.float64)
    h, w = half.shape[:2]
    box = full.reshape(h, 2, w, 2, 3).mean(axis=(1, 3))
    assert np.abs(box - half).max() <= 1.0  # both quantized to 8 bits from the same float image
    assert full.std() > 20.0  # not a flat image
    assert np.abs(np.diff(full, axis=1)).mean() > 5.0  # high-frequency detail for photometric refinement


def test_tracks_reproject(tiny_scene: Path) -> None:
    rec = pycolmap.Reconstruction(tiny_scene / "sparse" / "0")
    assert rec.num_points3D() > 200
    camera = rec.cameras[1]
    poses = {image_id: _cam_from_world(image) for image_id, image in rec.images.items()}
    worst = 0.0
    for point_id, point in rec.points3D.items():
        assert point.track.length() >= 2
        for element in point.track.elements:
            image = rec.images[element.image_id]
            point2d = image.points2D[element.point2D_idx]
            assert point2d.point3D_id == point_id
            in_cam = poses[element.image_id] @ np.append(point.xyz, 1.0)
            assert in_cam[2] > 0
            worst = max(worst, float(np.linalg.norm(camera.img_from_cam(in_cam) - point2d.xy)))
    assert worst < 0.5
    for image in rec.images.values():
        assert image.num_points3D > 0


def test_scene_info(tiny_scene: Path, tiny_scene_config: MakeSceneConfig) -> None:
    cfg = tiny_scene_config
    rec = pycolmap.Reconstruction(tiny_scene / "sparse" / "0")
    info = json.loads((tiny_scene / "scene_info.json").read_text())
    assert info["config"]["num_cameras"] == cfg.num_cameras
    assert info["camera"]["model"] == "RADIAL"
    np.testing.assert_allclose(info["camera"]["params"], rec.cameras[1].params)
    for entry in info["images"]:
        np.testing.assert_allclose(entry["cam_from_world"], _cam_from_world(rec.images[entry["image_id"]]), atol=1e-12)


def test_pinhole_when_undistorted(tmp_path: Path) -> None:
    cfg = MakeSceneConfig(output_dir=tmp_path / "s", num_cameras=12, width=64, height=48, k1=0.0, k2=0.0, fov="wide")
    make_scene(cfg)
    rec = pycolmap.Reconstruction(tmp_path / "s" / "sparse" / "0")
    camera = rec.cameras[1]
    assert camera.model.name == "PINHOLE"
    assert np.degrees(2 * np.arctan(32 / camera.params[0])) == pytest.approx(80.0)
    # The tracks were generated without distortion: a plain pinhole projection, written out here, reproduces them.
    fx, fy, cx, cy = camera.params
    worst = 0.0
    for point in rec.points3D.values():
        for element in point.track.elements:
            image = rec.images[element.image_id]
            x, y, z = _cam_from_world(image) @ np.append(point.xyz, 1.0)
            observed = image.points2D[element.point2D_idx].xy
            worst = max(worst, float(np.hypot(fx * x / z + cx - observed[0], fy * y / z + cy - observed[1])))
    assert rec.num_points3D() > 0 and worst < 0.5
    # regenerating into a scene directory replaces it (telling each image rendered, as the command prints it); a
    # foreign non-empty directory is refused
    told: list[tuple[int, int]] = []
    make_scene(dataclasses.replace(cfg, num_cameras=3), lambda done, total: told.append((done, total)))
    assert len(list((tmp_path / "s" / "images").iterdir())) == 3
    assert told == [(1, 3), (2, 3), (3, 3)]
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="output_dir"):
        make_scene(dataclasses.replace(cfg, output_dir=tmp_path / "foreign"))


def test_unprojection_is_consistent_with_colmap(tiny_scene_config: MakeSceneConfig) -> None:
    camera = make_camera(tiny_scene_config)
    u, v = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    normalized = camera.cam_from_img(pixels)
    back = camera.img_from_cam(np.concatenate([normalized, np.ones((len(pixels), 1))], axis=1))
    assert np.abs(back - pixels).max() < 1e-6


MODELS = {
    "SIMPLE_PINHOLE": dict(k1=0.0, k2=0.0),
    "SIMPLE_RADIAL": dict(k1=-0.03, k2=0.0),
    "OPENCV": dict(k1=-0.03, k2=0.004, p1=0.002, p2=-0.0015),
    "FULL_OPENCV": dict(k1=-0.03, k2=0.004, k3=0.001, p1=0.002, p2=-0.0015),
    "OPENCV_FISHEYE": dict(k1=0.02, k2=-0.004, k3=0.001, k4=-0.0002, fov="wide"),
}


@pytest.mark.parametrize("model", list(MODELS))
def test_each_camera_model_is_written_and_self_consistent(tmp_path: Path, model: str) -> None:
    cfg = MakeSceneConfig(
        output_dir=tmp_path / "s", num_cameras=3, width=32, height=24, points_per_image=20, camera_model=model,
        **MODELS[model],
    )  # fmt: skip
    make_scene(cfg)
    camera = pycolmap.Reconstruction(tmp_path / "s" / "sparse" / "0").cameras[1]
    assert camera.model.name == model
    focal, cx, cy = validate(cfg)
    coefficients = {name: getattr(cfg, name) for name in ("k1", "k2", "k3", "k4", "p1", "p2")}
    expected = {
        "SIMPLE_PINHOLE": [focal, cx, cy],
        "SIMPLE_RADIAL": [focal, cx, cy, cfg.k1],
        "OPENCV": [focal, focal, cx, cy, cfg.k1, cfg.k2, cfg.p1, cfg.p2],
        "FULL_OPENCV": [focal, focal, cx, cy, cfg.k1, cfg.k2, cfg.p1, cfg.p2, cfg.k3, 0.0, 0.0, 0.0],
        "OPENCV_FISHEYE": [focal, focal, cx, cy, cfg.k1, cfg.k2, cfg.k3, cfg.k4],
    }[model]
    np.testing.assert_allclose(camera.params, expected, rtol=1e-12)
    info = json.loads((tmp_path / "s" / "scene_info.json").read_text())
    assert {name: info["camera"][name] for name in coefficients} == coefficients
    if model == "OPENCV_FISHEYE":  # equidistant: the wide preset's 80 degrees span the image width
        assert np.degrees(cfg.width / camera.params[0]) == pytest.approx(80.0)
    u, v = np.meshgrid(np.arange(cfg.width) + 0.5, np.arange(cfg.height) + 0.5)
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    normalized = camera.cam_from_img(pixels)
    back = camera.img_from_cam(np.concatenate([normalized, np.ones((len(pixels), 1))], axis=1))
    assert np.abs(back - pixels).max() < 1e-6


@pytest.mark.parametrize(
    ("change", "pattern"),
    [
        ({"num_cameras": 1}, r"num_cameras must lie in \[2, inf\), got 1"),
        ({"width": 0}, r"width must lie in \[8, 8192\], got 0"),
        ({"height": -4}, r"height must lie in \[8, 8192\], got -4"),
        ({"width": 65}, r"width must be even"),
        ({"focal": 0.0}, r"focal must lie in \(0, inf\), got 0.0"),
        ({"focal": -10.0}, r"focal must lie in \(0, inf\)"),
        ({"k1": -0.5, "k2": 0.0}, r"k1, k2 = \(-0.5, 0\) .*make the radial distortion non-monotonic"),
        ({"k1": 0.0, "k2": -0.3, "fov": "wide"}, r"k1, k2 = \(0, -0.3\) .*make the radial distortion non-monotonic"),
        ({"principal_point": (70.0, 24.0)}, r"principal_point\[0\] \(cx\) must lie in \(0, 64\), got 70.0"),
        ({"ring_radius": 1.0}, r"ring_radius must lie in"),
        ({"fov": "fisheye"}, r"fov must be one of 'narrow', 'wide', got 'fisheye'"),
        ({"p1": 0.001}, r"COLMAP RADIAL has no p1, but the camera's p1 = 0.001"),
        ({"camera_model": "FOV"}, r"camera_model must be one of 'auto', 'SIMPLE_PINHOLE'"),
        ({"camera_model": "OPENCV_FISHEYE", "focal": 15.0}, r"fisheye corner angle .* must lie in \(-inf, 85"),
    ],
)
def test_bad_input_raises(tmp_path: Path, change: dict, pattern: str) -> None:
    cfg = dataclasses.replace(MakeSceneConfig(output_dir=tmp_path / "s", num_cameras=4, width=64, height=48), **change)
    with pytest.raises(ValueError, match=pattern):
        make_scene(cfg)
    assert not (tmp_path / "s").exists()  # validation happens before anything is written


def test_cli_help() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "s2camp_bench.scene.make_scene", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    for option in ("--output-dir", "--num-cameras", "--k1", "--fov", "--seed"):
        assert option in result.stdout
