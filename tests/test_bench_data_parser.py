"""The benchmarks' data parser ``s2camp-bench-data`` (``benchmarks/s2camp_bench/data_parser.py``): the true cameras of a
``--reference-model``, the phone start's VIO drift after CamP's steps, and its registration with nerfstudio.

The scene is conftest's ``generated_scene``, the COLMAP cases test_dataparser.py's; the drift's own statistics:
tests/test_phone_drift.py."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from conftest import write_transforms
from ns_train_parse import parse_ns_train
from test_dataparser import COLMAP_CASES, WIDTH, _set_camera, input_model, parse

from s2camp_bench.data_parser import SUBCOMMAND, BenchDataParserConfig
from s2camp_bench.phone_drift import DriftConfig, perturb_with_drift
from s2camp_ns.core.camera import opengl_to_opencv
from s2camp_ns.core.perturbation import PerturbationConfig

PHONE = PerturbationConfig(
    enabled=True, seed=2, sigma_position=0.0, sigma_look_at=0.0, sigma_dolly_z=0.0, sigma_focal_length=0.0
)
"""The phone start's perturbation: CamP's steps off, the drift alone."""


def parse_bench(data: Path, split: str = "train", **kwargs):
    return BenchDataParserConfig(data=data, **kwargs).setup().get_dataparser_outputs(split=split)


def _write_model(reconstruction: pycolmap.Reconstruction, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    reconstruction.write_binary(str(folder))
    return folder


def test_without_its_options_it_parses_as_s2camp_data(generated_scene: Path):
    """Drift off and no reference model: the outputs of ``s2camp-data``, CamP's perturbation included."""
    camp = PerturbationConfig(enabled=True, seed=3)
    for kwargs in ({}, {"perturbation": camp}):
        plain, bench = parse(generated_scene, **kwargs), parse_bench(generated_scene, **kwargs)
        assert torch.equal(bench.cameras.camera_to_worlds, plain.cameras.camera_to_worlds)
        assert torch.equal(bench.cameras.fx, plain.cameras.fx)
        reference = bench.metadata["reference_cameras"]
        assert torch.equal(reference.camera_to_worlds, plain.metadata["reference_cameras"].camera_to_worlds)
        assert bench.metadata["perturbed"] is plain.metadata["perturbed"]


def test_drift_moves_the_training_cameras_after_camps_steps(generated_scene: Path):
    """The phone start: the drift applied to the normalized OpenCV training cameras, exactly ``perturb_with_drift``;
    the reference cameras stay the input's and the evaluation cameras are not perturbed."""
    plain = parse(generated_scene)
    drift = DriftConfig(enabled=True, position_drift=0.05, yaw_drift_deg=3.0)
    train = parse_bench(generated_scene, perturbation=PHONE, drift=drift)
    expected = perturb_with_drift(
        opengl_to_opencv(plain.cameras.camera_to_worlds.double()),
        plain.cameras.fx[:, 0].double(),
        plain.cameras.fy[:, 0].double(),
        PHONE,
        drift,
    )
    got = opengl_to_opencv(train.cameras.camera_to_worlds.double())
    torch.testing.assert_close(got, expected.c2w, atol=1e-6, rtol=0)
    torch.testing.assert_close(train.cameras.fx[:, 0].double(), expected.fx, atol=1e-4, rtol=0)
    assert float((got - opengl_to_opencv(plain.cameras.camera_to_worlds.double())).abs().max()) > 1e-3
    assert train.metadata["perturbed"] is True
    torch.testing.assert_close(train.metadata["reference_cameras"].camera_to_worlds, plain.cameras.camera_to_worlds)
    test = parse_bench(generated_scene, "test", perturbation=PHONE, drift=drift)
    torch.testing.assert_close(test.cameras.camera_to_worlds, parse(generated_scene, "test").cameras.camera_to_worlds)


def test_drift_without_the_perturbation_is_refused(generated_scene: Path):
    with pytest.raises(ValueError, match="drift.enabled needs perturbation.enabled True"):
        parse_bench(generated_scene, drift=DriftConfig(enabled=True))
    with pytest.raises(ValueError, match=r"drift\.tilt_deg must lie in \[0, 10\], got 20"):
        parse_bench(generated_scene, perturbation=PHONE, drift=DriftConfig(tilt_deg=20.0))


def test_ns_train_takes_it_in_the_benchmarks_runs_and_no_entry_point_installs_it():
    """ns-train's parse of a command line with it, in the benchmarks' environment; pyproject.toml registers only
    s2camp-data, so a user's ns-train never imports the benchmarks."""
    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    section = pyproject.split('[project.entry-points."nerfstudio.dataparser_configs"]')[1].split("\n[")[0]
    assert section.strip() == 's2camp-data = "s2camp_ns.data.dataparser:s2camp_dataparser"'
    args = ["ns-train", "s2camp", "--data", "scene", SUBCOMMAND, "--perturbation.enabled", "True", "--drift.enabled",
            "True", "--reference-model", "truth"]  # fmt: skip
    (config,) = parse_ns_train([args])
    dataparser = config.pipeline.datamanager.dataparser
    assert isinstance(dataparser, BenchDataParserConfig)
    assert dataparser.drift.enabled and dataparser.perturbation.enabled
    assert dataparser.reference_model == Path("truth")


def test_reference_model_of_the_input_gives_the_input_cameras(generated_scene: Path):
    for split in ("train", "test"):
        plain = parse_bench(generated_scene, split)
        with_reference = parse_bench(generated_scene, split, reference_model=generated_scene / "sparse" / "0")
        reference = with_reference.metadata["reference_cameras"]
        torch.testing.assert_close(reference.camera_to_worlds, plain.cameras.camera_to_worlds, atol=1e-5, rtol=0)
        torch.testing.assert_close(reference.fx, plain.cameras.fx)
        torch.testing.assert_close(reference.cx, plain.cameras.cx)
        torch.testing.assert_close(reference.distortion_params, plain.cameras.distortion_params)
        # The training cameras themselves stay the input's.
        torch.testing.assert_close(with_reference.cameras.camera_to_worlds, plain.cameras.camera_to_worlds)


def test_reference_model_is_aligned_into_the_input_frame_and_scaled_to_the_images(scene: Path, tmp_path: Path):
    """The input is the truth moved by a similarity, with a wrong focal length: the reference poses are the input's
    (the similarity is undone), the reference focal is the truth's at the training resolution."""
    truth = input_model(scene)
    true_focal = float(truth.cameras[1].params[0])
    moved = input_model(scene)
    rotation = pycolmap.Rotation3d(np.array([0.1, -0.3, 0.2, 0.9]) / np.linalg.norm([0.1, -0.3, 0.2, 0.9]))
    moved.transform(pycolmap.Sim3d(2.5, rotation, np.array([3.0, -1.0, 0.5])))
    camera = moved.cameras[1]
    params = camera.params.copy()
    params[0] *= 1.1
    camera.params = params
    shutil.rmtree(scene / "sparse" / "0")
    _write_model(moved, scene / "sparse" / "0")
    truth_folder = _write_model(truth, tmp_path / "truth")
    for split in ("train", "test"):
        outputs = parse_bench(scene, split, downscale_factor=2, reference_model=truth_folder)
        reference = outputs.metadata["reference_cameras"]
        torch.testing.assert_close(reference.camera_to_worlds, outputs.cameras.camera_to_worlds, atol=1e-5, rtol=0)
        assert torch.allclose(reference.fx, torch.full_like(reference.fx, true_focal * 25 / WIDTH), atol=1e-4)
        assert torch.allclose(outputs.cameras.fx, torch.full_like(reference.fx, 1.1 * true_focal * 25 / WIDTH))


@pytest.mark.parametrize("model", list(COLMAP_CASES))
def test_reference_model_of_every_supported_model_keeps_its_distortion(scene: Path, tmp_path: Path, model: str):
    """The reference's own model and coefficients (the truth's), not the input's: the input has the same model with
    a 10% focal error and no distortion."""
    params, expected = COLMAP_CASES[model]
    _set_camera(scene, model, params)
    truth = input_model(scene)
    truth_folder = _write_model(truth, tmp_path / "truth")
    wrong = list(params)
    wrong[0] *= 1.1
    first_distortion = {"SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4, "FULL_OPENCV": 4, "OPENCV_FISHEYE": 4}
    first = first_distortion.get(model, len(params))
    wrong[first:] = [0.0] * (len(params) - first)
    _set_camera(scene, model, wrong)
    outputs = parse_bench(scene, reference_model=truth_folder)
    reference = outputs.metadata["reference_cameras"]
    torch.testing.assert_close(reference.distortion_params, torch.tensor(expected).expand(8, 6).float())
    torch.testing.assert_close(outputs.cameras.distortion_params, torch.zeros(8, 6))
    assert torch.allclose(reference.fx, torch.full_like(reference.fx, float(params[0])), atol=1e-4)
    assert torch.allclose(outputs.cameras.fx, torch.full_like(reference.fx, 1.1 * params[0]), atol=1e-4)
    assert torch.equal(reference.camera_type, outputs.cameras.camera_type)


def test_reference_model_of_another_projection_is_refused(scene: Path, tmp_path: Path):
    truth = input_model(scene)
    camera = truth.cameras[1]
    camera.model = pycolmap.CameraModelId.OPENCV_FISHEYE
    camera.params = COLMAP_CASES["OPENCV_FISHEYE"][0]
    truth_folder = _write_model(truth, tmp_path / "truth")
    with pytest.raises(ValueError, match=r"camera 1 \(OPENCV_FISHEYE\) is a fisheye camera.*input is perspective"):
        parse_bench(scene, reference_model=truth_folder)


def test_reference_model_missing_image_is_named(scene: Path, tmp_path: Path):
    truth = input_model(scene)
    image = next(image for image in truth.images.values() if image.name == "frame_00003.png")
    image.name = "renamed.png"
    folder = _write_model(truth, tmp_path / "truth")
    with pytest.raises(ValueError, match=r"frame_00003\.png.*images\.bin.*1 of 10 images missing"):
        parse_bench(scene, reference_model=folder)
    with pytest.raises(FileNotFoundError, match="reference_model"):
        parse_bench(scene, reference_model=tmp_path / "nowhere")


def test_reference_model_of_a_transforms_scene_is_refused(generated_scene: Path, tmp_path: Path):
    data = write_transforms(generated_scene, tmp_path / "ns").parent
    with pytest.raises(ValueError, match=r"reference_model .*sparse/0 needs a COLMAP scene .* is a nerfstudio scene"):
        parse_bench(data, reference_model=generated_scene / "sparse" / "0")
