"""Runs of earlier versions load (``s2camp_ns.compat``): old module paths in a config.yml, and the committed runs of
the version at 8b8539f (tests/data/run-8b8539f/, written before the package moved into folders by subsystem) exported,
evaluated and resumed by this version.

The runs were trained on the suite's tiny scene (``TINY_SCENE``); their config.yml names the scene and the output
folder by the paths they had then, which the tests point at this session's copies (nothing else is changed).
"""

from __future__ import annotations

import importlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pycolmap
import pytest
import torch
import yaml
from hang_guard import HANG_GUARD_S

from s2camp_bench import train_commands
from s2camp_ns import compat

RUNS = Path(__file__).parent / "data" / "run-8b8539f"
TIMESTAMP = "8b8539f"
WRITTEN_AT = {"data": Path("/tmp/prev/scene"), "output_dir": Path("/tmp/prev/outputs")}
"""The paths the runs' config.yml hold (tests/data/run-8b8539f/README.md)."""
SMALL_FIELD = [
    "--pipeline.datamanager.train-num-rays-per-batch", "256",
    "--pipeline.model.log2-hashmap-size", "10", "--pipeline.model.num-levels", "4", "--pipeline.model.max-res", "32",
    "--pipeline.model.num-nerf-samples-per-ray", "16", "--pipeline.model.num-proposal-samples-per-ray", "16", "16",
    "--pipeline.model.proposal-net-args-list.0.log2-hashmap-size", "10",
    "--pipeline.model.proposal-net-args-list.1.log2-hashmap-size", "10",
]  # fmt: skip
"""The field the s2camp run was trained with (its checkpoint's shapes)."""


def _yaml_path(path: Path) -> str:
    """A path as PyYAML writes a ``PosixPath`` at the top level of a config.yml: its parts as a list."""
    return "".join(f"- {part}\n" for part in path.parts)


def previous_run(method: str, scene: Path, outputs: Path) -> Path:
    """The committed run of ``method`` under ``outputs`` (as ns-train lays it out), its config.yml pointed at
    ``scene`` and ``outputs``; returns its config.yml."""
    run = outputs / "previous" / method / TIMESTAMP
    shutil.copytree(RUNS / method, run)
    config = run / "config.yml"
    text = config.read_text()
    for key, path in (("data", scene), ("output_dir", outputs)):
        assert _yaml_path(WRITTEN_AT[key]) in text, f"{config} no longer holds {key} {WRITTEN_AT[key]}"
        text = text.replace(_yaml_path(WRITTEN_AT[key]), _yaml_path(path.resolve()))
    config.write_text(text)
    return config


def _run(command: list[str]) -> subprocess.CompletedProcess:
    tool = Path(command[0])
    if not (tool.is_absolute() and tool.exists()):
        pytest.fail(f"{command[0]} is not installed next to {sys.executable}")
    environment = {**train_commands.training_environment(), "COLUMNS": "200"}
    result = subprocess.run(command, capture_output=True, text=True, timeout=HANG_GUARD_S, env=environment)
    assert result.returncode == 0, f"{command[0]} exited with {result.returncode}:\n{result.stderr[-4000:]}"
    return result


def test_old_module_paths_lend_the_new_modules_names() -> None:
    """Every path of ``MOVED_MODULES`` imports, as a module of its own (ours are not replaced), and finds the new
    module's names and the renamed ones; other names under the old package are not found."""
    for old, new in compat.MOVED_MODULES.items():
        module, target = importlib.import_module(old), importlib.import_module(new)
        assert module is not target and sys.modules[new] is target
        public = [name for name in vars(target) if not name.startswith("_") and isinstance(vars(target)[name], type)]
        assert all(getattr(module, name) is getattr(target, name) for name in public), old
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    schedulers = importlib.import_module("s2camp_ns.nerfstudio.schedulers")
    assert schedulers.FloatExponentialDecaySchedulerConfig is ExponentialDecaySchedulerConfig
    from s2camp_ns.core import perturbation

    assert perturbation.DriftConfig is compat.RemovedConfig
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("s2camp_ns.nerfstudio.nothing_of_ours")
    with pytest.raises(AttributeError):
        _ = schedulers.NotAName


def test_a_previous_config_yml_loads_as_todays_classes(tiny_scene: Path, tmp_path: Path) -> None:
    from s2camp_ns.data.dataparser import S2CampDataParserConfig
    from s2camp_ns.method.splat_model import S2CampSplatModel, S2CampSplatModelConfig
    from s2camp_ns.method.trainer import S2CampTrainerConfig

    for method in ("s2camp", "s2camp-splat"):
        text = previous_run(method, tiny_scene, tmp_path / "outputs").read_text()
        assert "s2camp_ns.nerfstudio.dataparser.S2CampDataParserConfig" in text  # the old layout
        config = yaml.load(text, Loader=yaml.Loader)
        assert type(config) is S2CampTrainerConfig
        assert type(config.pipeline.datamanager.dataparser) is S2CampDataParserConfig
    assert type(config.pipeline.model) is S2CampSplatModelConfig and config.pipeline.model._target is S2CampSplatModel


@pytest.mark.slow
@pytest.mark.timeout(HANG_GUARD_S)
@pytest.mark.parametrize("method", ["s2camp", "s2camp-splat"])
def test_a_previous_run_exports_the_cameras_that_version_exported(method: str, tiny_scene: Path, tmp_path: Path):
    """``s2camp-export-cameras`` on the run gives the cameras that version's export of it gave (expected values in
    tests/data/run-8b8539f/export-8b8539f.json, written by that version)."""
    config = previous_run(method, tiny_scene, tmp_path / "outputs")
    scripts = Path(sys.executable).parent
    out = tmp_path / "out"
    export = [str(scripts / "s2camp-export-cameras"), "--load-config", str(config), "--output-dir", str(out)]
    result = _run(export)
    # That version's run has no anchor tracks: made once (said), kept; the next export loads them.
    assert "has no anchor_tracks.pt (a run of an earlier version)" in " ".join(result.stderr.split())
    assert (config.parent / "anchor_tracks.pt").is_file()
    assert "earlier version" not in _run(export).stderr
    expected = json.loads((RUNS / "export-8b8539f.json").read_text())[method]
    reconstruction = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    assert reconstruction.num_points3D() > 0
    assert all(point.track.length() >= 2 for point in reconstruction.points3D.values())
    assert sorted(image.name for image in reconstruction.images.values()) == sorted(expected)
    for image in reconstruction.images.values():
        then, pose = expected[image.name], image.cam_from_world()
        camera = reconstruction.cameras[image.camera_id]
        assert camera.model.name == then["camera"]["model"]
        params = then["camera"]["params"]
        if method == "s2camp-splat":  # that version scaled the undistorted images' pinhole to the originals' size;
            # the export now writes the undistorted images with their own camera (nerfstudio crops them to 63 x 47)
            assert (camera.width, camera.height) == (63, 47) != (then["camera"]["width"], then["camera"]["height"])
            sx, sy = camera.width / then["camera"]["width"], camera.height / then["camera"]["height"]
            params = [params[0] * sx, params[1] * sy, params[2] * sx, params[3] * sy, *params[4:]]
        for got, want in ((camera.params, params), (pose.rotation.quat, then["quat_xyzw"])):
            torch.testing.assert_close(torch.tensor(got).double(), torch.tensor(want).double(), rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(torch.tensor(pose.translation).double(), torch.tensor(then["translation"]).double())


@pytest.mark.slow
@pytest.mark.timeout(HANG_GUARD_S)
def test_a_previous_run_evaluates_and_resumes(tiny_scene: Path, tmp_path: Path):
    """``s2camp-eval`` scores the splat run's held-out view; ``ns-train s2camp --load-dir`` on the nerfacto run
    continues from its step 5 for two steps and saves step 7."""
    scripts = Path(sys.executable).parent
    outputs = tmp_path / "outputs"
    config = previous_run("s2camp-splat", tiny_scene, outputs)
    aligned = tmp_path / "aligned.json"
    eval_command = [str(scripts / "s2camp-eval"), "--load-config", str(config), "--output-path", str(aligned)]
    _run([*eval_command, "--alignment.steps", "10"])
    result = json.loads(aligned.read_text())
    assert result["step"] == 5 and len(result["views"]) == 2 and result["mean"]["psnr"] > 5.0

    checkpoints = previous_run("s2camp", tiny_scene, outputs).parent / "nerfstudio_models"
    train = train_commands.ns_train_base_arguments("s2camp", tiny_scene, outputs, "resumed", "run", 2, 2)
    _run([*train, "--load-dir", str(checkpoints), "--vis", "tensorboard", *SMALL_FIELD])
    saved = torch.load(outputs / "resumed" / "s2camp" / "run" / "nerfstudio_models" / "step-000000007.ckpt")
    assert saved["step"] == 7
