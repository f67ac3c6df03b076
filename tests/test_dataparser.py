"""S2CampDataParser on a tiny generated mip-NeRF 360 style scene: detection, downscale folders, perturbation, errors.

The benchmarks' data parser (drift, reference model): tests/test_bench_data_parser.py."""

from __future__ import annotations

import json
import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from conftest import PARSER_SCENE, write_transforms
from nerfstudio.cameras.cameras import Cameras, CameraType
from PIL import Image

from s2camp_ns.core.camera import opengl_to_opencv
from s2camp_ns.core.perturbation import PerturbationConfig, perturb_cameras
from s2camp_ns.data.camera_perturbation import perturb_nerfstudio_cameras
from s2camp_ns.data.dataparser import S2CampDataParserConfig

WIDTH, HEIGHT, NUM_CAMERAS = PARSER_SCENE["width"], PARSER_SCENE["height"], PARSER_SCENE["num_cameras"]


def parse(data: Path, split: str = "train", **kwargs):
    return S2CampDataParserConfig(data=data, **kwargs).setup().get_dataparser_outputs(split=split)


def input_model(scene: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(scene / "sparse" / "0"))


def test_colmap_scene_detected_with_full_size_images(generated_scene: Path):
    train, test = parse(generated_scene), parse(generated_scene, "test")
    assert train.metadata["source_format"] == "colmap"
    assert len(train.image_filenames) + len(test.image_filenames) == NUM_CAMERAS
    assert len(test.image_filenames) == 2  # every 8th image (0 and 8)
    assert all(Path(p).parent.name == "images" for p in train.image_filenames)
    camera = input_model(generated_scene).cameras[1]
    assert int(train.cameras.width[0]) == WIDTH and int(train.cameras.height[0]) == HEIGHT
    assert abs(float(train.cameras.fx[0]) - camera.params[0]) < 1e-4
    torch.testing.assert_close(train.cameras.distortion_params[0, :2], torch.tensor(camera.params[3:5]).float())
    assert train.metadata["downscale_factor"] == 1 and train.metadata["perturbed"] is False
    assert isinstance(train.metadata["dataparser_scale"], float)
    assert train.metadata["dataparser_scale"] == pytest.approx(float(train.dataparser_scale))
    torch.testing.assert_close(train.metadata["reference_cameras"].camera_to_worlds, train.cameras.camera_to_worlds)
    # Normalized: camera centres inside [-1, 1]^3.
    assert float(train.cameras.camera_to_worlds[:, :, 3].abs().max()) <= 1.0 + 1e-6


def test_downscale_factor_two_uses_images_2(generated_scene: Path):
    full, half = parse(generated_scene), parse(generated_scene, downscale_factor=2)
    assert all(Path(p).parent.name == "images_2" for p in half.image_filenames)
    torch.testing.assert_close(half.cameras.fx, full.cameras.fx / 2)
    torch.testing.assert_close(half.cameras.cx, full.cameras.cx / 2)
    assert int(half.cameras.width[0]) == WIDTH // 2


def test_auto_picks_images_4_and_fits_rounded_sizes(scene: Path):
    (scene / "images_4").mkdir()
    small = (round(WIDTH / 4 + 0.01), round(HEIGHT / 4 + 0.01))  # 13 x 10, rounded up as ImageMagick does
    for path in (scene / "images").iterdir():
        Image.open(path).resize(small).save(scene / "images_4" / path.name)
    out = parse(scene)
    assert out.metadata["downscale_factor"] == 4
    assert all(Path(p).parent.name == "images_4" for p in out.image_filenames)
    camera = input_model(scene).cameras[1]
    assert (int(out.cameras.width[0]), int(out.cameras.height[0])) == small
    assert float(out.cameras.fx[0]) == pytest.approx(camera.params[0] * small[0] / WIDTH, rel=1e-6)
    assert float(out.cameras.fy[0]) == pytest.approx(camera.params[0] * small[1] / HEIGHT, rel=1e-6)
    assert float(out.cameras.cx[0]) == pytest.approx(camera.params[1] * small[0] / WIDTH, rel=1e-6)
    # A folder that does not match the model's size is reported, not silently used.
    for path in (scene / "images_4").iterdir():
        Image.open(path).resize((20, 10)).save(path)
    with pytest.raises(
        ValueError,
        match=r"image .*images_4/frame_\d+\.png is 20x10 but its COLMAP camera 1 in .*sparse/0/cameras\.bin is 50x38, "
        r"which at downscale_factor 4 gives 12\.5x9\.5",
    ):
        parse(scene)


def test_colmap_camera_size_that_disagrees_with_the_images_is_named(scene: Path):
    """A COLMAP camera twice as wide as its images: refused with the image, the cameras file and both sizes."""
    reconstruction = input_model(scene)
    reconstruction.cameras[1].width = 2 * WIDTH
    reconstruction.write_binary(str(scene / "sparse" / "0"))
    with pytest.raises(
        ValueError,
        match=r"image .*/images/frame_\d+\.png is 50x38 but its COLMAP camera 1 in .*sparse/0/cameras\.bin is "
        r"100x38: every ray would go through the wrong pixel",
    ):
        parse(scene)


def test_missing_downscale_folder_lists_present_ones(generated_scene: Path):
    with pytest.raises(FileNotFoundError, match=r"images_8.*images_2"):
        parse(generated_scene, downscale_factor=8)
    with pytest.raises(ValueError, match="downscale_factor must be an integer"):
        parse(generated_scene, downscale_factor=0)


def test_perturbation_off_by_default_on_when_enabled(generated_scene: Path):
    plain = parse(generated_scene)
    config = PerturbationConfig(enabled=True, seed=3)
    train = parse(generated_scene, perturbation=config)
    again = parse(generated_scene, perturbation=PerturbationConfig(enabled=True, seed=3))
    other = parse(generated_scene, perturbation=PerturbationConfig(enabled=True, seed=4))
    test = parse(generated_scene, "test", perturbation=config)
    reference = train.metadata["reference_cameras"]
    assert train.metadata["perturbed"] is True
    torch.testing.assert_close(reference.camera_to_worlds, plain.cameras.camera_to_worlds)
    torch.testing.assert_close(reference.fx, plain.cameras.fx)
    torch.testing.assert_close(reference.distortion_params, plain.cameras.distortion_params)
    assert not torch.allclose(train.cameras.camera_to_worlds, plain.cameras.camera_to_worlds, atol=1e-3)
    assert torch.equal(train.cameras.camera_to_worlds, again.cameras.camera_to_worlds)
    assert not torch.allclose(train.cameras.camera_to_worlds, other.cameras.camera_to_worlds, atol=1e-4)
    assert float(train.cameras.distortion_params.abs().max()) == 0.0
    # Exactly the core protocol applied to the normalized OpenCV cameras.
    expected = perturb_cameras(
        opengl_to_opencv(plain.cameras.camera_to_worlds.double()),
        plain.cameras.fx[:, 0].double(),
        plain.cameras.fy[:, 0].double(),
        config,
    )
    torch.testing.assert_close(
        opengl_to_opencv(train.cameras.camera_to_worlds.double()), expected.c2w, atol=1e-6, rtol=0
    )
    torch.testing.assert_close(train.cameras.fx[:, 0].double(), expected.fx, atol=1e-4, rtol=0)
    # Evaluation cameras are never perturbed.
    plain_test = parse(generated_scene, "test")
    assert test.metadata["perturbed"] is False
    torch.testing.assert_close(test.cameras.camera_to_worlds, plain_test.cameras.camera_to_worlds)
    torch.testing.assert_close(test.cameras.distortion_params, plain_test.cameras.distortion_params)


def test_perturbation_of_fisheye_cameras_draws_the_same_poses_and_focals(scene: Path):
    """The draws depend on poses and focal lengths only: a fisheye model of the same scene gets the perspective one's
    perturbed poses and focals, keeps its camera type, and loses its distortion when configured to."""
    config = PerturbationConfig(enabled=True, seed=3)
    perspective_plain, perspective = parse(scene), parse(scene, perturbation=config)
    _set_camera(scene, "OPENCV_FISHEYE", [50, 50, 25, 19, 0.02, -0.004, 1e-3, -2e-4])
    plain = parse(scene)
    fisheye = parse(scene, perturbation=config)
    assert (fisheye.cameras.camera_type == CameraType.FISHEYE.value).all()
    torch.testing.assert_close(fisheye.cameras.camera_to_worlds, perspective.cameras.camera_to_worlds)
    focal_scale = perspective.cameras.fx / perspective_plain.cameras.fx
    torch.testing.assert_close(fisheye.cameras.fx / plain.cameras.fx, focal_scale)
    assert not torch.allclose(fisheye.cameras.fx, plain.cameras.fx, rtol=1e-3)
    assert float(fisheye.cameras.distortion_params.abs().max()) == 0.0
    assert float(fisheye.metadata["reference_cameras"].distortion_params[:, 0].min()) == pytest.approx(0.02)


def test_perturbation_of_other_camera_types_is_refused_by_name():
    cameras = Cameras(
        camera_to_worlds=torch.eye(4)[:3][None], fx=10.0, fy=10.0, cx=5.0, cy=5.0, width=10, height=10,
        camera_type=CameraType.EQUIRECTANGULAR,
    )  # fmt: skip
    with pytest.raises(ValueError, match="supports PERSPECTIVE and FISHEYE cameras, got EQUIRECTANGULAR"):
        perturb_nerfstudio_cameras(cameras, PerturbationConfig(enabled=True))


def test_missing_image_is_named(scene: Path):
    (scene / "images" / "frame_00003.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"images\.bin lists image 'frame_00003\.png'"):
        parse(scene)


def _set_camera(scene: Path, model: str, params: list[float]) -> None:
    reconstruction = input_model(scene)
    camera = reconstruction.cameras[1]
    camera.model = getattr(pycolmap.CameraModelId, model)
    camera.params = params
    reconstruction.write_binary(str(scene / "sparse" / "0"))


def test_unsupported_camera_model_is_named(scene: Path):
    _set_camera(scene, "FOV", [50, 50, 25, 19, 0.9])
    with pytest.raises(
        ValueError,
        match=r"cameras\.bin: camera 1 uses the COLMAP camera model FOV.*"
        r"supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, OPENCV_FISHEYE",
    ):
        parse(scene)


# COLMAP parameters, and the nerfstudio distortion_params [k1, k2, k3, k4, p1, p2] they must become.
COLMAP_CASES = {
    "SIMPLE_PINHOLE": ([50, 25, 19], [0, 0, 0, 0, 0, 0]),
    "PINHOLE": ([50, 51, 25, 19], [0, 0, 0, 0, 0, 0]),
    "SIMPLE_RADIAL": ([50, 25, 19, -0.03], [-0.03, 0, 0, 0, 0, 0]),
    "RADIAL": ([50, 25, 19, -0.03, 0.005], [-0.03, 0.005, 0, 0, 0, 0]),
    "OPENCV": ([50, 51, 25, 19, -0.03, 0.005, 1e-3, -2e-3], [-0.03, 0.005, 0, 0, 1e-3, -2e-3]),
    "FULL_OPENCV": (
        [50, 51, 25, 19, -0.03, 0.005, 1e-3, -2e-3, 4e-4, 0, 0, 0],
        [-0.03, 0.005, 4e-4, 0, 1e-3, -2e-3],
    ),
    "OPENCV_FISHEYE": ([30, 31, 25, 19, 0.02, -0.004, 1e-3, -2e-4], [0.02, -0.004, 1e-3, -2e-4, 0, 0]),
}
LAYOUT_MODEL = {"OPENCV": "OPENCV", "FULL_OPENCV": "FULL_OPENCV", "OPENCV_FISHEYE": "OPENCV_FISHEYE"}


def _camera_optimizer(cameras):
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
    from s2camp_ns.core.preconditioner import SamplingConfig

    config = S2CampCameraOptimizerConfig(sampling=SamplingConfig(num_points=32, sampler="camp-random"))
    optimizer = config.setup(num_cameras=cameras.shape[0], device="cpu")
    optimizer.set_train_cameras(cameras)
    return optimizer


@pytest.mark.parametrize("model", list(COLMAP_CASES))
def test_every_supported_colmap_model_reaches_the_camera_optimizer(scene: Path, model: str):
    params, expected = COLMAP_CASES[model]
    _set_camera(scene, model, params)
    out = parse(scene)
    torch.testing.assert_close(out.cameras.distortion_params, torch.tensor(expected).expand(8, 6).float())
    fisheye = model == "OPENCV_FISHEYE"
    assert (out.cameras.camera_type == (CameraType.FISHEYE if fisheye else CameraType.PERSPECTIVE).value).all()
    assert float(out.cameras.fx[0]) == pytest.approx(params[0]) and float(out.cameras.cx[0]) == pytest.approx(25.0)
    assert out.metadata["camera_model"] == LAYOUT_MODEL.get(model, "RADIAL")
    optimizer = _camera_optimizer(out.cameras)
    assert optimizer.refiner.layout.camera_model == LAYOUT_MODEL.get(model, "RADIAL")
    assert optimizer.refiner.base_intrinsics_struct().model == ("fisheye" if fisheye else "perspective")


def test_full_opencv_with_a_rational_factor_is_refused(scene: Path):
    _set_camera(scene, "FULL_OPENCV", [50, 51, 25, 19, -0.03, 0.005, 0, 0, 0, 0.01, 0, 0])
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 1: COLMAP FULL_OPENCV .*k4 = 0\.01"):
        parse(scene)


def _write_ns_process_data_transforms(scene: Path, data: Path) -> dict:
    """transforms.json exactly as ns-process-data writes it (nerfstudio's colmap_to_json), images alongside."""
    from nerfstudio.process_data.colmap_utils import colmap_to_json

    shutil.copytree(scene / "images", data / "images")
    colmap_to_json(scene / "sparse" / "0", data)
    return json.loads((data / "transforms.json").read_text())


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_ns_process_data_transforms_reach_the_camera_optimizer(scene: Path, tmp_path: Path, model: str):
    params, expected = COLMAP_CASES[model]
    _set_camera(scene, model, params)
    meta = _write_ns_process_data_transforms(scene, tmp_path / "ns")
    assert meta["camera_model"] == model
    assert (meta["p1"], meta["p2"]) == (1e-3, -2e-3) if model == "OPENCV" else meta["k4"] == -2e-4
    out = parse(tmp_path / "ns" / "transforms.json")
    assert out.metadata["source_format"] == "nerfstudio"
    torch.testing.assert_close(out.cameras.distortion_params[0], torch.tensor(expected).float())
    optimizer = _camera_optimizer(out.cameras)
    assert optimizer.refiner.layout.camera_model == model
    assert optimizer.refiner.layout.num_params == 14 and optimizer.refiner.precond.shape[-1] == 14


def test_equirectangular_transforms_are_refused_by_name(scene: Path, tmp_path: Path):
    meta = _write_ns_process_data_transforms(scene, tmp_path / "ns")
    meta["camera_model"] = "EQUIRECTANGULAR"
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"transforms\.json: camera type EQUIRECTANGULAR is not supported.*FISHEYE"):
        parse(tmp_path / "ns" / "transforms.json")


def test_empty_scenes(scene: Path, tmp_path: Path):
    nothing = tmp_path / "nothing_here"
    nothing.mkdir()
    with pytest.raises(FileNotFoundError, match=r"(?s)looked for:.*sparse/0/cameras\.bin.*transforms\.json"):
        parse(nothing)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        parse(tmp_path / "absent")
    for path in (scene / "images").iterdir():
        path.unlink()
    with pytest.raises(ValueError, match=r"the scene is empty: image folder .*images holds no images"):
        parse(scene)
    empty_model = pycolmap.Reconstruction()
    empty_model.add_camera_with_trivial_rig(input_model(scene).cameras[1])
    empty_model.write_binary(str(scene / "sparse" / "0"))
    with pytest.raises(ValueError, match=r"images\.bin lists no images"):
        parse(scene)


def test_transforms_json_detected(generated_scene: Path, tmp_path: Path):
    data = tmp_path / "ns"
    meta = json.loads(write_transforms(generated_scene, data).read_text())
    frames, f = meta["frames"], meta["fl_x"]
    out = parse(data, eval_mode="interval")
    assert out.metadata["source_format"] == "nerfstudio"
    assert len(out.image_filenames) == 8 and float(out.cameras.fx[0]) == pytest.approx(f, rel=1e-6)
    (data / "images" / frames[1]["file_path"].split("/")[1]).unlink()
    with pytest.raises(FileNotFoundError, match="frame_00001.png"):
        parse(data)
    (data / "transforms.json").write_text(json.dumps({**meta, "frames": []}))
    with pytest.raises(ValueError, match="lists no frames"):
        parse(data)


# ------------------------------------------------------------------------------------ corrupt or truncated models
def _random_bytes(size: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, size=size, dtype=np.uint8).tobytes()


def _damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "random":  # overwritten with random bytes of the same size
        path.write_bytes(_random_bytes(len(data)))
    elif how == "truncated to 50 bytes":
        path.write_bytes(data[:50])
    elif how == "cut inside the last record":
        path.write_bytes(data[:-10])
    elif how == "trailing bytes":
        path.write_bytes(data + b"\0" * 7)
    elif how == "empty":
        path.write_bytes(b"")
    else:
        raise AssertionError(how)


@pytest.mark.parametrize(
    ("name", "how", "reason"),
    [
        # the two inputs of the issue: KeyError: -1168947745 and struct.error before
        ("cameras.bin", "random", r"its header announces \d+ camera records"),
        ("images.bin", "truncated to 50 bytes", r"its header announces 10 image records, .* only 42 bytes follow"),
        ("images.bin", "cut inside the last record", r"the file ends inside a record \(unpack requires"),
        ("images.bin", "random", r"its header announces \d+ image records"),
        ("points3D.bin", "random", r"its header announces \d+ point records"),
        ("points3D.bin", "cut inside the last record", r"the file ends inside a record"),
        ("points3D.bin", "trailing bytes", r"records, which take \d+ bytes, but the file holds \d+ bytes"),
        ("cameras.bin", "trailing bytes", r"announces 1 camera records, which take 72 bytes, but the file holds 79"),
        ("cameras.bin", "empty", r"it holds 0 bytes, fewer than the 8-byte record count"),
    ],
)
def test_corrupt_binary_model_file_is_named(scene: Path, name: str, how: str, reason: str):
    path = scene / "sparse" / "0" / name
    _damage(path, how)
    kind = name.split(".")[0]
    count = {"cameras": "camera", "images": "image", "points3D": "point"}[kind]
    with pytest.raises(ValueError, match=rf"(?s)^{re.escape(str(path))} is (corrupt|truncated).*{reason}") as info:
        parse(scene)
    assert f"expected a COLMAP {name} (a uint64 {count} count" in str(info.value)


def test_unknown_camera_model_id_is_named(scene: Path):
    """A header that fits the file but a model id no COLMAP model has (nerfstudio's reader: KeyError: <id>)."""
    path = scene / "sparse" / "0" / "cameras.bin"
    data = bytearray(path.read_bytes())
    struct.pack_into("<i", data, 12, -1168947745)  # the model id of the only camera (after count and camera id)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))} is corrupt .*unknown camera model id -1168947745"):
        parse(scene)


def test_image_with_an_unknown_camera_is_named(scene: Path):
    path = scene / "sparse" / "0" / "images.bin"
    data = bytearray(path.read_bytes())
    struct.pack_into("<i", data, 8 + 4 + 8 * 7, 99)  # camera_id of the first image (after count, id, qvec, tvec)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: image \d+ .* refers to camera 99, which cameras"):
        parse(scene)


@pytest.mark.parametrize(
    ("name", "damage", "reason"),
    [
        ("cameras.txt", "1 RADIAL 50 thirty-eight 45.0 25.0 19.0 0.0 0.0\n", r"ValueError: invalid literal for int"),
        ("cameras.txt", "1 RADIAL 50 38 45.0 25.0\n", r"camera 1 \(RADIAL\) has 2 parameters, expected 5"),
        ("images.txt", "1 1.0 0.0 0.0\n\n", r"IndexError|ValueError"),
        ("points3D.txt", "1 0.5 0.2 nan 10 20 30 0.1 1 0\n", r"points3D record 1 holds NaN"),
    ],
)
def test_corrupt_text_model_file_is_named(scene: Path, name: str, damage: str, reason: str):
    folder = scene / "sparse" / "0"
    input_model(scene).write_text(str(folder))
    for binary in folder.glob("*.bin"):
        binary.unlink()
    (folder / name).write_text("# damaged\n" + damage)
    with pytest.raises(ValueError, match=rf"(?s)^{re.escape(str(folder / name))}.*{reason}") as info:
        parse(scene)
    if "corrupt or truncated" in str(info.value):
        assert f"expected a COLMAP {name} (" in str(info.value)


def test_transforms_size_that_disagrees_with_the_images_is_named(generated_scene: Path, tmp_path: Path):
    """transforms.json ``w`` twice the images' width (global, then per frame as ns-process-data writes it): refused
    with the image, the json file and both sizes, instead of training every ray through the wrong pixel."""
    source = write_transforms(generated_scene, tmp_path / "global", w=2 * WIDTH)
    with pytest.raises(
        ValueError,
        match=rf"image .*/global/images/frame_\d+\.png is 50x38 but the w x h in {re.escape(str(source))} is 100x38: "
        r"every ray would go through the wrong pixel",
    ):
        parse(source)
    source = write_transforms(generated_scene, tmp_path / "per_frame")
    meta = json.loads(source.read_text())
    del meta["w"], meta["h"]
    for i, frame in enumerate(meta["frames"]):
        frame.update(w=WIDTH, h=HEIGHT + 5 * (i == 3))
    source.write_text(json.dumps(meta))
    with pytest.raises(
        ValueError, match=r"images/frame_00003\.png is 50x38 but the w x h in .*transforms\.json is 50x43"
    ):
        parse(source)


def test_transforms_images_of_a_downscaled_folder_are_checked_and_fitted(generated_scene: Path, tmp_path: Path):
    """downscale_factor 4 reads images_4 beside the json: its rounded sizes (13 x 10 for 50 x 38) are the cameras'
    (nerfstudio alone floors them to 12 x 9 and keeps f / 4), and a folder of another size is refused by name."""
    source = write_transforms(generated_scene, tmp_path / "ns")
    (source.parent / "images_4").mkdir()
    small = (13, 10)
    for path in (source.parent / "images").iterdir():
        Image.open(path).resize(small).save(source.parent / "images_4" / path.name)
    f, cx, cy = (json.loads(source.read_text())[key] for key in ("fl_x", "cx", "cy"))
    out = parse(source, downscale_factor=4)
    assert all(Path(p).parent.name == "images_4" for p in out.image_filenames)
    assert (int(out.cameras.width[0]), int(out.cameras.height[0])) == small
    assert float(out.cameras.fx[0]) == pytest.approx(f * 13 / 50, rel=1e-6)
    assert float(out.cameras.fy[0]) == pytest.approx(f * 10 / 38, rel=1e-6)
    assert float(out.cameras.cx[0]) == pytest.approx(cx * 13 / 50, rel=1e-6)
    assert float(out.cameras.cy[0]) == pytest.approx(cy * 10 / 38, rel=1e-6)
    for path in (source.parent / "images_4").iterdir():
        Image.open(path).resize((25, 19)).save(path)  # a half-size folder saved as images_4
    with pytest.raises(
        ValueError,
        match=r"images_4/frame_\d+\.png is 25x19 but the w x h in .*transforms\.json is 50x38, which at "
        r"downscale_factor 4 gives 12\.5x9\.5.*pick the downscale_factor that matches the folder",
    ):
        parse(source, downscale_factor=4)


@pytest.mark.parametrize("convention", [True, False])
@pytest.mark.parametrize("masks", [False, True])
def test_colmap_frames_are_those_of_nerfstudios_reader(generated_scene: Path, convention: bool, masks: bool):
    """Our reader of the COLMAP model (``ValidatingColmapDataParser._get_all_images_and_cameras``) gives nerfstudio's
    frames for a model nerfstudio reads (PINHOLE): paths, OpenGL c2w in either world convention, ids, intrinsics,
    mask paths; and it leaves nerfstudio's module as it was."""
    from nerfstudio.data.dataparsers import colmap_dataparser
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig

    from s2camp_ns.data.colmap_scene import ValidatingColmapDataParser

    nerfstudio_reader = colmap_dataparser.parse_colmap_camera_params
    config = ColmapDataParserConfig(
        data=generated_scene, colmap_path=Path("sparse/0"), assume_colmap_world_coordinate_convention=convention,
        masks_path=Path("masks") if masks else None,
    )  # fmt: skip
    model = generated_scene / "sparse" / "0"
    ours = ValidatingColmapDataParser(config, generated_scene / "images")._get_all_images_and_cameras(model)
    theirs = ColmapDataParser(config)._get_all_images_and_cameras(model)
    assert colmap_dataparser.parse_colmap_camera_params is nerfstudio_reader
    assert ours["camera_model"] == "OPENCV" and theirs["camera_model"] == "OPENCV"
    assert ("applied_transform" in ours) == convention
    if convention:
        np.testing.assert_array_equal(np.asarray(ours["applied_transform"]), np.asarray(theirs["applied_transform"]))
    assert len(ours["frames"]) == len(theirs["frames"]) == NUM_CAMERAS
    for mine, reference in zip(ours["frames"], theirs["frames"], strict=True):
        np.testing.assert_allclose(mine.pop("transform_matrix"), reference.pop("transform_matrix"), rtol=0, atol=1e-12)
        for name in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "p1", "p2"):  # nerfstudio omits a zero k3
            assert mine.pop(name, 0.0) == pytest.approx(reference.pop(name, 0.0), rel=1e-12, abs=1e-15), name
        assert mine == reference
