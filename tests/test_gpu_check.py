"""``make gpu-check`` (benchmarks/gpu_check) on the CPU: its options, the refusal without CUDA, the scene, the
``cuda`` test selection and skip reason, the command lines, the measurements and the report."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import tyro
from conftest import CUDA_SKIP_REASON
from hang_guard import HANG_GUARD_S
from test_camera_optimizer import NUM_CAMERAS, make_cameras

from s2camp_ns.benchmarks.gpu_check import report
from s2camp_ns.benchmarks.gpu_check.config import GpuCheckConfig
from s2camp_ns.benchmarks.gpu_check.environment import Environment, GpuCheckError, describe, require_cuda
from s2camp_ns.benchmarks.gpu_check.measured_train import StepClock
from s2camp_ns.benchmarks.gpu_check.report import MethodResult, StageResult
from s2camp_ns.benchmarks.gpu_check.runs import (
    check_nccl_checkpoint,
    cuda_tests_result,
    generate_scene,
    junit_counts,
    method_result,
    seconds_per_iteration,
    train_arguments,
)
from s2camp_ns.benchmarks.gpu_check.stock_nerfacto import StockNerfactoModel
from s2camp_ns.scene.make_scene import MakeSceneConfig

REPOSITORY = Path(__file__).resolve().parents[1]
NO_CUDA = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
"""Environment of a subprocess that must see no CUDA device, on any machine."""
CUDA_TESTS = [
    "tests/test_cuda.py::test_camera_optimizer_on_cuda_matches_the_cpu",
    "tests/test_cuda.py::test_training_steps_on_cuda_with_mixed_precision[s2camp]",
    "tests/test_cuda.py::test_training_steps_on_cuda_with_mixed_precision[s2camp-camp]",
    "tests/test_cuda.py::test_training_steps_on_cuda_with_mixed_precision[s2camp-so3xr3]",
    "tests/test_cuda.py::test_gsplat_imports",
    "tests/test_device_audit.py::test_camera_optimizer_on_real_cuda[RADIAL-per-camera-frolov]",
    "tests/test_device_audit.py::test_camera_optimizer_on_real_cuda[OPENCV-per-image-camp-random]",
    "tests/test_device_audit.py::test_camera_optimizer_on_real_cuda[FULL_OPENCV-per-camera-camp-random]",
    "tests/test_device_audit.py::test_camera_optimizer_on_real_cuda[OPENCV_FISHEYE-per-image-frolov]",
    "tests/test_mixed_precision.py::test_camera_gradients_under_cuda_autocast_are_close_to_float32",
    "tests/test_splat_alignment.py::test_gsplat_cuda_alignment_gradients_match_the_reference",
    "tests/test_splat_identity.py::test_gsplat_cuda_intrinsics_gradient_through_view_matrix",
]
CUDA_MODULES = [
    "test_cuda.py",
    "test_device_audit.py",
    "test_mixed_precision.py",
    "test_splat_alignment.py",
    "test_splat_identity.py",
]
"""The test modules that use the ``cuda`` marker."""
NO_GPU = Environment(
    cuda_available=False, device_names=(), torch_version="2.14.1", torch_cuda="13.0", tinycudann=False, nvcc=None,
    gsplat=True,
)  # fmt: skip


# ---------------------------------------------------------------------------------------------------- options
def test_options_parse_from_the_command_line() -> None:
    config = tyro.cli(
        GpuCheckConfig,
        args=[
            "--stages", "tests", "train", "--methods", "nerfacto", "s2camp", "--iterations", "50",
            "--warmup-steps", "5", "--write-docs", "--scene.num-cameras", "16",
        ],
    )  # fmt: skip
    assert config.stages == ("tests", "train")
    assert config.methods == ("nerfacto", "s2camp")
    assert (config.iterations, config.warmup_steps, config.write_docs) == (50, 5, True)
    assert config.scene.num_cameras == 16
    config.validate()


def test_defaults_are_a_room_sized_scene_and_the_four_methods() -> None:
    config = GpuCheckConfig()
    config.validate()
    assert (config.scene.width, config.scene.height) == (778, 518)
    assert config.methods == ("nerfacto", "s2camp-so3xr3", "s2camp", "s2camp-camp")
    assert config.baseline == "nerfacto"
    assert config.report_path == Path("outputs/gpu-check/gpu-check.md")
    assert not config.write_docs


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"stages": ("tests", "bogus")}, "stages must be one of"),
        ({"stages": ()}, "stages must name at least one"),
        ({"methods": ("s2camp", "nerfacto-huge")}, "methods must be one of"),
        ({"methods": ("s2camp", "s2camp")}, "must not repeat"),
        ({"warmup_steps": 299}, r"warmup_steps must be an integer in \[0, iterations - 1\) = \[0, 299\)"),
        ({"iterations": 0}, "iterations"),
        ({"run_timeout_minutes": 0.0}, "run_timeout_minutes must be > 0"),
        ({"tcnn_source": Path("/nonexistent/tcnn")}, "tcnn_source must be a tiny-cuda-nn checkout"),
        ({"cpu_smoke": True, "write_docs": True}, "write_docs must be False with cpu_smoke"),
    ],
)
def test_bad_options_are_refused_by_name(overrides: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        replace(GpuCheckConfig(), **overrides).validate()


def test_cpu_smoke_runs_only_the_training_on_a_tiny_cpu_scene() -> None:
    config = GpuCheckConfig(cpu_smoke=True).effective()
    config.validate()
    assert config.stages == ("train",)
    assert (config.scene.num_cameras, config.scene.width, config.scene.height) == (9, 48, 36)
    assert config.iterations == 8
    arguments = train_arguments(config, "nerfacto", Path("scene"))
    assert arguments[arguments.index("--machine.device-type") + 1] == "cpu"
    assert GpuCheckConfig().effective() == GpuCheckConfig()


def test_train_arguments_of_the_methods() -> None:
    config = GpuCheckConfig(output_dir=Path("out"))
    shared = [
        "--data", "scene",
        "--output-dir", "out/runs",
        "--experiment-name", "gpu-check",
    ]  # fmt: skip
    run = [
        "--max-num-iterations", "300",
        "--steps-per-save", "300",
        "--steps-per-eval-batch", "0",
        "--steps-per-eval-image", "0",
        "--steps-per-eval-all-images", "0",
        "--vis", "tensorboard",
        "--pipeline.datamanager.train-num-rays-per-batch", "4096",
    ]  # fmt: skip
    perturbed = ["s2camp-data", "--perturbation.enabled", "True"]
    assert train_arguments(config, "s2camp", Path("scene")) == [
        "s2camp", *shared, "--timestamp", "s2camp", *run, "--pipeline.model.camera-optimizer.refresh-every", "100",
        *perturbed,
    ]  # fmt: skip
    for method in ("nerfacto", "s2camp-so3xr3", "s2camp-camp"):
        assert train_arguments(config, method, Path("scene")) == [
            method,
            *shared,
            "--timestamp",
            method,
            *run,
            *perturbed,
        ]


# ------------------------------------------------------------------------------------------------- no CUDA
def test_refuses_without_cuda_with_a_clear_message(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    with pytest.raises(GpuCheckError) as refusal:
        require_cuda(NO_GPU)
    assert str(refusal.value) == (
        "gpu-check needs a CUDA device, and torch.cuda.is_available() is False here (torch 2.14.1, built for CUDA "
        "13.0). Nothing was checked. Run it on a machine with an NVIDIA GPU and a driver for that CUDA version; the "
        "CPU-side tests run with `make test`."
    )
    require_cuda(replace(NO_GPU, cuda_available=True, device_names=("NVIDIA H200",)))  # no error


def test_the_command_exits_non_zero_without_cuda_and_writes_no_report(tmp_path: Path) -> None:
    output = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "s2camp_ns.benchmarks.gpu_check", "--output-dir", str(output)],
        capture_output=True, text=True, env=NO_CUDA, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    text = " ".join((result.stdout + result.stderr).split())
    assert result.returncode == 2, text
    assert "gpu-check: gpu-check needs a CUDA device, and torch.cuda.is_available() is False here" in text
    assert "CUDA_VISIBLE_DEVICES=''" in text
    assert not output.exists()


def test_a_missing_tinycudann_is_reported_with_the_fallback() -> None:
    lines = describe(NO_GPU)
    assert lines[0] == "torch 2.14.1 (CUDA 13.0)"
    assert lines[1] == "CUDA devices: none"
    assert lines[2].startswith("tiny-cuda-nn: not installed. It is not on the package registries")
    assert "nerfstudio's pure-torch fallback" in lines[2]
    assert lines[3] == "CUDA compiler (nvcc): not found"
    with_gpus = replace(NO_GPU, cuda_available=True, device_names=("A", "B"), tinycudann=True)
    assert describe(with_gpus)[1] == "CUDA devices: cuda:0 A, cuda:1 B"
    assert describe(with_gpus)[2].startswith("tiny-cuda-nn: installed")


# ------------------------------------------------------------------------------------------------------ scene
def test_the_scene_is_generated_once_and_reused(tmp_path: Path) -> None:
    scene = MakeSceneConfig(num_cameras=4, width=64, height=48, points_per_image=150, k1=0.0, k2=0.0)
    config = GpuCheckConfig(output_dir=tmp_path, scene=scene)
    stage = generate_scene(config)
    path = tmp_path / "scene"
    assert stage.passed
    assert re.fullmatch(r"4 images 64x48, generated in \d+ s", stage.detail)
    assert len(list((path / "images").glob("*.png"))) == 4
    assert (path / "sparse" / "0" / "cameras.bin").is_file()
    again = generate_scene(config)
    assert again.detail == f"4 images 64x48, reused from {tmp_path / 'scene'}"
    other = generate_scene(replace(config, scene=replace(scene, seed=1)))
    assert "generated in" in other.detail


# -------------------------------------------------------------------------------------- the cuda test selection
def test_the_cuda_marker_selects_exactly_the_cuda_tests() -> None:
    """``-m cuda`` selects exactly the marked tests of the modules that use the marker and nothing unmarked (here:
    this module's tests). (Collecting the whole suite would say the same in about 30 s of CPU time.)"""
    uses_marker = re.compile(r"mark\.cuda\b")
    marked = [path.name for path in sorted((REPOSITORY / "tests").glob("*.py")) if uses_marker.search(path.read_text())]
    assert marked == CUDA_MODULES
    result = subprocess.run(
        [
            sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "cuda",
            *[f"tests/{name}" for name in CUDA_MODULES], "tests/test_gpu_check.py", "-p", "no:cacheprovider",
        ],
        capture_output=True, text=True, env=NO_CUDA, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    selected = [line for line in result.stdout.splitlines() if "::" in line]
    assert selected == CUDA_TESTS


def test_without_cuda_the_cuda_tests_skip_with_the_reason_and_nothing_else_does(tmp_path: Path) -> None:
    junit = tmp_path / "junit.xml"
    unmarked = "tests/test_gpu_check.py::test_the_report_tables_are_exact"
    result = subprocess.run(
        [
            sys.executable, "-m", "pytest", "-q", "tests/test_cuda.py", unmarked, "-p", "no:cacheprovider",
            f"--junitxml={junit}",
        ],
        capture_output=True, text=True, env=NO_CUDA, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:]
    assert junit_counts(junit) == {"tests": 6, "failures": 0, "errors": 0, "skipped": 5, "passed": 1}
    import xml.etree.ElementTree as ElementTree

    cases = {case.get("name"): case for case in ElementTree.parse(junit).getroot().iter("testcase")}
    assert cases["test_the_report_tables_are_exact"].find("skipped") is None
    skipped = {name: case.find("skipped") for name, case in cases.items() if case.get("classname") == "tests.test_cuda"}
    assert len(skipped) == 5
    for name, element in skipped.items():
        assert element is not None and CUDA_SKIP_REASON in element.get("message"), name
    # The check itself counts skips as a failure: on a CUDA machine nothing may skip.
    stage = cuda_tests_result(0, junit_counts(junit), junit, 60.0)
    assert stage.passed is False and stage.detail.startswith("1 passed, 5 skipped")


# ---------------------------------------------------------------------------------------- measurements, results
JUNIT = """<?xml version="1.0" encoding="utf-8"?>
<testsuites><testsuite name="pytest" errors="{errors}" failures="{failures}" skipped="{skipped}" tests="{tests}">
</testsuite></testsuites>"""


def _junit(tmp_path: Path, **counts: int) -> Path:
    path = tmp_path / "junit.xml"
    path.write_text(JUNIT.format(**counts))
    return path


def test_cuda_tests_pass_only_when_all_ran_and_passed(tmp_path: Path) -> None:
    log = Path("logs/cuda-tests.log")
    every = junit_counts(_junit(tmp_path, errors=0, failures=0, skipped=0, tests=5))
    assert every == {"tests": 5, "failures": 0, "errors": 0, "skipped": 0, "passed": 5}
    assert cuda_tests_result(0, every, log, 60.0) == StageResult("`pytest -m cuda`", True, "5 passed")
    failed = junit_counts(_junit(tmp_path, errors=1, failures=1, skipped=0, tests=5))
    assert cuda_tests_result(1, failed, log, 60.0) == StageResult(
        "`pytest -m cuda`", False, "3 passed, 1 failures, 1 errors; log logs/cuda-tests.log"
    )
    none = junit_counts(_junit(tmp_path, errors=0, failures=0, skipped=0, tests=0))
    assert cuda_tests_result(5, none, log, 60.0).detail == "no test marked cuda was collected; log logs/cuda-tests.log"
    assert cuda_tests_result(None, None, log, 120.0) == StageResult(
        "`pytest -m cuda`", False, "pytest ran past 2 minutes and was stopped; log logs/cuda-tests.log"
    )


def test_step_times_and_seconds_per_iteration() -> None:
    clock = StepClock(synchronize=False, stamps=[1.0, 1.5, 2.5, 2.75])
    assert clock.step_seconds() == [0.5, 1.0, 0.25]
    assert seconds_per_iteration([1.0, 0.5, 0.1, 0.2, 0.3], warmup_steps=2) == pytest.approx(0.2)
    assert seconds_per_iteration([1.0, 0.5, 0.1, 0.2, 0.3], warmup_steps=4) is None


def test_method_result_from_the_measurements() -> None:
    evaluation = {
        "start_rot_err": 0.3, "rot_err": 0.1, "start_pos_err": 4e-3, "pos_err": 1e-3, "start_focal_err": 3.4,
        "focal_err": 0.5, "psnr": 24.0,
    }  # fmt: skip
    measured = {"step_seconds": [9.0, 0.02, 0.04], "peak_memory_bytes": 123, "evaluation": evaluation}
    assert method_result("s2camp", measured, 1, None) == MethodResult(
        "s2camp", None, pytest.approx(0.03), 123, 0.3, 0.1, 4e-3, 1e-3, 3.4, 0.5, 24.0
    )
    no_evaluation = method_result("s2camp", {**measured, "evaluation": None}, 1, "ns-train s2camp exited with 1")
    assert no_evaluation.error == "ns-train s2camp exited with 1"
    assert no_evaluation.sec_per_iter == pytest.approx(0.03) and no_evaluation.psnr is None
    assert method_result("s2camp", {**measured, "evaluation": None}, 1, None).error == "no evaluation written"
    assert method_result("s2camp", None, 1, None) == MethodResult("s2camp", "no measurements written")


def test_the_nccl_checkpoint_check(tmp_path: Path) -> None:
    path = tmp_path / "step-000000059.ckpt"
    key = "_model.module.camera_optimizer.whitened_delta"
    assert check_nccl_checkpoint(path) == f"no final checkpoint {path}"
    torch.save({"pipeline": {key: torch.tensor([[0.0, 1e-4]])}}, path)
    assert check_nccl_checkpoint(path) is None
    torch.save({"pipeline": {key: torch.zeros(2, 6)}}, path)
    assert check_nccl_checkpoint(path) == f"the camera latent in {path} is still zero: the cameras were not refined"
    torch.save({"pipeline": {key: torch.tensor([[float("nan")]])}}, path)
    assert check_nccl_checkpoint(path) == f"the camera latent in {path} is not finite"
    torch.save({"pipeline": {}}, path)
    assert check_nccl_checkpoint(path) == f"{path} holds 0 camera latents (whitened_delta), expected 1"


def test_stock_nerfacto_cameras_are_refined_as_its_rays_are() -> None:
    """nerfstudio's stock optimizer moves training rays in the world frame (origins + t, R directions): the refined
    camera is [R_adj R | c + t], the frame the evaluation compares against the true cameras."""
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

    optimizer = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=NUM_CAMERAS, device="cpu")
    with torch.no_grad():
        optimizer.pose_adjustment.copy_(0.05 * torch.randn(NUM_CAMERAS, 6, generator=torch.Generator().manual_seed(0)))
    cameras, reference = make_cameras(), make_cameras(k1=-0.01)
    datamanager = SimpleNamespace(
        train_dataset=SimpleNamespace(cameras=cameras),
        train_dataparser_outputs=SimpleNamespace(metadata={"reference_cameras": reference}),
    )
    model = StockNerfactoModel(SimpleNamespace(camera_optimizer=optimizer), datamanager)
    c2w, fx = model.refined_train_cameras()
    with torch.no_grad():
        correction = optimizer(torch.arange(NUM_CAMERAS)).double()
    base = cameras.camera_to_worlds.double()
    expected = torch.cat([correction[:, :, :3] @ base[:, :, :3], base[:, :, 3:] + correction[:, :, 3:]], dim=-1)
    assert c2w.dtype == torch.float64 and c2w.device.type == "cpu"
    torch.testing.assert_close(c2w, expected, rtol=0, atol=1e-6)
    assert (c2w - base).abs().max() > 1e-3  # the adjustment is not the identity
    torch.testing.assert_close(fx, cameras.fx.reshape(-1).double())
    assert model.reference_cameras() is reference
    assert not model.uses_s2camp_optimizer
    mismatched = SimpleNamespace(**{**vars(datamanager), "train_dataparser_outputs": SimpleNamespace(
        metadata={"reference_cameras": reference[:2]})})  # fmt: skip
    assert StockNerfactoModel(SimpleNamespace(camera_optimizer=optimizer), mismatched).reference_cameras() is None


# ------------------------------------------------------------------------------------------------------ report
RESULTS = [
    MethodResult("nerfacto", None, 0.040, 3 * 2**30, 0.3, 0.25, 4.1e-3, 3.0e-3, 3.38, 3.0, 25.123),
    MethodResult("s2camp", None, 0.044, int(3.5 * 2**30), 0.3, 0.05, 4.1e-3, 1.0e-3, 3.38, 0.4, 26.0),
    MethodResult("s2camp-camp", "ns-train s2camp-camp exited with status 1; log x.log"),
]
STAGES = [
    StageResult("`pytest -m cuda`", True, "5 passed"),
    StageResult("2-process NCCL training (s2camp)", None, "needs 2 CUDA devices, this machine has 1"),
]


def test_the_report_tables_are_exact() -> None:
    assert report.method_table(RESULTS, "nerfacto") == "\n".join(
        [
            "| method | ms / iter | vs nerfacto | peak CUDA memory (GiB) | rotation err (deg) | position err | "
            "focal err (px) | held-out PSNR (dB) | result |",
            "|---|---|---|---|---|---|---|---|---|",
            "| nerfacto | 40.0 | 1.00x | 3.00 | 0.300 → 0.250 | 4.10e-03 → 3.00e-03 | 3.38 → 3.00 | 25.12 | passed |",
            "| s2camp | 44.0 | 1.10x | 3.50 | 0.300 → 0.050 | 4.10e-03 → 1.00e-03 | 3.38 → 0.40 | 26.00 | passed |",
            "| s2camp-camp | - | - | - | - | - | - | - | FAILED: ns-train s2camp-camp exited with status 1; "
            "log x.log |",
        ]
    )
    assert report.stage_table(STAGES) == "\n".join(
        [
            "| check | result | detail |",
            "|---|---|---|",
            "| `pytest -m cuda` | passed | 5 passed |",
            "| 2-process NCCL training (s2camp) | not run | needs 2 CUDA devices, this machine has 1 |",
        ]
    )
    # Without the baseline's time there is no ratio.
    without_baseline = report.method_table(RESULTS[1:2], None).splitlines()
    assert without_baseline[0].split(" | ")[2] == "vs baseline"
    assert without_baseline[2].split(" | ")[2] == "-"


def test_pass_and_fail_of_the_whole_check() -> None:
    assert report.all_passed(STAGES, RESULTS[:2])  # a stage that did not run fails nothing
    assert not report.all_passed(STAGES, RESULTS)  # a method that failed
    assert not report.all_passed([*STAGES, StageResult("scene", False, "s2camp-make-scene failed")], RESULTS[:2])


def test_the_report_file(tmp_path: Path) -> None:
    path = report.write(
        tmp_path / "gpu-check.md", ["torch 2.14.1 (CUDA 13.0)"], STAGES, RESULTS, "Setup text.", "nerfacto", 9.46, 8.0
    )
    assert path == tmp_path / "gpu-check.md"
    text = path.read_text()
    assert text.startswith("# GPU check\n\nRegenerate with `make gpu-check`.\n")
    for part in (
        "- torch 2.14.1 (CUDA 13.0)\n",
        "## Checks\n",
        report.stage_table(STAGES),
        "## Training side by side\n",
        "Setup text.\n",
        report.method_table(RESULTS, "nerfacto"),
        "Whole check: 9.5 minutes, over its budget of 8 minutes.\n",
    ):
        assert part in text
    assert not list(tmp_path.glob("*.tmp"))
    json.dumps(text)  # plain text, no objects


def test_a_report_is_rebuilt_from_the_folder_of_a_check_that_was_stopped(tmp_path: Path) -> None:
    """A check whose machine was lost before the report: --report-from writes it from what the check left, on a
    machine without CUDA, and a method whose evaluation is missing is a failed row."""
    from s2camp_ns.benchmarks.gpu_check.cli import run

    folder = tmp_path / "check"
    (folder / "runs").mkdir(parents=True)
    (folder / "logs").mkdir()
    (folder / "environment.txt").write_text("torch 2.11.0+cu130 (CUDA 13.0)\nCUDA devices: cuda:0 H100\n")
    (folder / "logs" / "cuda-tests.xml").write_text(
        '<testsuites><testsuite tests="5" failures="0" errors="0" skipped="0"/></testsuites>'
    )
    evaluation = {
        "start_rot_err": 0.3, "rot_err": 0.25, "start_pos_err": 4.1e-3, "pos_err": 3e-3, "start_focal_err": 3.38,
        "focal_err": 3.0, "psnr": 25.123,
    }  # fmt: skip
    steps = [9.0] * 30 + [0.04] * 270
    (folder / "runs" / "nerfacto.json").write_text(
        json.dumps({"step_seconds": steps, "peak_memory_bytes": 3 * 2**30, "evaluation": evaluation})
    )
    (folder / "runs" / "s2camp.json").write_text(json.dumps({"step_seconds": [0.05] * 299, "peak_memory_bytes": 1}))
    config = GpuCheckConfig(report_from=folder, output_dir=tmp_path / "out")
    assert run(config) is False  # s2camp has no evaluation
    text = config.report_path.read_text()
    assert f"Regenerate with `python -m s2camp_ns.benchmarks.gpu_check --report-from {folder.as_posix()}`." in text
    assert "_measured on the machine listed below; report rebuilt " in text and "Python" not in text
    assert "- torch 2.11.0+cu130 (CUDA 13.0)\n- CUDA devices: cuda:0 H100\n" in text
    assert "| `pytest -m cuda` | passed | 5 passed |" in text
    assert (
        "| nerfacto | 40.0 | 1.00x | 3.00 | 0.300 → 0.250 | 4.10e-03 → 3.00e-03 | 3.38 → 3.00 | 25.12 | passed |"
        in text
    )
    assert "| s2camp | 50.0 | 1.25x | 0.00 | - | - | - | - | FAILED: no evaluation written |" in text
    # A method that left no measurements is not a row.
    assert not [line for line in text.splitlines() if line.startswith("| s2camp-camp ")]
    assert "Whole check: its wall time was not recorded" in text
    with pytest.raises(ValueError, match="report_from must be the output folder of an earlier check"):
        GpuCheckConfig(report_from=tmp_path / "out").validate()


# ---------------------------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_cpu_smoke_run_trains_and_evaluates_stock_nerfacto(tmp_path: Path) -> None:
    """The training stage end to end on the CPU (``--cpu-smoke``): measured_train runs stock nerfacto (offline
    without its LPIPS weights), evaluates it through StockNerfactoModel, and the report holds its row. About 35 s of
    CPU time. Its training run gets the suite's hang guard as gpu-check's run timeout, whose default (6 minutes) is
    sized for a GPU, not for a busy CPU."""
    output = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "s2camp_ns.benchmarks.gpu_check", "--cpu-smoke", "--methods", "nerfacto", "--output-dir",
         str(output), "--run-timeout-minutes", str(HANG_GUARD_S / 60)],
        capture_output=True, text=True, env={**NO_CUDA, "OMP_NUM_THREADS": "1"}, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + (output / "logs" / "train-nerfacto.log").read_text()[-3000:]
    text = (output / "gpu-check.md").read_text()
    assert "**CPU smoke run of the script itself (`--cpu-smoke`)" in text
    assert "| scene | passed | 9 images 48x36, generated in" in text
    row = next(line for line in text.splitlines() if line.startswith("| nerfacto |")).split(" | ")
    assert row[2] == "1.00x" and row[3] == "-"  # its own baseline; no CUDA memory on the CPU
    start_rot, final_rot = (float(value) for value in row[4].split(" → "))
    assert start_rot > 0.05  # perturbed start (the table rounds to 1e-3 deg: seven steps may move less)
    assert 5.0 < float(row[7]) < 60.0  # held-out PSNR after test-time alignment
    assert row[8] == "passed |"
    measured = json.loads((output / "runs" / "nerfacto.json").read_text())
    evaluation = measured["evaluation"]  # unrounded: the stock optimizer moved the cameras
    assert evaluation["rot_err"] != evaluation["start_rot_err"] and round(evaluation["start_rot_err"], 3) == start_rot
    assert len(measured["step_seconds"]) == 7 and all(seconds > 0 for seconds in measured["step_seconds"])
    assert not list((output / "runs").glob("gpu-check/*/*/nerfstudio_models"))  # checkpoints removed
    # The machine is written first, for a report rebuilt from this folder (--report-from).
    environment = (output / "environment.txt").read_text().splitlines()
    assert environment[0].startswith("torch ") and environment[1] == "CUDA devices: none"
    assert "- CUDA devices: none\n" in text
