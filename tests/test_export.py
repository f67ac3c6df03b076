"""COLMAP export of (refined) cameras: conversion round trip, undoing nerfstudio's normalization, CLI path."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
import torch
import tyro
from colmap_arrays import reconstruction_to_arrays
from latents import write_latent
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene
from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.camera import se3_exp
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.data.camera_conversion import refined_nerfstudio_cameras
from s2camp_ns.data.colmap_writer import cameras_to_reconstruction, nerfstudio_to_reconstruction
from s2camp_ns.data.dataparser import S2CampDataParserConfig
from s2camp_ns.method.datamanager import PixelRayGenerator
from s2camp_ns.scripts import export_cameras as export
from s2camp_ns.scripts.export_cameras import ExportCamerasConfig, refined_training_cameras


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    config = MakeSceneConfig(
        output_dir=tmp_path_factory.mktemp("export") / "tiny",
        num_cameras=9,
        width=40,
        height=30,
        supersample=1,
        points_per_image=30,
    )
    return make_scene(config)


def random_cameras(n: int, seed: int = 0) -> dict:
    generator = torch.Generator().manual_seed(seed)
    c2w = se3_exp(torch.randn(n, 6, dtype=torch.float64, generator=generator) * 2)
    u = torch.rand(n, 6, dtype=torch.float64, generator=generator)
    return dict(
        c2w_opencv=c2w,
        fx=300 + 50 * u[:, 0],
        fy=300 + 50 * u[:, 1],
        cx=160 + u[:, 2],
        cy=120 + u[:, 3],
        width=320,
        height=240,
        k1=-0.1 * u[:, 4],
        k2=0.01 * u[:, 5],
        image_names=[f"dir/img_{i:03d}.jpg" for i in range(n)],
    )


def compare(arrays: dict, expected: dict, pose_atol: float, rel: float) -> None:
    assert arrays["names"] == list(expected["names"])
    np.testing.assert_allclose(arrays["c2w"], expected["c2w"], atol=pose_atol, rtol=0)
    for key in ("fx", "fy", "cx", "cy"):
        np.testing.assert_allclose(arrays[key], expected[key], rtol=rel, atol=0, err_msg=key)
    for key in ("k1", "k2"):
        np.testing.assert_allclose(arrays[key], expected[key], atol=1e-7, rtol=0, err_msg=key)
    np.testing.assert_array_equal(arrays["width"], expected["width"])
    np.testing.assert_array_equal(arrays["height"], expected["height"])


@pytest.mark.parametrize("same_focal", [False, True])
def test_conversion_round_trip_through_files(tmp_path: Path, same_focal: bool):
    cams = random_cameras(7)
    if same_focal:
        cams["fy"] = cams["fx"]
    points = np.random.default_rng(0).normal(size=(25, 3))
    colours = np.random.default_rng(1).integers(0, 256, size=(25, 3))
    reconstruction = cameras_to_reconstruction(**cams, points_xyz=points, points_rgb=colours)
    reconstruction.write_binary(str(tmp_path))
    assert (tmp_path / "cameras.bin").exists() and (tmp_path / "images.bin").exists()
    loaded = pycolmap.Reconstruction(str(tmp_path))
    assert loaded.num_cameras() == 7 and loaded.num_images() == 7 and loaded.num_points3D() == 25
    assert {c.model.name for c in loaded.cameras.values()} == {"RADIAL" if same_focal else "OPENCV"}
    expected = {
        key: np.broadcast_to(np.asarray(value, dtype=np.float64), (7,))
        if key in ("width", "height")
        else (value.numpy() if isinstance(value, torch.Tensor) else value)
        for key, value in cams.items()
    }
    expected["names"], expected["c2w"] = cams["image_names"], cams["c2w_opencv"].numpy()
    compare(reconstruction_to_arrays(loaded), expected, pose_atol=1e-9, rel=1e-12)
    xyz = np.array([loaded.points3D[i].xyz for i in sorted(loaded.points3D)])
    np.testing.assert_allclose(xyz, points, atol=1e-12)


def test_conversion_rejects_bad_input():
    cams = random_cameras(3)
    with pytest.raises(ValueError, match="RADIAL needs fx = fy"):
        cameras_to_reconstruction(**cams, camera_model="RADIAL")
    with pytest.raises(ValueError, match="image_names must have 3 entries"):
        cameras_to_reconstruction(**{**cams, "image_names": ["a"]})
    with pytest.raises(ValueError, match="fx must lie in"):
        cameras_to_reconstruction(**{**cams, "fx": -cams["fx"]})
    bad = cams["c2w_opencv"].clone()
    bad[0, :, 0] *= -1
    with pytest.raises(ValueError, match="det"):
        cameras_to_reconstruction(**{**cams, "c2w_opencv": bad})


def input_arrays(scene: Path, names: list[str]) -> dict:
    arrays = reconstruction_to_arrays(pycolmap.Reconstruction(str(scene / "sparse" / "0")))
    order = [arrays["names"].index(name) for name in names]
    return {
        key: ([value[i] for i in order] if key in ("names", "models") else value[order])
        for key, value in arrays.items()
    }


@pytest.mark.parametrize("downscale", [1, 2])
def test_unrefined_cameras_reproduce_input_model(scene: Path, downscale: int):
    out = S2CampDataParserConfig(data=scene, downscale_factor=downscale).setup().get_dataparser_outputs("train")
    names = out.metadata["image_names"]
    reconstruction = nerfstudio_to_reconstruction(
        out.cameras, out.dataparser_transform, out.dataparser_scale, names, out.metadata["full_image_size"]
    )
    compare(reconstruction_to_arrays(reconstruction), input_arrays(scene, names), pose_atol=2e-5, rel=2e-6)


def stub_pipeline(outputs, optimizer):
    datamanager = SimpleNamespace(
        train_dataparser_outputs=outputs, train_dataset=SimpleNamespace(cameras=outputs.cameras)
    )
    return SimpleNamespace(model=SimpleNamespace(camera_optimizer=optimizer), datamanager=datamanager)


def training_rays(cameras, optimizer, indices: torch.Tensor):
    """Rays of ``cameras`` at pixel ``indices`` [R, 3] (camera, y, x) as training sees them through ``optimizer``."""
    bundle = PixelRayGenerator(cameras)(indices)
    with torch.no_grad():
        optimizer.apply_to_raybundle(bundle)
    return bundle


def exported_rays(pipeline, indices: torch.Tensor):
    """The same pixels' rays generated by nerfstudio from the exported (refined) cameras."""
    return PixelRayGenerator(refined_training_cameras(pipeline))(indices)


def pixel_indices(cameras, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    n = 64
    camera = torch.randint(0, cameras.shape[0], (n,), generator=generator)
    y = torch.randint(0, int(cameras.height[0]), (n,), generator=generator)
    x = torch.randint(0, int(cameras.width[0]), (n,), generator=generator)
    return torch.stack([camera, y, x], dim=-1)


def test_exported_cameras_reproduce_the_training_rays_of_nerfstudio_pose_optimizer(scene: Path):
    """s2camp-so3xr3: the exported cameras generate the rays nerfstudio's SO3xR3 correction gives in training."""
    out = S2CampDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    optimizer = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=out.cameras.shape[0], device="cpu")
    with torch.no_grad():
        optimizer.pose_adjustment.normal_(0.0, 0.02, generator=torch.Generator().manual_seed(2))
    indices = pixel_indices(out.cameras)
    expected, exported = (
        training_rays(out.cameras, optimizer, indices),
        exported_rays(stub_pipeline(out, optimizer), indices),
    )
    torch.testing.assert_close(exported.origins, expected.origins, atol=1e-6, rtol=0)
    torch.testing.assert_close(exported.directions, expected.directions, atol=1e-6, rtol=0)
    assert (expected.directions - PixelRayGenerator(out.cameras)(indices).directions).norm(dim=-1).min() > 1e-3


def test_exported_cameras_reproduce_the_training_rays_of_s2camp(scene: Path):
    """s2camp: pose, focal lengths, principal point and k1, k2 exported are those the training rays came from."""
    out = S2CampDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    # per image, so that every camera gets its own intrinsics deltas here
    config = S2CampCameraOptimizerConfig(
        sampling=SamplingConfig(num_points=32, sampler="camp-random"), precondition=False, intrinsics="per-image"
    )
    optimizer = config.setup(num_cameras=out.cameras.shape[0], device="cpu")
    optimizer.set_train_cameras(out.cameras)
    # raw deltas (P = I), skew 0: nerfstudio's Cameras cannot hold skew
    raw = torch.tensor([0.02, -0.01, 0.03, 0.01, -0.02, 0.015, 2.0, 1.0, -1.5, 0.0, 0.02, -0.005])
    scale = torch.linspace(-1.0, 1.0, out.cameras.shape[0])[:, None]
    write_latent(optimizer.refiner, raw * scale)
    indices = pixel_indices(out.cameras, seed=1)
    expected, exported = (
        training_rays(out.cameras, optimizer, indices),
        exported_rays(stub_pipeline(out, optimizer), indices),
    )
    torch.testing.assert_close(exported.origins, expected.origins, atol=1e-5, rtol=0)
    torch.testing.assert_close(exported.directions, expected.directions, atol=1e-5, rtol=0)
    assert (expected.directions - PixelRayGenerator(out.cameras)(indices).directions).norm(dim=-1).max() > 1e-2


def test_cli_main_writes_a_readable_model(scene: Path, tmp_path: Path, monkeypatch):
    import nerfstudio.utils.eval_utils as eval_utils

    out = S2CampDataParserConfig(data=scene, downscale_factor=2).setup().get_dataparser_outputs("train")
    optimizer = CameraOptimizerConfig(mode="off").setup(num_cameras=len(out.image_filenames), device="cpu")
    monkeypatch.setattr(eval_utils, "eval_setup", lambda *a, **k: (None, stub_pipeline(out, optimizer), None, 0))
    config_file = tmp_path / "config.yml"
    config_file.write_text("stub")
    args = ["--load-config", str(config_file), "--output-dir", str(tmp_path / "sparse" / "0"), "--text"]
    config = tyro.cli(ExportCamerasConfig, args=args)
    export.main(config)
    loaded = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    names = out.metadata["image_names"]
    compare(reconstruction_to_arrays(loaded), input_arrays(scene, names), pose_atol=2e-5, rel=2e-6)
    source = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    assert loaded.num_points3D() == source.num_points3D() > 0
    src_xyz = np.array([source.points3D[i].xyz for i in sorted(source.points3D)])
    out_xyz = np.array([loaded.points3D[i].xyz for i in sorted(loaded.points3D)])
    np.testing.assert_allclose(out_xyz, src_xyz, atol=1e-12)
    assert (tmp_path / "sparse" / "0" / "text" / "cameras.txt").exists()
    with pytest.raises(FileNotFoundError, match="--load-config"):
        export.main(ExportCamerasConfig(load_config=tmp_path / "missing.yml", output_dir=tmp_path / "x"))


def test_an_export_never_replaces_a_scenes_own_files(scene: Path, tmp_path: Path, monkeypatch):
    """--output-dir <input scene>/sparse/0 (the earlier form) must not replace the scene's transforms.json; a folder an
    export wrote is rewritten (its transforms.json says so), with the image links replaced."""
    import nerfstudio.utils.eval_utils as eval_utils

    out = S2CampDataParserConfig(data=scene, downscale_factor=2).setup().get_dataparser_outputs("train")
    optimizer = CameraOptimizerConfig(mode="off").setup(num_cameras=len(out.image_filenames), device="cpu")
    monkeypatch.setattr(eval_utils, "eval_setup", lambda *a, **k: (None, stub_pipeline(out, optimizer), None, 0))
    config_file = tmp_path / "config.yml"
    config_file.write_text("stub")
    own = '{"frames": []}'
    (scene / "transforms.json").write_text(own)
    before = (scene / "sparse" / "0" / "images.bin").read_bytes()
    with pytest.raises(FileExistsError, match="transforms.json exists and was not written by s2camp-export-cameras"):
        export.main(ExportCamerasConfig(load_config=config_file, output_dir=scene / "sparse" / "0"))
    assert (scene / "transforms.json").read_text() == own
    assert (scene / "sparse" / "0" / "images.bin").read_bytes() == before
    for _ in range(2):  # the second export rewrites the first
        export.main(ExportCamerasConfig(load_config=config_file, output_dir=tmp_path / "refined"))
    written = json.loads((tmp_path / "refined" / "transforms.json").read_text())
    assert written["s2camp_export"]["load_config"] == str(config_file.resolve())
    assert len(written["frames"]) == len(out.image_filenames)
    assert (tmp_path / "refined" / "images").resolve() == (scene / "images").resolve()
    assert (tmp_path / "refined" / "images_2").resolve() == (scene / "images_2").resolve()


@pytest.mark.parametrize("optimizer_config", ["off", "pose", "so3xr3"])
def test_unrefined_intrinsics_export_one_camera_per_physical_camera(scene: Path, tmp_path: Path, monkeypatch,
                                                                    optimizer_config: str):  # fmt: skip
    """Refinement off, pose only, or nerfstudio's pose optimizer keep the scene's single shared camera: one COLMAP
    camera, as the refined export writes; per-image focal lengths (CamP's perturbation) give one per image."""
    import nerfstudio.utils.eval_utils as eval_utils

    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig

    for perturbed, expected in ((False, 1), (True, None)):
        config = S2CampDataParserConfig(data=scene, downscale_factor=2)
        config.perturbation.enabled = perturbed
        out = config.setup().get_dataparser_outputs("train")
        n = len(out.image_filenames)
        if optimizer_config == "so3xr3":
            optimizer = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=n, device="cpu")
        else:
            mode, parameters = ("off", "all") if optimizer_config == "off" else ("SE3", "pose")
            optimizer = S2CampCameraOptimizerConfig(mode=mode, parameters=parameters).setup(num_cameras=n, device="cpu")
            optimizer.set_train_cameras(out.cameras)
        pipeline = stub_pipeline(out, optimizer)
        monkeypatch.setattr(eval_utils, "eval_setup", lambda *a, p=pipeline, **k: (None, p, None, 0))
        config_file = tmp_path / "config.yml"
        config_file.write_text("stub")
        folder = tmp_path / f"{optimizer_config}-{perturbed}"
        export.main(ExportCamerasConfig(load_config=config_file, output_dir=folder))
        loaded = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
        assert loaded.num_images() == n
        assert loaded.num_cameras() == (n if expected is None else expected)


MODEL_PARAMS = {
    "OPENCV": [50.0, 51.0, 20.0, 15.0, -0.03, 0.005, 1e-3, -2e-3],
    "FULL_OPENCV": [50.0, 51.0, 20.0, 15.0, -0.03, 0.005, 1e-3, -2e-3, 4e-4, 0.0, 0.0, 0.0],
    "OPENCV_FISHEYE": [30.0, 31.0, 20.0, 15.0, 0.02, -0.004, 1e-3, -2e-4],
}


def scene_with_model(scene: Path, tmp_path: Path, model: str) -> Path:
    copy = Path(shutil.copytree(scene, tmp_path / "scene"))
    reconstruction = pycolmap.Reconstruction(str(copy / "sparse" / "0"))
    camera = reconstruction.cameras[1]
    camera.model = getattr(pycolmap.CameraModelId, model)
    camera.params = MODEL_PARAMS[model]
    reconstruction.write_binary(str(copy / "sparse" / "0"))
    return copy


@pytest.mark.parametrize("model", list(MODEL_PARAMS))
def test_each_camera_model_exports_in_colmap_meaning(scene: Path, tmp_path: Path, model: str):
    """Unrefined cameras come back as the same COLMAP model with the same parameters; refined ones project, for
    pycolmap, exactly as S2CamP's refined camera does."""
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
    from s2camp_ns.core.camera import project
    from s2camp_ns.core.preconditioner import SamplingConfig

    data = scene_with_model(scene, tmp_path, model)
    out = S2CampDataParserConfig(data=data).setup().get_dataparser_outputs("train")
    names = out.metadata["image_names"]
    reconstruction = nerfstudio_to_reconstruction(out.cameras, out.dataparser_transform, out.dataparser_scale, names)
    (tmp_path / "unrefined").mkdir()
    reconstruction.write_binary(str(tmp_path / "unrefined"))
    loaded = pycolmap.Reconstruction(str(tmp_path / "unrefined"))
    assert {camera.model.name for camera in loaded.cameras.values()} == {model}
    for camera in loaded.cameras.values():
        np.testing.assert_allclose(camera.params, MODEL_PARAMS[model], rtol=1e-6, atol=1e-9)

    # Per image, so that each image's deltas can be set directly.
    config = S2CampCameraOptimizerConfig(
        sampling=SamplingConfig(num_points=32, sampler="camp-random"), intrinsics="per-image"
    )
    optimizer = config.setup(num_cameras=len(names), device="cpu")
    optimizer.set_train_cameras(out.cameras)
    layout = optimizer.refiner.layout
    with torch.no_grad():  # raw focal, principal point and distortion deltas (skew stays zero: COLMAP has none)
        phi = torch.zeros(len(names), 16, dtype=torch.float64)
        phi[:, 6:9] = torch.tensor([1.5, -0.5, 0.7])
        phi[:, 10:] = torch.tensor([0.004, -0.001, 2e-4, 3e-5, 2e-4, -3e-4])
        write_latent(optimizer.refiner, (optimizer.refiner.precond @ phi[:, list(layout.indices), None])[..., 0])
    refined = refined_nerfstudio_cameras(optimizer.refiner, out.cameras)
    reconstruction = nerfstudio_to_reconstruction(refined, out.dataparser_transform, out.dataparser_scale, names)
    intrinsics = optimizer.refiner.refined_intrinsics().detach()
    points = torch.tensor([[[0.1, -0.2, 1.0], [0.3, 0.2, 2.0], [-0.25, 0.1, 1.5]]], dtype=torch.float64)
    for index, name in enumerate(names):
        image = next(image for image in reconstruction.images.values() if image.name == name)
        camera = reconstruction.cameras[image.camera_id]
        assert camera.model.name == model
        expected, _ = project(points, intrinsics[index])
        # float32 storage of nerfstudio's Cameras bounds the agreement.
        np.testing.assert_allclose(camera.img_from_cam(points[0].numpy()), expected[0].numpy(), rtol=1e-5)


def test_perspective_r8_coefficient_cannot_be_exported():
    cams = random_cameras(2)
    with pytest.raises(ValueError, match=r"camera 0 \(dir/img_000\.jpg\): k4 = 0\.001 \(a polynomial r\^8 term\)"):
        cameras_to_reconstruction(**cams, k4=0.001)
    with pytest.raises(ValueError, match="camera_model must be one of"):
        cameras_to_reconstruction(**cams, camera_model="FOV")
