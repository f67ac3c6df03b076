"""Tracks made from a scene's images (``s2camp_ns.tracks.image_tracks``): they bring noisy cameras near the truth,
are cached, refuse what cannot anchor cameras, and reach the data parser's track evidence."""

from __future__ import annotations

import copy
import io
import math
import os
import re
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from s2camp_ns.core.alignment import camera_errors
from s2camp_ns.data.image_check import ImageFileError
from s2camp_ns.tracks import image_tracks as module
from s2camp_ns.tracks.image_tracks import cache_key, image_tracks, neighbour_pairs

ROTATION_NOISE = 0.01
"""Per-axis rotation noise of the given cameras (rad): about one degree in all, a phone's visual-inertial poses."""
CENTRE_NOISE = 0.02
"""Per-axis centre noise (scene units; the ring radius is 4)."""
FOCAL_FACTOR = 1.02
"""The given focal length, 2% long."""


@pytest.fixture(scope="module")
def textured_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """32 images of 320x240, 80 degrees (about 20 s). Smaller scenes track too little to test against: 16 images of
    160x120 give 14 points, and 24 of 240x180 about 500, whose bundle adjustment ends 0.3 degrees from the truth with
    centres further off than the noise."""
    from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

    folder = tmp_path_factory.mktemp("image_tracks") / "scene"
    return make_scene(MakeSceneConfig(output_dir=folder, num_cameras=32, width=320, height=240, fov="wide", seed=0))


def _given(truth: pycolmap.Reconstruction, rotation=ROTATION_NOISE, centre=CENTRE_NOISE, focal=FOCAL_FACTOR):
    """The truth's images with noisy poses and a scaled focal length, and no points."""
    rng = np.random.default_rng(0)
    given = pycolmap.Reconstruction()
    camera = copy.copy(truth.cameras[1])
    params = camera.params.copy()
    params[0] *= focal
    camera.params = params
    given.add_camera_with_trivial_rig(camera)
    for image in sorted(truth.images.values(), key=lambda image: image.name):
        world_to_camera = image.cam_from_world()
        centre_true = -(world_to_camera.rotation.inverse() * world_to_camera.translation)
        rotation_noisy = pycolmap.Rotation3d(rng.normal(0.0, rotation, 3)) * world_to_camera.rotation
        centre_noisy = centre_true + rng.normal(0.0, centre, 3)
        noisy = pycolmap.Rigid3d(rotation_noisy, -(rotation_noisy * centre_noisy))
        given.add_image_with_trivial_frame(pycolmap.Image(name=image.name, camera_id=1, image_id=image.image_id), noisy)
    return given


def _c2w_and_focal(reconstruction: pycolmap.Reconstruction, names: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
    by_name = {image.name: image for image in reconstruction.images.values()}
    c2w, focal = [], []
    for name in names:
        image = by_name[name]
        c2w.append(np.asarray(image.cam_from_world().inverse().matrix()))
        focal.append(reconstruction.cameras[image.camera_id].focal_length_x)
    return torch.tensor(np.stack(c2w)), torch.tensor(focal, dtype=torch.float64)


def _errors(reconstruction, truth) -> dict[str, float]:
    names = sorted(image.name for image in reconstruction.images.values())
    c2w, focal = _c2w_and_focal(reconstruction, names)
    true_c2w, true_focal = _c2w_and_focal(truth, names)
    return camera_errors(c2w, true_c2w, focal, true_focal, align=True)


def test_tracks_bring_noisy_cameras_near_the_truth_and_keep_the_given_frame(textured_scene: Path, tmp_path: Path):
    truth = pycolmap.Reconstruction(textured_scene / "sparse" / "0")
    given = _given(truth)
    result = image_tracks(given, textured_scene / "images", tmp_path / "cache")
    assert result.model is not None, result.reason
    made = pycolmap.Reconstruction(result.model)
    before, after = _errors(given, truth), _errors(made, truth)
    assert math.degrees(before["rot_err_mean"]) > 0.8
    assert after["rot_err_mean"] < 0.25 * before["rot_err_mean"]
    assert after["pos_err_mean"] < 0.5 * before["pos_err_mean"]
    assert after["focal_err_mean"] < 0.25 * before["focal_err_mean"]  # 2% = 2.9 px before
    assert all(image.num_points3D >= 10 for image in made.images.values())
    # The similarity keeps the given world: centres stay within a few noise sigmas of the given ones.
    names = sorted(image.name for image in given.images.values())
    made_c2w, _ = _c2w_and_focal(made, names)
    given_c2w, _ = _c2w_and_focal(given, names)
    assert float((made_c2w[:, :, 3] - given_c2w[:, :, 3]).norm(dim=1).max()) < 5 * math.sqrt(3) * CENTRE_NOISE
    assert "points" in result.summary and "focal length" in result.summary and "; built in " in result.summary


def test_a_second_call_reads_the_cache_and_any_change_of_input_is_another_key(
    textured_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    truth = pycolmap.Reconstruction(textured_scene / "sparse" / "0")
    given = _given(truth)
    first = image_tracks(given, textured_scene / "images", tmp_path)
    assert [path.name for path in tmp_path.iterdir()] == [first.model.name]  # no temporary folder left

    def fail(*args, **kwargs):
        raise AssertionError("the cache was rebuilt")

    monkeypatch.setattr(module, "_build", fail)
    again = image_tracks(given, textured_scene / "images", tmp_path)
    assert (again.model, again.summary) == (first.model, first.summary)

    key = cache_key(given, textured_scene / "images")
    moved = pycolmap.Reconstruction(given)
    image = next(iter(moved.images.values()))
    pose = image.cam_from_world()
    translation = pose.translation.copy()
    translation[0] = np.nextafter(translation[0], np.inf)
    moved.frame(image.frame_id).set_cam_from_world(image.camera_id, pycolmap.Rigid3d(pose.rotation, translation))
    assert cache_key(moved, textured_scene / "images") != key
    images = tmp_path / "images"
    images.mkdir()
    for file in (textured_scene / "images").iterdir():
        (images / file.name).write_bytes(file.read_bytes())
    stat = (images / image.name).stat()
    keys = {cache_key(given, images)}
    os.utime(images / image.name, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1))
    keys.add(cache_key(given, images))
    assert len(keys) == 2


def test_images_too_small_to_track_give_no_tracks_with_the_reason_and_the_failure_is_cached(
    tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    truth = pycolmap.Reconstruction(tiny_scene / "sparse" / "0")
    given = _given(truth, rotation=0.0, centre=0.0, focal=1.0)
    result = image_tracks(given, tiny_scene / "images", tmp_path)
    assert result.model is None
    assert result.reason is not None
    assert result.reason.startswith("no point could be triangulated from the images' matched features")
    assert str(tmp_path) in result.reason  # where COLMAP's log is
    monkeypatch.setattr(module, "_build", lambda *args: pytest.fail("the failed build was repeated"))
    assert image_tracks(given, tiny_scene / "images", tmp_path).reason == result.reason


def test_cameras_far_from_their_tracks_are_refused(textured_scene: Path):
    """``_implausible`` against the scene's own tracked model: the truth passes; cameras turned by 20 degrees, or
    moved by half the ring, are refused with the measured change."""
    truth = pycolmap.Reconstruction(textured_scene / "sparse" / "0")
    assert module._implausible(truth, truth) is None
    turned = _given(truth, rotation=math.radians(20.0) / math.sqrt(3.0), centre=0.0, focal=1.0)
    assert "turn the cameras by" in module._implausible(turned, truth)
    moved = _given(truth, rotation=0.0, centre=2.0, focal=1.0)
    assert "move the camera centres by" in module._implausible(moved, truth)
    sparse = pycolmap.Reconstruction(truth)
    for point_id in sorted(sparse.points3D)[5:]:  # 5 points left: no image sees 10
        sparse.delete_point3D(point_id)
    reason = module._implausible(truth, sparse)
    assert reason is not None and "only 0 of 32 images see at least 10 tracked points (5 points in all)" in reason


def test_a_missing_image_and_an_unwritable_cache_are_named(textured_scene: Path, tmp_path: Path):
    truth = pycolmap.Reconstruction(textured_scene / "sparse" / "0")
    given = _given(truth)
    with pytest.raises(FileNotFoundError, match=r"image '.*nowhere/frame_00000\.png' does not exist \(32 of 32"):
        image_tracks(given, tmp_path / "nowhere", tmp_path / "cache")
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OSError, match=r"cannot write the image tracks' cache folder .*file/cache.*image-tracks-cache"):
        image_tracks(given, textured_scene / "images", blocker / "cache")


def _line_of_cameras(count: int) -> pycolmap.Reconstruction:
    """``count`` cameras 1 unit apart along x, all looking along +z, except the last, which looks along -z."""
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=100, height=100, params=[50.0, 50.0, 50.0, 50.0], camera_id=1)
    )
    for i in range(count):
        rotation = pycolmap.Rotation3d(np.array([0.0, math.pi, 0.0]) if i == count - 1 else np.zeros(3))
        pose = pycolmap.Rigid3d(rotation, -(rotation * np.array([float(i), 0.0, 0.0])))
        image = pycolmap.Image(name=f"{i:03d}.png", camera_id=1, image_id=i + 1)
        reconstruction.add_image_with_trivial_frame(image, pose)
    return reconstruction


def test_neighbour_pairs_join_nearest_cameras_that_face_alike(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(module, "NEIGHBOURS", 2)
    pairs = neighbour_pairs(_line_of_cameras(6))
    # Each camera's two nearest: 000 -> 001, 002; 001 -> 000, 002; 002 -> 001, 003; 003 -> 002, 004; 004 -> 003, 002.
    expected = {("000.png", "001.png"), ("000.png", "002.png"), ("001.png", "002.png"), ("002.png", "003.png"),
                ("002.png", "004.png"), ("003.png", "004.png")}  # fmt: skip
    assert set(pairs) == expected  # 005 looks the other way: no pair
    assert pairs == sorted(pairs)


def test_the_data_parser_uses_image_tracks_where_asked(textured_scene: Path, tmp_path: Path):
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    def evidence(**options):
        config = S2CampDataParserConfig(data=textured_scene, downscale_factor=2, image_tracks_cache=tmp_path, **options)
        return config.setup()._generate_dataparser_outputs("train").metadata.get("track_evidence")

    scene_points = pycolmap.Reconstruction(textured_scene / "sparse" / "0").num_points3D()
    own = evidence()  # the scene has tracks: auto keeps them and makes none
    assert own.tracks.points.shape[0] == scene_points
    assert not any(tmp_path.iterdir())
    made = evidence(image_tracks="always")
    (folder,) = tmp_path.iterdir()
    assert made.tracks.points.shape[0] == pycolmap.Reconstruction(folder).num_points3D() != scene_points
    # Pixels at the training resolution (images_2): inside the 160x120 training images, not only their top-left quarter.
    assert 120 < float(made.tracks.pixels[:, 0].max()) <= 160 and 90 < float(made.tracks.pixels[:, 1].max()) <= 120
    assert evidence(tracks=False) is None
    assert evidence(tracks=False, image_tracks="always") is None


def test_a_transforms_json_without_tracks_gets_them_from_its_full_size_images(textured_scene: Path, tmp_path: Path):
    """A hand-made transforms.json (no COLMAP model beside it) trained at images_2: auto makes tracks from the
    full-size images its frames name; never leaves the scene without tracks."""
    import json

    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    data = tmp_path / "scene"
    data.mkdir()
    for folder in ("images", "images_2"):
        (data / folder).symlink_to(textured_scene / folder, target_is_directory=True)
    truth = pycolmap.Reconstruction(textured_scene / "sparse" / "0")
    frames = []
    for image in sorted(truth.images.values(), key=lambda image: image.name):
        c2w = np.asarray(image.cam_from_world().inverse().matrix())
        c2w[:, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": [*c2w.tolist(), [0, 0, 0, 1]]})
    f, cx, cy, k1, k2 = truth.cameras[1].params
    content = {"camera_model": "OPENCV", "fl_x": f, "fl_y": f, "cx": cx, "cy": cy, "w": 320, "h": 240}
    (data / "transforms.json").write_text(json.dumps({**content, "k1": k1, "k2": k2, "frames": frames}))

    def parse(**options):
        config = S2CampDataParserConfig(data=data / "transforms.json", downscale_factor=2, **options)
        return config.setup()._generate_dataparser_outputs("train").metadata

    assert "track_evidence" not in parse(image_tracks="never")
    metadata = parse()
    evidence = metadata["track_evidence"]
    (folder,) = (data / "s2camp_image_tracks").iterdir()
    made = pycolmap.Reconstruction(folder)
    assert evidence.tracks.points.shape[0] == made.num_points3D() > 100
    assert sorted(image.name for image in made.images.values()) == sorted(
        Path(name).name for name in metadata["image_names"]
    )
    # Every training image is fitted: each sees at least 10 tracked points, and its RMS is the tracks' noise.
    rms = metadata["track_rms_px"]
    assert bool(torch.isfinite(rms).all()) and float(rms.max()) < 1.0


def test_an_image_that_cannot_be_decoded_is_named_before_the_build(tiny_scene: Path, tmp_path: Path):
    """COLMAP skips an image it cannot decode (the scene then had no tracks, for a reason in a note): the build
    decodes every image first and stops, naming it, and caches nothing."""
    images = tmp_path / "images"
    images.mkdir()
    for file in (tiny_scene / "images").iterdir():
        (images / file.name).write_bytes(file.read_bytes())
    (images / "frame_00003.png").write_bytes(b"not a png")
    truth = pycolmap.Reconstruction(tiny_scene / "sparse" / "0")
    pattern = rf"^image {re.escape(str(images / 'frame_00003.png'))}, listed by the scene \(image tracks\), cannot be"
    with pytest.raises(ImageFileError, match=pattern):
        image_tracks(_given(truth, rotation=0.0, centre=0.0, focal=1.0), images, tmp_path / "cache")
    assert not [path for path in (tmp_path / "cache").iterdir() if not path.name.startswith(".")]


@pytest.mark.parametrize(
    ("has_cuda", "device_present", "expected", "notice"),
    [
        (True, True, "cuda", False),
        (False, True, "cpu", True),
        (True, False, "cpu", False),
        (False, False, "cpu", False),
    ],
)
def test_sift_runs_on_cuda_only_where_pycolmap_has_it_and_a_device_is_present(
    monkeypatch: pytest.MonkeyPatch, has_cuda: bool, device_present: bool, expected: str, notice: bool
):
    monkeypatch.setattr(pycolmap, "has_cuda", has_cuda)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: device_present)
    device, text = module.feature_device()
    assert device == getattr(pycolmap.Device, expected)
    assert (text is not None) == notice
    if notice:
        assert "s2camp-ns[gpu]" in text and "\n" not in text


class _Stop(Exception):
    """Ends a build once the calls under test were made."""


def test_the_device_reaches_extraction_and_matching_and_not_the_cache_key(
    tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture
):
    given = _given(pycolmap.Reconstruction(tiny_scene / "sparse" / "0"), rotation=0.0, centre=0.0, focal=1.0)
    key = cache_key(given, tiny_scene / "images")
    devices = []
    extract = pycolmap.extract_features

    def extract_on_the_cpu(*args, device, **kwargs):
        devices.append(("extract", device))
        extract(*args, device=pycolmap.Device.cpu, **kwargs)

    def match(*args, device, **kwargs):
        devices.append(("match", device))
        raise _Stop

    monkeypatch.setattr(pycolmap, "extract_features", extract_on_the_cpu)
    monkeypatch.setattr(pycolmap, "match_exhaustive", match)
    monkeypatch.setattr(module, "feature_device", lambda: (pycolmap.Device.cuda, "a notice"))
    monkeypatch.setattr(pycolmap, "has_cuda", True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    with pytest.raises(_Stop):
        image_tracks(given, tiny_scene / "images", tmp_path)
    assert devices == [("extract", pycolmap.Device.cuda), ("match", pycolmap.Device.cuda)]
    output = capfd.readouterr().err
    assert "SIFT and matching on the GPU" in output and "a notice" in output
    assert cache_key(given, tiny_scene / "images") == key
    assert not any(tmp_path.iterdir())  # the interrupted build left nothing


def _pinhole(width: int, height: int, focal: float, camera_id: int = 1) -> pycolmap.Camera:
    params = [focal, focal, width / 2, height / 2]
    return pycolmap.Camera(model="PINHOLE", width=width, height=height, params=params, camera_id=camera_id)


@pytest.mark.parametrize(
    ("width", "height", "focal", "keypoint_px", "given_px"),
    [
        (64, 48, 50.0, 4.0, 4.0),  # 2 degrees are 1.7 px: COLMAP's 4 px bound the keypoints
        (320, 240, 190.0, 4.0, 6.632),  # 80 degrees wide
        (1920, 1440, 1300.0, 4.8, 45.379),  # a phone: SIFT sees it at 1600 px
        (4000, 3000, 3000.0, 10.0, 104.720),
    ],
)
def test_thresholds_grow_with_the_extraction_downsampling_and_the_focal_length(
    width: int, height: int, focal: float, keypoint_px: float, given_px: float
):
    given = pycolmap.Reconstruction()
    given.add_camera_with_trivial_rig(_pinhole(width, height, focal))
    thresholds = module.Thresholds.of(given)
    assert thresholds.keypoint_px == pytest.approx(keypoint_px)
    assert thresholds.given_px == pytest.approx(given_px, abs=1e-3)
    given.add_camera_with_trivial_rig(_pinhole(width // 2, height // 2, focal / 2, camera_id=2))
    assert module.Thresholds.of(given) == thresholds  # the camera that needs the loosest bound sets it


def _cameras(centres, rotations) -> pycolmap.Reconstruction:
    """Cameras at ``centres`` with world-to-camera ``rotations`` (3x3 each), named 000.png, 001.png, ..."""
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(_pinhole(100, 100, 50.0))
    for i, (centre, matrix) in enumerate(zip(centres, rotations, strict=True)):
        rotation = pycolmap.Rotation3d(np.asarray(matrix, dtype=np.float64))
        pose = pycolmap.Rigid3d(rotation, -(rotation * np.asarray(centre, dtype=np.float64)))
        reconstruction.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{i:03d}.png", camera_id=1, image_id=i + 1), pose
        )
    return reconstruction


def test_neighbour_pairs_prefer_a_camera_that_faces_alike_to_a_nearer_one_turned_away(monkeypatch: pytest.MonkeyPatch):
    """000 and 002 face +z, 1.5 apart; 001, 1 from 000, is turned 80 degrees: it counts (2 - cos 80) = 1.83 times as
    far, 1.83 from 000 (so 000 matches 002) and 0.91 from 002."""
    monkeypatch.setattr(module, "NEIGHBOURS", 1)
    turned = np.asarray(pycolmap.Rotation3d(np.array([0.0, math.radians(80.0), 0.0])).matrix())
    reconstruction = _cameras([[0, 0, 0], [1, 0, 0], [1.5, 0, 0]], [np.eye(3), turned, np.eye(3)])
    assert neighbour_pairs(reconstruction) == [("000.png", "002.png"), ("001.png", "002.png")]


def _ring(count: int, radius: float = 4.0) -> pycolmap.Reconstruction:
    """``count`` cameras evenly on a horizontal ring, each looking at its centre."""
    centres, rotations = [], []
    for angle in np.linspace(0.0, 2.0 * math.pi, count, endpoint=False):
        centre = radius * np.array([math.cos(angle), math.sin(angle), 0.0])
        axis = -centre / radius
        down = np.array([0.0, 0.0, -1.0])
        centres.append(centre)
        rotations.append(np.stack([np.cross(down, axis), down, axis]))
    return _cameras(centres, rotations)


def test_neighbour_pairs_are_near_linear_in_the_images_and_do_not_depend_on_the_rows_ranked_at_once(
    monkeypatch: pytest.MonkeyPatch,
):
    ring = _ring(300)
    pairs = neighbour_pairs(ring)
    assert len(pairs) == len(set(pairs)) == 300 * module.NEIGHBOURS // 2  # each camera's 15 on either side
    per_image = {}
    for a, b in pairs:
        assert a < b
        per_image[a] = per_image.get(a, 0) + 1
        per_image[b] = per_image.get(b, 0) + 1
    assert set(per_image.values()) == {module.NEIGHBOURS}
    assert ("000.png", "015.png") in pairs and ("000.png", "016.png") not in pairs and ("000.png", "285.png") in pairs
    monkeypatch.setattr(module, "PAIR_ROWS", 7)
    assert neighbour_pairs(ring) == pairs


def test_a_build_shows_its_stages_with_counts_and_times(tiny_scene: Path, tmp_path: Path, capfd: pytest.CaptureFixture):
    """stderr is no terminal under pytest: one line per finished stage, then the breakdown (the tiny scene's images
    give no points, so the build ends after the first triangulation)."""
    given = _given(pycolmap.Reconstruction(tiny_scene / "sparse" / "0"), rotation=0.0, centre=0.0, focal=1.0)
    result = image_tracks(given, tiny_scene / "images", tmp_path)
    output = capfd.readouterr().err
    assert list(result.stage_seconds) == ["SIFT", "matching", "triangulation"]  # the entry keeps its cost
    assert all(seconds > 0.0 for seconds in result.stage_seconds.values())
    assert image_tracks(given, tiny_scene / "images", tmp_path).stage_seconds == result.stage_seconds  # cached
    assert "Making image tracks of 12 images (64x48) for the track prior, SIFT and matching on the CPU" in output
    assert re.search(r"\n  SIFT features: \d+ keypoints \(12/12 images, [0-9.]+ s\)\n", output)
    assert re.search(r"\n  matching, every pair: \d+ verified \(4\.0 px\), \d+ inlier matches \(66/66 pairs, ", output)
    assert re.search(
        r"\n  triangulation 1/4, given cameras \(4\.0 px\): 0 points, 0 observations \([0-9.]+ s\)", output
    )
    assert re.search(
        r"\nImage tracks built: SIFT [0-9.]+ s, matching [0-9.]+ s, triangulation [0-9.]+ s, total ", output
    )


def test_build_progress_lines_without_a_terminal_and_the_breakdown_by_kind():
    from rich.console import Console

    from s2camp_ns.tracks.build_progress import BuildProgress

    console = Console(file=io.StringIO(), width=200)
    with BuildProgress("Built", console=console) as progress:
        with progress.stage("counting", "count", 3, "things", lambda: 2) as stage:
            stage.outcome = "three things"
        for _ in range(2):
            with progress.stage("waiting", "wait"):
                pass
    text = console.file.getvalue()
    assert re.search(r"^  counting: three things \(3/3 things, [0-9.]+ s\)$", text, re.MULTILINE)
    assert len(re.findall(r"^  waiting \([0-9.]+ s\)$", text, re.MULTILINE)) == 2
    assert re.search(r"^Built: count [0-9.]+ s, wait [0-9.]+ s \(2\), total [0-9.]+ s$", text, re.MULTILINE)
    with pytest.raises(_Stop), BuildProgress("Built", console=console) as progress:
        raise _Stop
    assert console.file.getvalue().count("Built:") == 1  # no breakdown of a build that raised


def test_build_progress_on_a_terminal_shows_the_count_read_while_the_stage_runs(monkeypatch: pytest.MonkeyPatch):
    import threading

    from rich.console import Console

    from s2camp_ns.tracks import build_progress

    monkeypatch.setattr(build_progress, "POLL_SECONDS", 0.01)
    console = Console(file=io.StringIO(), width=200, force_terminal=True)
    reads = []
    read_twice = threading.Event()

    def count():
        reads.append(None)
        if len(reads) >= 2:
            read_twice.set()
        return None if len(reads) == 1 else 7  # unreadable first, then more than the total

    progress = build_progress.BuildProgress("Built", console=console)
    with progress, progress.stage("reading", "read", 5, "rows", count):
        assert read_twice.wait(5.0)
        time.sleep(0.3)  # rich redraws 10 times a second
        (task,) = progress._progress.tasks
        assert task.completed == 5 and task.fields["count"] == "5/5 rows"  # clipped to the total
    text = console.file.getvalue()
    assert "0/5 rows" in text and "5/5 rows" in text and "✓" in text
    assert re.search(r"Built: read [0-9.]+ s, total", text)


def test_database_count_reads_rows_or_says_it_cannot(tmp_path: Path):
    import sqlite3

    from s2camp_ns.tracks.build_progress import database_count, duration_text

    database = tmp_path / "database.db"
    assert database_count(database, "keypoints") is None
    connection = sqlite3.connect(database)
    connection.execute("CREATE TABLE two_view_geometries (rows INTEGER)")
    connection.executemany("INSERT INTO two_view_geometries VALUES (?)", [(0,), (12,), (30,)])
    connection.commit()
    connection.close()
    assert database_count(database, "two_view_geometries") == 3
    assert database_count(database, "two_view_geometries", "rows > 0") == 2
    assert database_count(database, "keypoints") is None  # no such table yet
    assert [duration_text(s) for s in (0.42, 12.4, 185.0, 3720.0)] == ["0.4 s", "12 s", "3 min 05 s", "1 h 02 min"]


def test_the_database_counter_reads_in_another_process_while_this_one_writes(tmp_path: Path):
    """A live stage's count comes from a child process (two SQLite libraries in one process break each other's locks:
    a bus error in COLMAP), follows the rows as they are committed, and the child is gone after the block."""
    import sqlite3

    from s2camp_ns.tracks.build_progress import DatabaseCounter

    database = tmp_path / "database.db"
    connection = sqlite3.connect(database)
    connection.execute("PRAGMA journal_mode=WAL")  # as COLMAP's database
    connection.execute("CREATE TABLE keypoints (image_id INTEGER)")
    connection.commit()
    with DatabaseCounter(database, "keypoints") as count:
        child = count._child
        assert child.pid != os.getpid()
        for rows in (1, 2, 3):
            connection.execute("INSERT INTO keypoints VALUES (?)", (rows,))
            connection.commit()
            deadline = time.monotonic() + 10.0
            while count() != rows and time.monotonic() < deadline:
                time.sleep(0.05)
            assert count() == rows
    assert child.poll() is not None  # stopped
    with DatabaseCounter(database, "keypoints", enabled=False) as idle:
        assert idle() is None and idle._child is None  # no live display: nothing read
    connection.close()


def _scene(folder: Path, **config) -> Path:
    from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

    return make_scene(MakeSceneConfig(output_dir=folder, seed=0, **config))


def _stage_line(output: str, stage: str) -> str:
    """The line the build wrote for ``stage`` (stderr is no terminal under pytest: one line per finished stage)."""
    (line,) = [line for line in output.splitlines() if line.strip().startswith(stage)]
    return line


@pytest.mark.slow
def test_more_than_exhaustive_limit_images_are_matched_with_neighbours_and_tracked(
    tmp_path: Path, capfd: pytest.CaptureFixture
):
    """104 images of 128x96 (a ring, 3.5 degrees apart; about 50 s to generate, 20 s to build) with cameras a
    degree off: the neighbour pairs are matched, every image is in the model, and the adjustment brings rotations and
    focal length nearer the truth (measured: 0.90 -> 0.52 degrees, 1.5 -> 0.06 px)."""
    scene = _scene(tmp_path / "scene", num_cameras=module.EXHAUSTIVE_LIMIT + 4, width=128, height=96, fov="wide")
    truth = pycolmap.Reconstruction(scene / "sparse" / "0")
    given = _given(truth)
    result = image_tracks(given, scene / "images", tmp_path / "cache")
    assert result.model is not None, result.reason
    output = capfd.readouterr().err
    pairs = len(neighbour_pairs(given))
    assert pairs <= 104 * module.NEIGHBOURS < 104 * 103 // 2
    assert f"({pairs}/{pairs} pairs, " in _stage_line(output, "matching, 30 neighbours")
    assert "(104/104 images, " in _stage_line(output, "SIFT features")
    breakdown = r"Image tracks built: SIFT .*, matching .*, adjustment .* \(4\), keypoints .*, refined\s+adjustment"
    breakdown += " .*, total "  # the line wraps at 120 characters
    assert re.search(breakdown, output)
    made = pycolmap.Reconstruction(result.model)
    assert made.num_images() == 104
    before, after = _errors(given, truth), _errors(made, truth)
    assert after["rot_err_mean"] < 0.75 * before["rot_err_mean"]
    assert after["focal_err_mean"] < 0.25 * before["focal_err_mean"]
    assert re.search(r"; built in [0-9. a-z]+ on the CPU$", result.summary)


@pytest.mark.slow
def test_the_first_triangulation_admits_the_given_cameras_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """32 images of 320x240 at f 600 px (30 degrees wide; about a minute to generate) with cameras a degree off, 10
    px: the bound of ``GIVEN_ANGLE_ERROR_DEG`` x focal (21 px) keeps enough observations of the wrong cameras and the
    adjustment ends 0.24 degrees from the truth; with COLMAP's fixed 4 px the first triangulation keeps a quarter of
    them and no point survives the adjusted cameras' triangulation (measured: 377 points, then none)."""
    scene = _scene(tmp_path / "scene", num_cameras=32, width=320, height=240, focal=600.0)
    truth = pycolmap.Reconstruction(scene / "sparse" / "0")
    given = _given(truth)
    thresholds = module.Thresholds.of(given)
    assert thresholds.given_px == pytest.approx(math.radians(module.GIVEN_ANGLE_ERROR_DEG) * 600 * FOCAL_FACTOR)
    result = image_tracks(given, scene / "images", tmp_path / "cache")
    assert result.model is not None, result.reason
    before, after = _errors(given, truth), _errors(pycolmap.Reconstruction(result.model), truth)
    assert after["rot_err_mean"] < 0.4 * before["rot_err_mean"]

    fixed = module.Thresholds(thresholds.keypoint_px, thresholds.keypoint_px)
    monkeypatch.setattr(module.Thresholds, "of", classmethod(lambda cls, given: fixed))
    colmap_default = image_tracks(given, scene / "images", tmp_path / "fixed 4 px")
    if colmap_default.model is not None:  # measured: none
        worse = _errors(pycolmap.Reconstruction(colmap_default.model), truth)
        assert worse["rot_err_mean"] > 1.5 * after["rot_err_mean"]


def test_perturbed_cameras_are_tracked_as_the_refiner_models_them(tiny_scene: Path, tmp_path: Path, monkeypatch):
    """CamP's perturbation gives every image its own focal length, but the images still come from one physical camera,
    whose intrinsics the refiner shares (starting from their mean). The image tracks' adjustment must model the
    cameras the same way: one COLMAP camera per physical camera at that mean, not one per image with a focal length
    free to trade against its depth."""
    from s2camp_ns.core.perturbation import PerturbationConfig
    from s2camp_ns.data.dataparser import S2CampDataParserConfig
    from s2camp_ns.tracks import track_evidence

    seen = []

    def capture(given, *args, **kwargs):
        seen.append(given)
        return module.ImageTracks(None, reason="captured")

    monkeypatch.setattr(track_evidence, "image_tracks", capture)
    config = S2CampDataParserConfig(
        data=tiny_scene, perturbation=PerturbationConfig(enabled=True, seed=3), image_tracks_cache=tmp_path
    )
    outputs = config.setup().get_dataparser_outputs("train")
    perturbed_fx = outputs.cameras.fx[:, 0].double()
    assert float(perturbed_fx.max() - perturbed_fx.min()) > 0.1  # the perturbation gave each image its own focal
    (given,) = seen
    assert given.num_cameras() == 1 and given.num_images() == outputs.cameras.shape[0]
    camera = next(iter(given.cameras.values()))
    # The tiny scene's training images are full size: the model's focal length is theirs, unscaled.
    assert camera.focal_length_x == pytest.approx(float(perturbed_fx.mean()), rel=1e-6)


def test_image_tracks_model_the_physical_cameras_the_refiner_shares(tiny_scene: Path, tmp_path: Path, monkeypatch):
    """The refiner groups images into physical cameras by the reference cameras (``camera_ids``); the image tracks'
    adjustment must model the same cameras, even where the scene's own model groups them otherwise. The reference here
    (the benchmarks' data parser's ``reference_model``) is the scene's model with every second image on a second camera
    of 5% longer focal length; the scene's own model has one camera."""
    from s2camp_bench.data_parser import BenchDataParserConfig
    from s2camp_ns.tracks import track_evidence

    seen = []

    def capture(given, *args, **kwargs):
        seen.append(given)
        return module.ImageTracks(None, reason="captured")

    monkeypatch.setattr(track_evidence, "image_tracks", capture)
    reference = tmp_path / "reference"
    reference.mkdir()
    pycolmap.Reconstruction(tiny_scene / "sparse" / "0").write_text(reference)
    cameras = (reference / "cameras.txt").read_text().splitlines()
    (camera_line,) = [line for line in cameras if line and not line.startswith("#")]
    fields = camera_line.split()
    fields[0], fields[4] = "2", repr(1.05 * float(fields[4]))
    (reference / "cameras.txt").write_text("\n".join([*cameras, " ".join(fields)]) + "\n")
    lines = (reference / "images.txt").read_text().splitlines()
    header = [line for line in lines if line.startswith("#")]
    body = [line for line in lines if not line.startswith("#")]
    for row in range(0, len(body), 4):  # every second image (two lines each)
        fields = body[row].split()
        fields[8] = "2"
        body[row] = " ".join(fields)
    (reference / "images.txt").write_text("\n".join(header + body) + "\n")
    config = BenchDataParserConfig(
        data=tiny_scene, reference_model=reference, image_tracks="always", image_tracks_cache=tmp_path / "cache"
    )
    outputs = config.setup().get_dataparser_outputs("train")
    camera_ids = outputs.metadata["camera_ids"]
    assert len(set(camera_ids)) == 2  # the refiner's two physical cameras
    (given,) = seen
    assert given.num_cameras() == 2 and given.num_images() == len(camera_ids)
    # Images share a COLMAP camera exactly when the refiner shares their intrinsics.
    by_name = {image.name: image.camera_id for image in given.images.values()}
    names = outputs.metadata["image_names"]
    for i in range(len(names)):
        for j in range(len(names)):
            assert (by_name[names[i]] == by_name[names[j]]) == (camera_ids[i] == camera_ids[j])


def test_physical_camera_means_average_each_cameras_intrinsics_and_keep_the_rest():
    from nerfstudio.cameras.cameras import Cameras, CameraType

    from s2camp_ns.data.camera_fields import physical_camera_means

    c2w = torch.eye(4)[:3].repeat(3, 1, 1)
    c2w[:, 0, 3] = torch.tensor([0.0, 1.0, 2.0])
    cameras = Cameras(
        camera_to_worlds=c2w, fx=torch.tensor([[100.0], [300.0], [50.0]]), fy=torch.tensor([[110.0], [310.0], [60.0]]),
        cx=torch.tensor([[20.0], [22.0], [30.0]]), cy=torch.tensor([[15.0], [17.0], [25.0]]), width=64, height=48,
        distortion_params=torch.tensor([[0.1, 0, 0, 0, 0, 0], [0.3, 0, 0, 0, 0, 0], [0.5, 0, 0, 0, 0, 0]]),
        camera_type=CameraType.PERSPECTIVE,
    )  # fmt: skip
    means = physical_camera_means(cameras, torch.tensor([7, 7, 2]))
    assert means.fx[:, 0].tolist() == [200.0, 200.0, 50.0] and means.fy[:, 0].tolist() == [210.0, 210.0, 60.0]
    assert means.cx[:, 0].tolist() == [21.0, 21.0, 30.0] and means.cy[:, 0].tolist() == [16.0, 16.0, 25.0]
    assert means.distortion_params[:, 0].tolist() == pytest.approx([0.2, 0.2, 0.5])
    assert torch.equal(means.camera_to_worlds, c2w) and means.width[:, 0].tolist() == [64, 64, 64]
    with pytest.raises(ValueError, match="camera_ids must hold 3 entries"):
        physical_camera_means(cameras, torch.tensor([0, 1]))


def test_two_builds_of_the_same_images_and_cameras_are_bit_identical(textured_scene: Path, tmp_path: Path):
    """Images numbered before SIFT and matching on one thread (``number_images``, ``MATCHING_THREADS``): otherwise two
    builds' image numbers and verified matches differed, and so did the cameras the tracks anchor."""
    given = _given(pycolmap.Reconstruction(textured_scene / "sparse" / "0"))
    first = image_tracks(given, textured_scene / "images", tmp_path / "first")
    second = image_tracks(given, textured_scene / "images", tmp_path / "second")
    assert first.model is not None and second.model is not None, (first.reason, second.reason)
    assert first.model.name == second.model.name  # one key
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (first.model / name).read_bytes() == (second.model / name).read_bytes(), name
