"""``s2camp-export-cameras`` as a user's next step: the exported scene opens in nerfstudio and COLMAP as the input did.

Two trained runs, each as ``ns-train s2camp`` makes it: one on a COLMAP scene (the anchors fitted to its SfM tracks,
re-adjusted) and one on a transforms.json scene without a COLMAP model (tracks made from the images). Their export
must hold the refined cameras, the images' keypoints and the anchors' points with tracks of two or more images,
whose reprojection error in the exported cameras (pycolmap's projection) is no higher than at the anchors; loading
the run must do no track work; stock ``ns-train nerfacto`` must train on it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from s2camp_ns.core.anchor_tracks import ANCHOR_TRACKS_FILE, AnchorTracks

pytestmark = pytest.mark.slow

ITERATIONS = 5
TRACK_WORK = ("Track prior", "Levenberg", "Making image tracks", "Image tracks built")
"""What the data parser and the anchor fit print when they work: a loaded run must print none of it."""


def _run(command: list[str], **environment: str) -> subprocess.CompletedProcess:
    from s2camp_bench import train_commands

    env = {**train_commands.training_environment(), "COLUMNS": "200", **environment}
    result = subprocess.run(command, capture_output=True, text=True, timeout=900, env=env)
    assert result.returncode == 0, f"{command[0]} exited with {result.returncode}:\n{result.stderr[-4000:]}"
    return result


def _train_s2camp(data: Path, output: Path, method: str = "s2camp") -> Path:
    from s2camp_bench import train_commands

    if method == "s2camp":
        command = train_commands.ns_train_arguments(method, data, output, "export", "run", ITERATIONS, 100, 256)
    else:
        command = train_commands.ns_train_base_arguments(method, data, output, "export", "run", ITERATIONS, 100)
    _run([*command, "--vis", "tensorboard"])
    return output / "export" / method / "run"


@pytest.fixture(scope="module")
def colmap_run(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run on the tiny COLMAP scene, unperturbed: its anchors are fitted to the scene's SfM tracks."""
    return _train_s2camp(tiny_scene, tmp_path_factory.mktemp("colmap_run"))


@pytest.fixture(scope="module")
def splat_run(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An ``s2camp-splat`` run on the tiny COLMAP scene, whose RADIAL camera splatfacto undistorts."""
    return _train_s2camp(tiny_scene, tmp_path_factory.mktemp("splat_run"), "s2camp-splat")


@pytest.fixture(scope="module")
def transforms_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run on a transforms.json scene with no COLMAP model beside it: its tracks are made from the images."""
    from conftest import write_transforms

    from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

    folder = tmp_path_factory.mktemp("transforms_scene")
    scene = make_scene(MakeSceneConfig(output_dir=folder / "colmap_scene", num_cameras=16, width=320, height=240))
    data = folder / "phone"
    data.mkdir()
    transforms = write_transforms(scene, data)
    return _train_s2camp(transforms, folder / "outputs")


@pytest.fixture(scope="module")
def exports(tmp_path_factory: pytest.TempPathFactory):
    """``export(run)``: the run's ``s2camp-export-cameras --output-dir .../refined`` (folder, process), made once."""
    made: dict[Path, tuple[Path, subprocess.CompletedProcess]] = {}

    def export(run: Path) -> tuple[Path, subprocess.CompletedProcess]:
        if run not in made:
            refined = tmp_path_factory.mktemp("export") / "refined"
            command = [str(Path(sys.executable).with_name("s2camp-export-cameras")), "--load-config",
                       str(run / "config.yml"), "--output-dir", str(refined)]  # fmt: skip
            made[run] = refined, _run(command)
        return made[run]

    return export


def _reprojection_squared(reconstruction: pycolmap.Reconstruction) -> np.ndarray:
    """Squared reprojection distance (px^2) of every track element, by pycolmap's own camera models."""
    squared = []
    for point in reconstruction.points3D.values():
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            camera = reconstruction.cameras[image.camera_id]
            projected = camera.img_from_cam(image.cam_from_world() * point.xyz)
            squared.append(float(((projected - image.points2D[element.point2D_idx].xy) ** 2).sum()))
    return np.asarray(squared)


@pytest.mark.parametrize("run_name", ["colmap_run", "transforms_run", "splat_run"])
def test_the_export_is_a_complete_scene(run_name: str, request: pytest.FixtureRequest, exports):
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    run = request.getfixturevalue(run_name)
    refined, result = exports(run)
    said = result.stdout + result.stderr
    assert not [line for line in said.splitlines() if any(work in line for work in TRACK_WORK)], said

    anchor = AnchorTracks.load(run / ANCHOR_TRACKS_FILE)
    assert anchor.tracks is not None and anchor.tracks.points.shape[0] > 50
    reconstruction = pycolmap.Reconstruction(str(refined / "sparse" / "0"))
    assert reconstruction.num_images() == anchor.num_images
    assert reconstruction.num_points3D() == anchor.tracks.points.shape[0]
    assert min(point.track.length() for point in reconstruction.points3D.values()) >= 2
    observations = anchor.tracks.image.shape[0]
    assert sum(len(image.points2D) for image in reconstruction.images.values()) == observations
    assert sum(point.track.length() for point in reconstruction.points3D.values()) == observations
    # The anchor fit's RMS over the same observations (per image RMS pooled by count).
    count = torch.bincount(anchor.tracks.image, minlength=anchor.num_images).double()
    anchor_rms = float((anchor.rms_px.nan_to_num().square() * count).sum().div(count.sum()).sqrt())
    exported_rms = float(np.sqrt(_reprojection_squared(reconstruction).mean()))
    print(f"{run_name}: reprojection RMS {exported_rms:.4f} px exported, {anchor_rms:.4f} px at the anchors")
    assert 0.0 < exported_rms <= anchor_rms
    colours = np.array([point.color for point in reconstruction.points3D.values()])
    assert colours.max() > 0, "the points must be coloured from the images"

    # The images as nerfstudio's parsers look for them, and both parsers read the export with its points.
    names = {image.name for image in reconstruction.images.values()}
    assert all((refined / "images" / name).is_file() for name in names)
    if run_name == "splat_run":  # splatfacto's undistorted images, written, with their pinhole cameras
        assert not (refined / "images").is_symlink()
        for camera in reconstruction.cameras.values():
            assert not any(camera.params[4:]), "undistorted images have no distortion"
            with Image.open(refined / "images" / sorted(names)[0]) as image:
                assert image.size == (camera.width, camera.height)
    else:
        assert (refined / "images").is_symlink()
    transforms = json.loads((refined / "transforms.json").read_text())
    assert transforms["ply_file_path"] == "sparse_pc.ply" and len(transforms["frames"]) == len(names)
    parsers = {
        "nerfstudio": NerfstudioDataParserConfig(data=refined, load_3D_points=True, eval_mode="all"),
        "colmap": ColmapDataParserConfig(data=refined, colmap_path=Path("sparse/0"), eval_mode="all"),
    }
    for name, parser in parsers.items():
        outputs = parser.setup().get_dataparser_outputs("train")
        assert len(outputs.image_filenames) == len(names), name
        assert outputs.metadata["points3D_xyz"].shape == (reconstruction.num_points3D(), 3), name


def _alexnet_cache(folder: Path) -> dict[str, str]:
    """A torch hub cache holding AlexNet's weight file (random weights): stock nerfacto builds LPIPS from it and
    would otherwise download it (this machine is offline). The metric is not looked at."""
    import torchvision

    checkpoints = folder / "hub" / "checkpoints"
    checkpoints.mkdir(parents=True)
    weights = torchvision.models.AlexNet_Weights.IMAGENET1K_V1
    torch.save(torchvision.models.alexnet().state_dict(), checkpoints / Path(weights.url).name)
    return {"TORCH_HOME": str(folder)}


def test_stock_nerfacto_trains_on_the_export(colmap_run: Path, transforms_run: Path, exports, tmp_path: Path):
    """``ns-train nerfacto --data refined`` (the exported transforms.json) and ``... colmap`` (the exported model)."""
    from s2camp_bench import train_commands

    environment = _alexnet_cache(tmp_path / "torch")
    small = ["--pipeline.model.implementation", "torch", "--machine.device-type", "cpu", "--vis", "tensorboard"]
    for run, parser in ((transforms_run, ["nerfstudio-data"]), (colmap_run, ["colmap", "--colmap-path", "sparse/0"])):
        refined, _ = exports(run)
        command = train_commands.ns_train_arguments("nerfacto", refined, tmp_path / "out", parser[0], "t", 5, 100, 256)
        _run([*command, *small, *parser], **environment)
        assert (tmp_path / "out" / parser[0] / "nerfacto" / "t" / "nerfstudio_models" / "step-000000004.ckpt").is_file()
