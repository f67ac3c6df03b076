"""Keypoints, cameras and image sizes in one convention for a rounded downscaled folder (mip-NeRF 360's images_4:
3114 x 2075 -> 779 x 519, per-axis ratios 779 / 3114 and 519 / 2075, not 1 / 4).

The model's keypoints are exact projections through its own cameras plus known noise, so the RMS each camera must
have against its own tracks at the training size is computed here from that noise alone, scaled by the folder's
ratios: no code of the package computes the expectation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

FULL = (3114, 2075)
ROUNDED = (779, 519)  # round(3114 / 4), round(2075 / 4), as mip-NeRF 360's images_4
FOCAL, CX, CY = 2600.0, 1557.0, 1037.5
NOISE_PX = 0.4
NUM_IMAGES, NUM_POINTS = 6, 150


def _look_at(centre: np.ndarray) -> np.ndarray:
    """World -> camera rotation of an OpenCV camera at ``centre`` looking at the origin (y down, world z up)."""
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def _model(folder: Path, images: Path) -> dict[str, np.ndarray]:
    """A COLMAP model of one PINHOLE camera at full size whose keypoints are exact projections plus N(0, NOISE_PX)
    noise; returns each image's noise [M, 2] (full-size pixels). Writes the rounded images_4 folder."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.6, 0.6, size=(NUM_POINTS, 3))
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="PINHOLE", width=FULL[0], height=FULL[1], params=[FOCAL, FOCAL, CX, CY],
                             camera_id=1)  # fmt: skip
    reconstruction.add_camera_with_trivial_rig(camera)
    noise, observed = {}, {index: [] for index in range(NUM_POINTS)}
    images.mkdir(parents=True)
    for image_id in range(1, NUM_IMAGES + 1):
        angle = 2.0 * math.pi * image_id / NUM_IMAGES
        centre = np.array([4.0 * math.cos(angle), 4.0 * math.sin(angle), 0.5])
        rotation = _look_at(centre)
        camera_points = (points - centre) @ rotation.T  # [P, 3]
        pixels = FOCAL * camera_points[:, :2] / camera_points[:, 2:] + np.array([CX, CY])
        inside = (pixels > 0).all(axis=1) & (pixels < np.array(FULL)).all(axis=1)
        assert inside.all(), "every point must be seen by every camera"
        name = f"frame_{image_id:03d}.png"
        noise[name] = rng.normal(0.0, NOISE_PX, size=pixels.shape)
        image = pycolmap.Image(name=name, keypoints=pixels + noise[name], camera_id=1, image_id=image_id)
        world_to_camera = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre)
        reconstruction.add_image_with_trivial_frame(image, world_to_camera)
        for index in range(NUM_POINTS):
            observed[index].append(pycolmap.TrackElement(image_id, index))
        Image.new("RGB", ROUNDED, (128, 128, 128)).save(images / name)
    for index in range(NUM_POINTS):
        reconstruction.add_point3D(points[index], pycolmap.Track(observed[index]), np.zeros(3, np.uint8))
    folder.mkdir(parents=True)
    reconstruction.write_binary(str(folder))
    for extra in ("rigs.bin", "frames.bin"):
        (folder / extra).unlink(missing_ok=True)
    return noise


@pytest.fixture(scope="module")
def rounded_scene(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray]]:
    scene = tmp_path_factory.mktemp("rounded")
    (scene / "images").mkdir()  # the full-size folder exists; the parser reads images_4 only
    noise = _model(scene / "sparse" / "0", scene / "images_4")
    return scene, noise


def test_given_cameras_miss_their_tracks_by_the_full_size_noise_times_the_folder_ratio(rounded_scene) -> None:
    from s2camp_ns.nerfstudio.dataparser import S2CampDataParserConfig

    scene, noise = rounded_scene
    config = S2CampDataParserConfig(data=scene, downscale_factor=4, eval_mode="all", image_tracks="never")
    outputs = config.setup().get_dataparser_outputs("train")
    sx, sy = ROUNDED[0] / FULL[0], ROUNDED[1] / FULL[1]
    assert outputs.cameras.fx[:, 0].double() == pytest.approx(FOCAL * sx, rel=1e-6)  # the intrinsics kept
    assert outputs.cameras.cy[:, 0].double() == pytest.approx(CY * sy, rel=1e-6)
    names = outputs.metadata["image_names"]
    expected = [math.sqrt(np.mean((noise[name] * [sx, sy]) ** 2) * 2.0) for name in names]
    measured = outputs.metadata["track_rms_px"].tolist()
    # float32 cameras: agreement to a thousandth of the noise. Keypoints divided by 4 instead would be off by
    # (779 / 3114 - 1 / 4) u, up to 0.5 px at the right border, several times the noise.
    assert measured == pytest.approx(expected, rel=2e-3)


def test_the_anchor_keeps_the_given_intrinsics_of_a_rounded_folder(rounded_scene) -> None:
    from s2camp_ns.camera_optimizer import intrinsics_from_cameras
    from s2camp_ns.core.camera import ParameterLayout
    from s2camp_ns.core.track_fit import fit_anchor
    from s2camp_ns.nerfstudio.dataparser import S2CampDataParserConfig

    scene, _ = rounded_scene
    config = S2CampDataParserConfig(data=scene, downscale_factor=4, eval_mode="all", image_tracks="never")
    outputs = config.setup().get_dataparser_outputs("train")
    evidence = outputs.metadata["track_evidence"]
    intrinsics = intrinsics_from_cameras(outputs.cameras)
    shared = torch.zeros(NUM_IMAGES, dtype=torch.long)
    fit = fit_anchor(evidence.tracks, evidence.c2w, intrinsics, ParameterLayout.from_preset("all").indices, shared)
    assert fit.intrinsics_held is not None and bool(fit.intrinsics_held.all())
