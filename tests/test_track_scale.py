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


def _model(folder: Path, images: Path, keypoint_scale: float = 1.0) -> dict[str, np.ndarray]:
    """A COLMAP model of one PINHOLE camera at full size whose keypoints are exact projections plus N(0, NOISE_PX)
    noise, times ``keypoint_scale`` (1: the cameras' pixels); returns each image's noise [M, 2] (full-size pixels).
    Writes the rounded images_4 folder."""
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
        keypoints = (pixels + noise[name]) * keypoint_scale
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=image_id)
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
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    scene, noise = rounded_scene
    config = S2CampDataParserConfig(
        data=scene, downscale_factor=4, eval_mode="all", image_tracks="never", refine_keypoints=False  # exact tracks
    )
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
    from s2camp_ns.core.camera import ParameterLayout
    from s2camp_ns.core.track_fit import fit_anchor
    from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    scene, _ = rounded_scene
    config = S2CampDataParserConfig(
        data=scene, downscale_factor=4, eval_mode="all", image_tracks="never", refine_keypoints=False  # exact tracks
    )
    outputs = config.setup().get_dataparser_outputs("train")
    evidence = outputs.metadata["track_evidence"]
    intrinsics = intrinsics_from_cameras(outputs.cameras)
    shared = torch.zeros(NUM_IMAGES, dtype=torch.long)
    fit = fit_anchor(evidence.tracks, evidence.c2w, intrinsics, ParameterLayout.from_preset("all").indices, shared)
    assert fit.intrinsics_held is not None and bool(fit.intrinsics_held.all())


def test_a_model_whose_keypoints_are_at_another_scale_is_refused_by_name(tmp_path: Path) -> None:
    """Keypoints left at the resolution SfM ran on (a quarter of the cameras' declared size, as after rescaling
    cameras.bin by hand): the given cameras miss their tracks by hundreds of pixels, and the model is refused."""
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    scene = tmp_path / "edited"
    (scene / "images").mkdir(parents=True)
    _model(scene / "sparse" / "0", scene / "images_4", keypoint_scale=0.25)
    config = S2CampDataParserConfig(
        data=scene, downscale_factor=4, eval_mode="all", image_tracks="never", refine_keypoints=False  # exact tracks
    )
    with pytest.raises(ValueError) as refused:
        config.setup().get_dataparser_outputs("train")
    message = " ".join(str(refused.value).split())
    assert str(scene / "sparse" / "0" / "images.bin") in message
    assert "the model's own cameras miss their tracks by" in message and "median over 6 images; worst" in message
    assert "far more than SfM leaves (at most 10 px): check that the keypoints and the cameras" in message
    assert "pass s2camp-data --image-tracks always (tracks made from the images) or --tracks False" in message
    median = float(message.split("miss their tracks by ")[1].split(" px")[0])
    assert 100.0 < median < 2000.0  # hundreds of pixels at the model's 3114 px
    without = S2CampDataParserConfig(data=scene, downscale_factor=4, eval_mode="all", tracks=False)
    assert "track_evidence" not in without.setup().get_dataparser_outputs("train").metadata  # the way out


def test_the_refusal_threshold_is_in_the_model_s_pixels() -> None:
    from s2camp_ns.tracks.colmap_tracks import MAX_SFM_TRACK_RMS_PX, check_sfm_track_rms

    width, model_width = torch.tensor([779.0, 779.0, 779.0]), torch.full((3,), 3114.0)
    # 2.4 px at 779 px are 9.6 px at 3114: accepted; 2.6 px are 10.4 px: refused (median of the three).
    check_sfm_track_rms(torch.tensor([2.4, 2.4, float("nan")]), width, model_width, Path("images.bin"), "x")
    with pytest.raises(ValueError, match=r"images.bin: .* by 10.39 px \(median over 3 images; worst 10.39 px"):
        check_sfm_track_rms(torch.tensor([2.6, 2.6, 2.6]), width, model_width, Path("images.bin"), "x")
    assert MAX_SFM_TRACK_RMS_PX == 10.0
