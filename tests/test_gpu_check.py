"""The GPU check and its regime stage (benchmarks/s2camp_bench/gpu_check) on the CPU: options, the refusal
without CUDA, the deadline, the records written as results are made and the reports rebuilt from them (also for a
cut run), the ``cuda`` test selection and its collection from an installed package, the offline bundle."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
import zipfile
from dataclasses import replace
from pathlib import Path

import pytest
import tyro
from conftest import CUDA_SKIP_REASON
from hang_guard import HANG_GUARD_S

from s2camp_bench.gpu_check import report
from s2camp_bench.gpu_check.bundle import OWN_PROJECTS, SLIM, normalized, to_carry
from s2camp_bench.gpu_check.cli import allowed
from s2camp_bench.gpu_check.config import (
    CUDA_TEST_FILES,
    GROUPS,
    LEASE_SCENE,
    STAGE_MINIMUM_S,
    CheckFolder,
    GpuCheckConfig,
)
from s2camp_bench.gpu_check.environment import Environment, GpuCheckError, describe, require_cuda
from s2camp_bench.gpu_check.measured_train import TrainPlan, run_stop
from s2camp_bench.gpu_check.processes import Deadline
from s2camp_bench.gpu_check.records import StageResult, append_record, read_lines, read_records
from s2camp_bench.gpu_check.regime import variant_arguments
from s2camp_bench.gpu_check.run_logs import REFINED, START, ErrorRecord, RunEnd, StepLog, read_step_log
from s2camp_bench.gpu_check.tests_stage import cuda_tests_result, junit_counts, pytest_command
from s2camp_bench.gpu_check.timing import group_plan, timing_arguments, timing_rows
from s2camp_bench.gpu_check.wheels import slim_wheel
from s2camp_bench.train_commands import PHOTOMETRIC_ONLY

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
NO_GPU = Environment(
    cuda_available=False, device_names=(), torch_version="2.14.1", torch_cuda="13.0", tinycudann=False, gsplat=True
)
NERFACTO_GROUP = "off/s2camp-so3xr3/s2camp"


# ---------------------------------------------------------------------------------------------------- options
def test_options_parse_from_the_command_line() -> None:
    config = tyro.cli(
        GpuCheckConfig,
        args=[
            "--stages", "timing", "tests", "--groups", "off/s2camp", "--timing-steps", "50", "--warmup-steps",
            "5", "--deadline", "240", "--scene.num-cameras", "16",
        ],
    )  # fmt: skip
    assert config.stages == ("timing", "tests")
    assert config.groups == ("off/s2camp",)
    assert (config.timing_steps, config.warmup_steps, config.deadline) == (50, 5, 240.0)
    assert config.scene.num_cameras == 16
    config.validate()


def test_defaults_are_the_lease_scene_the_groups_and_the_stage_order() -> None:
    config = GpuCheckConfig()
    config.validate()
    assert config.scene == LEASE_SCENE and (config.scene.width, config.scene.height) == (640, 480)
    assert config.stages == ("timing", "regime", "tests")
    assert config.groups == (NERFACTO_GROUP, "splat-off/s2camp-splat-so3xr3/s2camp-splat") == GROUPS
    assert config.regime_variants == ("tracks-alone", "s2camp", "images-alone")
    assert config.deadline is None
    assert config.folder.steps_log("s2camp") == Path("outputs/gpu-check/timing/s2camp.jsonl")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"stages": ("tests", "rest")}, "stages must be one of"),
        ({"regime_variants": ("s2camp", "photometric")}, r"regime_variants must be one of .*got 'photometric'"),
        ({"regime_passes": 0}, "regime_passes must be a number > 0, got 0"),
        ({"groups": ("off",)}, "groups must be 'baseline/method/...' with two or more different methods, got"),
        ({"groups": ("off/off",)}, "groups must be 'baseline/method/...' with two or more different methods"),
        ({"groups": ("off/nerfacto",)}, "groups' methods must be one of"),
        ({"warmup_steps": 199}, r"warmup_steps must be an integer in \[0, 199\)"),
        ({"timing_steps": 0}, "timing_steps"),
        ({"deadline": -5.0}, "deadline must be a number > 0, got -5.0"),
        ({"refresh_repeats": -1}, "refresh_repeats must be an integer >= 0, got -1"),
        ({"run_timeout_minutes": 0.0}, "run_timeout_minutes must be a number > 0, got 0.0"),
        ({"report_from": Path("/nonexistent/check")}, "report_from must be the folder of an earlier check"),
    ],
)
def test_bad_options_are_refused_by_name(overrides: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        replace(GpuCheckConfig(), **overrides).validate()


def test_cpu_smoke_keeps_what_the_command_line_chose() -> None:
    smoke = GpuCheckConfig(cpu_smoke=True).effective()
    smoke.validate()
    assert smoke.stages == ("timing", "regime")  # the CPU cannot run the cuda tests
    assert smoke.groups == (NERFACTO_GROUP,)  # splatting needs gsplat's CUDA kernels
    assert (smoke.timing_steps, smoke.scene.width, smoke.scene.height) == (8, 320, 240)
    chosen = GpuCheckConfig(cpu_smoke=True, timing_steps=500).effective()
    assert chosen.timing_steps == 500 and chosen.warmup_steps == 2
    assert GpuCheckConfig().effective() == GpuCheckConfig()


def test_timing_runs_at_the_methods_defaults_with_refinement_off_as_the_baseline() -> None:
    config = GpuCheckConfig(output_dir=Path("out"))
    timing = timing_arguments(config, "s2camp", Path("scene"))
    assert timing[:9] == ["s2camp", "--data", "scene", "--output-dir", "out/ns-train", "--experiment-name", "timing",
                          "--timestamp", "s2camp"]  # fmt: skip
    assert timing[-3:] == ["s2camp-data", "--perturbation.enabled", "True"]
    assert timing[timing.index("--max-num-iterations") + 1] == "200"
    # The method's defaults: no ray batch, no refresh interval, no device, no model size given.
    assert not [a for a in timing if a.startswith(("--pipeline.", "--machine."))]
    off = timing_arguments(config, "off", Path("scene"))
    # s2camp with refinement off (and its own timestamp): nerfacto's field and data path, no camera optimizer.
    mode = "--pipeline.model.camera-optimizer.mode"
    assert off[0] == "s2camp" and [a for a in off if a not in timing] == ["off", mode, "off"]
    assert timing_arguments(config, "splat-off", Path("scene"))[0] == "s2camp-splat"
    assert timing_arguments(config, "s2camp-so3xr3", Path("scene"))[0] == "s2camp-so3xr3"
    smoke = timing_arguments(GpuCheckConfig(cpu_smoke=True).effective(), "off", Path("scene"))
    assert smoke[smoke.index("--machine.device-type") + 1] == "cpu"


def test_a_group_is_one_plan_baseline_first_sharing_the_time_left(tmp_path: Path) -> None:
    config = GpuCheckConfig(output_dir=tmp_path)
    plan = group_plan(config, NERFACTO_GROUP, Path("scene"), stop_at=123.0)
    assert [spec.arguments[0] for spec in plan.runs] == ["s2camp", "s2camp-so3xr3", "s2camp"]
    assert [spec.refresh_repeats for spec in plan.runs] == [3, 3, 3]  # a no-op without S2CamP's refiner
    assert [spec.steps_log for spec in plan.runs] == [str(tmp_path / "timing" / f"{m}.jsonl") for m in
                                                       ("off", "s2camp-so3xr3", "s2camp")]  # fmt: skip
    assert (plan.stop_at, plan.share) == (123.0, True)
    assert TrainPlan.read(plan.write(tmp_path / "plan.json")) == plan


def test_the_time_left_is_shared_among_the_runs_of_a_plan_that_shares_it() -> None:
    now = time.time()
    shared = TrainPlan([], now + 100.0, share=True)
    assert run_stop(shared, 2) == pytest.approx(now + 50.0, abs=1.0)
    assert run_stop(shared, 1) == pytest.approx(now + 100.0, abs=1.0)
    assert run_stop(TrainPlan([], now + 100.0), 2) == now + 100.0  # each run may use it all
    assert run_stop(TrainPlan([], None, share=True), 2) is None


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


@pytest.mark.parametrize("command", ["s2camp_bench.gpu_check"])
def test_the_commands_exit_non_zero_without_cuda_and_write_nothing(tmp_path: Path, command: str) -> None:
    output = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", command, "--output-dir", str(output)],
        capture_output=True, text=True, env=NO_CUDA, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    text = " ".join((result.stdout + result.stderr).split())
    assert result.returncode == 2, text
    assert "gpu-check needs a CUDA device, and torch.cuda.is_available() is False here" in text
    assert "CUDA_VISIBLE_DEVICES=''" in text
    assert not output.exists()


def test_a_missing_tinycudann_is_reported_with_the_fallback() -> None:
    lines = describe(NO_GPU)
    assert lines[:2] == ["torch 2.14.1 (CUDA 13.0)", "CUDA devices: none"]
    assert lines[2].startswith("tiny-cuda-nn: not installed (not on the package registries)")
    assert "nerfstudio's pure-torch fallback" in lines[2]
    assert lines[3] == "gsplat: installed (its CUDA kernels compile on first use)"
    with_gpus = replace(NO_GPU, cuda_available=True, device_names=("A", "B"), tinycudann=True)
    assert describe(with_gpus)[1:3] == ["CUDA devices: cuda:0 A, cuda:1 B", "tiny-cuda-nn: installed"]


# ----------------------------------------------------------------------------------------------- deadline
def test_the_deadline() -> None:
    assert Deadline.after(None).remaining() == float("inf") and Deadline().allows(1e9)
    deadline = Deadline.after(100.0)
    assert 99.0 < deadline.remaining() <= 100.0
    assert deadline.allows(90.0) and not deadline.allows(101.0)
    assert deadline.limit(10.0) == 10.0 and 99.0 < deadline.limit(500.0) <= 100.0
    assert Deadline(time.time() - 5.0).remaining() == 0.0
    with pytest.raises(ValueError, match=r"deadline must be a number of seconds > 0, got 0"):
        Deadline.after(0)


def test_a_stage_with_too_little_time_left_is_recorded_as_skipped(tmp_path: Path) -> None:
    config = GpuCheckConfig(output_dir=tmp_path)
    tmp_path.joinpath("environment.txt").write_text("torch 2.11.0+cu130 (CUDA 13.0)\nCUDA devices: cuda:0 H100\n")
    deadline = Deadline(time.time() + 30.0)
    assert not allowed(config, deadline, "tests", "`pytest -m cuda`")
    assert not allowed(config, deadline, "timing", f"timing {NERFACTO_GROUP}")  # 30 s < 45 s
    stages = read_records(config.folder.stages_path, StageResult)
    assert [(s.name, s.passed) for s in stages] == [("`pytest -m cuda`", None), (f"timing {NERFACTO_GROUP}", None)]
    assert re.fullmatch(r"skipped: (29|30) s left before the deadline, it needs about 60 s", stages[0].detail)
    text = (tmp_path / "gpu-check.md").read_text()  # rebuilt after each record
    assert "| `pytest -m cuda` | not run | - | skipped: " in text
    assert allowed(config, Deadline(), "tests", "`pytest -m cuda`")
    assert STAGE_MINIMUM_S["timing"] > 30.0


# -------------------------------------------------------------------------------------- the cuda test selection
def test_the_cuda_files_are_exactly_those_with_cuda_tests() -> None:
    uses_marker = re.compile(r"mark\.cuda\b")
    modules = sorted((REPOSITORY / "tests").glob("*.py"))
    assert tuple(f"tests/{p.name}" for p in modules if uses_marker.search(p.read_text())) == CUDA_TEST_FILES
    command = pytest_command(Path("junit.xml"))
    first = command.index("cuda") + 1
    assert command[first : first + len(CUDA_TEST_FILES)] == list(CUDA_TEST_FILES)
    assert "tests" not in command and "tests/" not in command  # never the whole folder


COLLECT_WITH_TORCH_2_11 = """
import sys
import torch._subclasses.fake_tensor as fake_tensor
if hasattr(fake_tensor, "FakeTensorDeviceMismatchError"):
    del fake_tensor.FakeTensorDeviceMismatchError  # as torch 2.11, the GPU machines' torch
import pytest
sys.exit(pytest.main(["--collect-only", "-q", "-m", "cuda", "-p", "no:cacheprovider", *sys.argv[1:]]))
"""


def test_the_cuda_tests_collect_with_torch_2_11s_fake_tensor() -> None:
    """On the GPU machine torch 2.11 has no FakeTensorDeviceMismatchError: the files of the ``cuda`` tests must
    collect without that class, every ``cuda`` test of them."""
    result = subprocess.run(
        [sys.executable, "-c", COLLECT_WITH_TORCH_2_11, *CUDA_TEST_FILES],
        capture_output=True, text=True, env=NO_CUDA, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert [line for line in result.stdout.splitlines() if "::" in line] == CUDA_TESTS


def test_without_cuda_the_cuda_tests_skip_with_the_reason_and_nothing_else_does(tmp_path: Path) -> None:
    junit = tmp_path / "junit.xml"
    unmarked = "tests/test_gpu_check.py::test_the_deadline"
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
    assert cases["test_the_deadline"].find("skipped") is None
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
    passed = cuda_tests_result(0, every, log, 60.0)
    assert (passed.name, passed.passed, passed.detail) == ("`pytest -m cuda`", True, "5 passed")
    failed = junit_counts(_junit(tmp_path, errors=1, failures=1, skipped=0, tests=5))
    assert cuda_tests_result(1, failed, log, 60.0).detail == "3 passed, 1 failures, 1 errors; log logs/cuda-tests.log"
    none = junit_counts(_junit(tmp_path, errors=0, failures=0, skipped=0, tests=0))
    assert cuda_tests_result(5, none, log, 60.0).detail == "no test marked cuda was collected; log logs/cuda-tests.log"
    assert cuda_tests_result(None, None, log, 120.0).detail == (
        "pytest ran past 2 minutes and was stopped; log logs/cuda-tests.log"
    )


def test_records_are_appended_and_a_cut_last_line_is_left_out(tmp_path: Path) -> None:
    path = tmp_path / "stages.jsonl"
    append_record(path, StageResult("machine", True, "H100", 1.5, 10.0))
    append_record(path, StageResult("scene", False, "failed", float("nan"), 11.0))
    assert read_records(path, StageResult) == [
        StageResult("machine", True, "H100", 1.5, 10.0), StageResult("scene", False, "failed", None, 11.0)
    ]  # fmt: skip
    with open(path, "a") as file:
        file.write('{"name": "timing", "pas')  # the check was killed while writing
    assert [s.name for s in read_records(path, StageResult)] == ["machine", "scene"]
    path.write_text('{"a": 1}\nnot json\n{"b": 2}\n')
    with pytest.raises(ValueError, match=r"stages.jsonl: line 2 is not JSON"):
        read_lines(path)
    assert read_records(tmp_path / "missing.jsonl", StageResult) == []


def _step_log(path: Path, method: str, seconds: list[float], refresh_at: tuple[int, ...] = (), end: bool = True):
    log = StepLog(path, method, "NVIDIA H100 80GB HBM3", every=4)
    for step, value in enumerate(seconds):
        log.add(step, value, step in refresh_at)
    if end:
        log.end(RunEnd(len(seconds), 3 * 2**30, stopped_early=False, refresh_seconds=[0.5, 0.7, 0.6]))
    return log


def test_step_logs_are_written_every_few_steps_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / "s2camp.jsonl"
    log = _step_log(path, "s2camp", [9.0, 8.0, 0.05, 0.04, 0.06, 0.05, 0.9], refresh_at=(6,), end=False)
    cut = read_step_log(path)  # a run cut now: the steps of the last flush are there, the others are lost
    assert cut.end is None and [s.step for s in cut.steps] == [0, 1, 2, 3]
    log.end(RunEnd(7, 123, stopped_early=True, refresh_seconds=[0.5]))
    times = read_step_log(path)
    assert (times.method, times.device) == ("s2camp", "NVIDIA H100 80GB HBM3")
    assert times.ordinary_seconds(warmup_steps=2) == [0.05, 0.04, 0.06, 0.05]  # the refresh step kept apart
    assert times.median_seconds(2) == pytest.approx(0.05)
    assert times.median_seconds(6) is None  # fewer than two timed steps
    assert times.refresh_seconds() == [0.9, 0.5]
    assert times.end == RunEnd(7, 123, True, [0.5])
    assert read_step_log(tmp_path / "never.jsonl") is None


def test_timing_rows_give_the_ratio_to_the_baseline_of_the_group(tmp_path: Path) -> None:
    folder = CheckFolder(tmp_path)
    _step_log(folder.steps_log("off"), "s2camp", [1.0] * 3 + [0.080, 0.082, 0.078, 0.080])
    _step_log(folder.steps_log("s2camp"), "s2camp", [1.0] * 3 + [0.084, 0.084, 0.090, 0.080, 0.084], end=False)
    baseline, so3xr3, method = timing_rows(folder, NERFACTO_GROUP, warmup_steps=3)
    assert (baseline.median_s, baseline.ratio, baseline.state) == (pytest.approx(0.080), None, "ended")
    assert method.median_s == pytest.approx(0.084) and method.ratio == pytest.approx(0.084 / 0.080)
    assert method.state == "cut" and method.timed_steps == 5  # the 8 steps written before the cut
    assert (so3xr3.state, so3xr3.ratio) == ("not run", None)
    assert baseline.refresh_s == 0.6 and baseline.peak_memory_bytes == 3 * 2**30
    splat = timing_rows(folder, "splat-off/s2camp-splat-so3xr3/s2camp-splat", 3)
    assert [row.state for row in splat] == ["not run"] * 3


def test_the_report_tables_are_exact(tmp_path: Path) -> None:
    stages = [StageResult("`pytest -m cuda`", True, "5 passed", 61.4), StageResult("timing", None, "skipped")]
    assert report.stage_table(stages) == "\n".join(
        [
            "| check | result | seconds | detail |",
            "|---|---|---|---|",
            "| `pytest -m cuda` | passed | 61 | 5 passed |",
            "| timing | not run | - | skipped |",
        ]
    )
    folder = CheckFolder(tmp_path)
    _step_log(folder.steps_log("off"), "s2camp", [1.0] * 3 + [0.080, 0.082, 0.078, 0.080])
    _step_log(folder.steps_log("s2camp"), "s2camp", [1.0] * 3 + [0.084, 0.084, 0.090, 0.080])
    assert report.timing_table(timing_rows(folder, "off/s2camp", 3)).splitlines()[2:] == [
        "| off/s2camp | off | NVIDIA H100 80GB HBM3 | 4 | 80.00 | - | 600.0 | 3.00 | ended |",
        "| off/s2camp | s2camp | NVIDIA H100 80GB HBM3 | 4 | 84.00 | 1.050 | 600.0 | 3.00 | ended |",
    ]


def _cut_check_folder(root: Path) -> CheckFolder:
    """The folder a check leaves when its machine is lost during the splat group: no report, no end records."""
    folder = CheckFolder(root)
    root.mkdir(parents=True)
    folder.environment_path.write_text("torch 2.11.0+cu130 (CUDA 13.0)\nCUDA devices: cuda:0 H100\n")
    append_record(folder.stages_path, StageResult("machine", True, "H100", 2.0, 1000.0))
    append_record(folder.stages_path, StageResult("scene", True, "40 images 640x480", 60.0, 1060.0))
    append_record(folder.stages_path, StageResult(f"timing {NERFACTO_GROUP}", True, "s2camp 1.050", 70.0, 1130.0))
    for method in ("off", "s2camp-so3xr3"):
        _step_log(folder.steps_log(method), "s2camp", [1.0] * 30 + [0.080] * 10)
    _step_log(folder.steps_log("s2camp"), "s2camp", [1.0] * 30 + [0.084] * 10)
    _step_log(folder.steps_log("splat-off"), "s2camp-splat", [1.0] * 30 + [0.010] * 10, end=False)
    with open(folder.steps_log("splat-off"), "a") as file:
        file.write('{"step": 40, "seco')
    return folder


def test_a_report_is_rebuilt_from_the_folder_of_a_check_that_was_cut(tmp_path: Path) -> None:
    """A check whose machine was lost mid-stage: --report-from writes its report from what it left, on a machine
    without CUDA, with the time per step of every run that had started."""
    from s2camp_bench.gpu_check.cli import run

    folder = _cut_check_folder(tmp_path / "check")
    config = GpuCheckConfig(report_from=folder.root, output_dir=tmp_path / "report")
    assert run(config) is True  # every stage that ended passed
    text = (tmp_path / "report" / "gpu-check.md").read_text()
    assert f"Regenerate with `python -m s2camp_bench.gpu_check --report-from {folder.root.as_posix()}`." in text
    assert "_measured on the machine listed below; report rebuilt " in text
    assert "- torch 2.11.0+cu130 (CUDA 13.0)\n- CUDA devices: cuda:0 H100\n" in text
    assert f"| timing {NERFACTO_GROUP} | passed | 70 | s2camp 1.050 |" in text
    assert f"| {NERFACTO_GROUP} | s2camp | NVIDIA H100 80GB HBM3 | 10 | 84.00 | 1.050 | 600.0 | 3.00 | ended |" in text
    splat = "splat-off/s2camp-splat-so3xr3/s2camp-splat"
    assert f"| {splat} | splat-off | NVIDIA H100 80GB HBM3 | 10 | 10.00 | - | - | - | cut |" in text
    assert f"| {splat} | s2camp-splat | - | 0 | - | - | - | - | not run |" in text
    assert "Whole check: 2.2 minutes" in text


# ----------------------------------------------------------------------------------------------------- regime
def test_the_regime_run_is_one_pass_over_the_lease_scene() -> None:
    assert GpuCheckConfig().regime_steps == 2625  # ceil(35 training images x 640 x 480 / 4096)
    assert GpuCheckConfig(regime_passes=0.5).regime_steps == 1313


def test_the_regime_variants_share_their_evidence_and_differ_only_in_their_options() -> None:
    config = GpuCheckConfig()
    runs = {v: variant_arguments(config, v, Path("scene")) for v in ("s2camp", "tracks-alone", "images-alone")}
    for arguments in runs.values():
        assert arguments[0] == "s2camp"
        assert arguments[-3:] == ["s2camp-data", "--perturbation.enabled", "True"]  # tracks from the images
        assert "--image-tracks" not in arguments and "--reference-model" not in arguments
        assert not [a for a in arguments if "log2-hashmap-size" in a or a == "--machine.device-type"]  # own field
        assert arguments[arguments.index("--max-num-iterations") + 1] == "2625"
    extra = {v: [a for a in args if a not in runs["s2camp"]] for v, args in runs.items()}
    assert extra["tracks-alone"] == ["tracks-alone", "--pipeline.model.camera-optimizer.photometric", "False"]
    assert extra["images-alone"] == ["images-alone", *PHOTOMETRIC_ONLY]


def _errors(path: Path, records: list[ErrorRecord]) -> None:
    for record in records:
        append_record(path, record)


def test_the_regime_section_has_its_figures_even_when_the_run_was_cut(tmp_path: Path) -> None:
    folder = _cut_check_folder(tmp_path / "check")
    _errors(folder.errors_log("tracks-alone"), [ErrorRecord(START, 0, 0.3, 4e-3, 22.0, 7.0),
                                                ErrorRecord(REFINED, 0, 0.08, 2e-3, 1.5, 1.2)])  # fmt: skip
    _errors(folder.errors_log("s2camp"), [ErrorRecord(START, 0, 0.3, 4e-3, 22.0, 7.0),
                                          ErrorRecord(REFINED, 0, 0.3, 4e-3, 22.0, 6.9),
                                          ErrorRecord(REFINED, 250, 0.07, 1.9e-3, 1.2, 1.0)])  # fmt: skip
    with open(folder.errors_log("s2camp"), "a") as file:
        file.write('{"label": "refined", "step": 500, "rot')  # cut while writing
    config = GpuCheckConfig(output_dir=tmp_path / "report")
    text = report.build(config, folder, "python -m s2camp_bench.gpu_check", rebuilt=True)[0].read_text()
    section = text.split("## The regime at real resolution")[1]
    rows = [line for line in section.splitlines() if line.startswith("| ") and "evidence" not in line]
    assert rows == [
        "| start (CamP's perturbation) | - | - | 0.3000 | 4.00e-03 | 22.000 | 7.000 |",
        "| tracks alone (the track prior's anchor, no training) | - | - | 0.0800 | 2.00e-03 | 1.500 | 1.200 |",
        "| s2camp (tracks and images) | 0 | 0.00 | 0.3000 | 4.00e-03 | 22.000 | 6.900 |",
        "| s2camp (tracks and images) | 250 | 0.10 | 0.0700 | 1.90e-03 | 1.200 | 1.000 |",
    ]
    assert "2625 steps of 4096 rays, 1 pass(es) over the training pixels" in section
    assert "## The regime" not in report.build(config, _cut_check_folder(tmp_path / "none"), "c", False)[0].read_text()


# ------------------------------------------------------------------------------------------------------ bundle
def test_the_bundle_carries_what_the_machine_lacks_and_never_this_repositorys_packages_from_the_registry() -> None:
    imported = {"torch": "2.14.1", "numpy": "2.3.0", "nerfstudio": "1.1.5", "PySocks": "1.7.1",
                "typing_extensions": "4.12", "s2camp-ns": "0.1.0", "s2camp_bench": "0.1.0",
                "docstring_parser": "0.18.0"}  # fmt: skip
    assert to_carry(imported) == {"nerfstudio": "1.1.5", "PySocks": "1.7.1", "docstring_parser": "0.18.0"}
    assert normalized("Docstring_Parser") == "docstring-parser" and normalized("torch_fidelity") in SLIM
    assert OWN_PROJECTS == {"s2camp-ns": ".", "s2camp-bench": "benchmarks"}
    assert all((REPOSITORY / folder / "pyproject.toml").is_file() for folder in OWN_PROJECTS.values())


def test_a_slimmed_wheel_loses_the_folders_and_their_record_lines(tmp_path: Path) -> None:
    wheel = tmp_path / "gsplat-1.4.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        archive.writestr("gsplat/__init__.py", "x = 1\n")
        archive.writestr("gsplat/cuda/csrc/third_party/glm/glm/glm.hpp", "// header\n")
        archive.writestr("gsplat/cuda/csrc/third_party/glm/doc/manual.pdf", b"%PDF" + bytes(200_000))
        archive.writestr("gsplat-1.4.0.dist-info/RECORD", "gsplat/__init__.py,,\n"
                         "gsplat/cuda/csrc/third_party/glm/glm/glm.hpp,,\n"
                         "gsplat/cuda/csrc/third_party/glm/doc/manual.pdf,,\n")  # fmt: skip
    assert slim_wheel(wheel, SLIM["gsplat"]) > 0
    with zipfile.ZipFile(wheel) as archive:
        assert archive.namelist() == [
            "gsplat/__init__.py", "gsplat/cuda/csrc/third_party/glm/glm/glm.hpp", "gsplat-1.4.0.dist-info/RECORD"
        ]  # fmt: skip
        assert archive.read("gsplat-1.4.0.dist-info/RECORD").decode().splitlines() == [
            "gsplat/__init__.py,,", "gsplat/cuda/csrc/third_party/glm/glm/glm.hpp,,"
        ]  # fmt: skip


@pytest.mark.slow
def test_the_bundle_dry_run_lists_the_training_paths_packages() -> None:
    """``bundle --dry-run`` imports the training path in a fresh process and lists what the machine lacks, at this
    checkout's versions, and this repository's two packages, fetching nothing."""
    result = subprocess.run(
        [sys.executable, "-m", "s2camp_bench.gpu_check.bundle", "--dry-run"],
        capture_output=True, text=True, env={**NO_CUDA, "PIP_NO_INDEX": "1"}, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    listed = re.findall(r"^  (\S+?)==(\S+)", result.stdout, re.MULTILINE)
    names = {normalized(name) for name, _ in listed}
    assert {"nerfstudio", "gsplat", "pycolmap", "tyro", "viser", "fpsample", "nerfacc", "tensorly"} <= names
    assert not names & {"torch", "numpy", "pytest", "rich", "s2camp-ns", "s2camp-bench"}  # the machine's, or ours
    assert "  s2camp-ns (this checkout's ., built as a wheel)" in result.stdout
    assert "  s2camp-bench (this checkout's benchmarks, built as a wheel)" in result.stdout
    assert dict(listed)["nerfstudio"] == "1.1.5"


# ---------------------------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_a_cpu_check_cut_by_its_deadline_keeps_what_it_measured(tmp_path: Path) -> None:
    """The check end to end on the CPU (``--cpu-smoke``) with a deadline that falls inside the timing group: the
    runs are stopped cleanly with their time shared, each keeps its timed steps, and the report gives their medians.
    About 150 s of CPU time."""
    output = tmp_path / "out"
    began = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", "s2camp_bench.gpu_check", "--cpu-smoke", "--stages", "timing", "--timing-steps", "5000",
         "--deadline", "150", "--output-dir", str(output)],
        capture_output=True, text=True, env={**NO_CUDA, "OMP_NUM_THREADS": "1"}, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    elapsed = time.monotonic() - began
    log = (output / "logs" / f"timing-{NERFACTO_GROUP.replace('/', '-')}.log").read_text(errors="replace")
    assert result.returncode == 0, result.stdout[-3000:] + log[-3000:]
    assert elapsed < 150 + 20, elapsed  # stopped before its deadline (the interpreter's start and exit aside)
    text = (output / "gpu-check.md").read_text()
    for method in ("off", "s2camp-so3xr3", "s2camp"):
        row = next(line for line in text.splitlines() if line.startswith(f"| {NERFACTO_GROUP} | {method} |"))
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        assert cells[2] == "cpu" and int(cells[3]) >= 2 and float(cells[4]) > 0, row
        assert cells[8] == "stopped at the deadline", row
    stages = read_records(output / "stages.jsonl", StageResult)
    names = [("machine", True), ("scene", True), (f"timing {NERFACTO_GROUP}", True)]
    assert [(s.name, s.passed) for s in stages] == names
    times = read_step_log(output / "timing" / "s2camp.jsonl")
    assert times.end.stopped_early and times.end.refresh_seconds and times.end.steps == len(times.steps)
    assert not read_step_log(output / "timing" / "off.jsonl").end.refresh_seconds  # no P without refinement
    environment = (output / "environment.txt").read_text().splitlines()
    assert environment[0].startswith("torch ") and environment[1] == "CUDA devices: none"


@pytest.mark.slow
def test_the_regime_stage_on_the_cpu_logs_errors_as_it_goes(tmp_path: Path) -> None:
    """The regime stage end to end on the CPU (``--cpu-smoke``): tracks alone read after set-up, s2camp's errors
    logged every few steps, images alone after it, the report with all three; then rebuilt by --report-from."""
    output = tmp_path / "check"
    result = subprocess.run(
        [sys.executable, "-m", "s2camp_bench.gpu_check", "--cpu-smoke", "--stages", "regime", "--regime-passes",
         "0.01", "--output-dir", str(output)],
        capture_output=True, text=True, env={**NO_CUDA, "OMP_NUM_THREADS": "1"}, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    folder = CheckFolder(output)
    tracks = [r for r in read_records(folder.errors_log("tracks-alone"), ErrorRecord) if r.label == REFINED]
    s2camp = [r for r in read_records(folder.errors_log("s2camp"), ErrorRecord) if r.label == REFINED]
    start = next(r for r in read_records(folder.errors_log("s2camp"), ErrorRecord) if r.label == START)
    assert [r.step for r in s2camp] == list(range(0, 43, 3))  # 42 steps: ceil(0.01 x 14 x 320 x 240 / 256)
    assert tracks and tracks[0].focal_err != start.focal_err  # the anchor is not the start
    assert s2camp[-1].rot_err != s2camp[0].rot_err  # the cameras moved
    stages = [(s.name, s.passed) for s in read_records(folder.stages_path, StageResult)]
    assert stages == [("machine", True), ("scene", True), ("regime", True)]
    text = (output / "gpu-check.md").read_text()
    assert "| images alone | 42 |" in text and "| tracks alone (the track prior's anchor, no training) |" in text
    again = subprocess.run(
        [sys.executable, "-m", "s2camp_bench.gpu_check", "--cpu-smoke", "--regime-passes", "0.01",
         "--report-from", str(output), "--output-dir", str(tmp_path / "rebuilt")],
        capture_output=True, text=True, env=NO_CUDA, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert again.returncode == 0 and "| images alone | 42 |" in (tmp_path / "rebuilt" / "gpu-check.md").read_text()


@pytest.mark.slow
def test_the_lease_script_runs_the_commands_in_order_and_packs_their_results(tmp_path: Path) -> None:
    """``benchmarks/s2camp_bench/gpu_check/lease.sh`` on the CPU (``SMOKE``: the check's ``--cpu-smoke``;
    ``NO_INSTALL``: this checkout's packages): the check's timing and the regime's tracks alone, then the tests step
    (nothing to run on the CPU), each under its deadline, and after each the report and the archive of records in
    ``$OUT``."""
    work, out = tmp_path / "lease", tmp_path / "out"
    environment = {
        **NO_CUDA, "OMP_NUM_THREADS": "1", "SMOKE": "1", "NO_INSTALL": "1", "PYTHON": sys.executable,
        "PYTHONPATH": f"{REPOSITORY}:{REPOSITORY / 'benchmarks'}", "WORK": str(work), "OUT": str(out),
        "CHECK_S": "300", "TESTS_S": "380", "CHECK_ARGS": "--regime-variants tracks-alone",
    }  # fmt: skip
    result = subprocess.run(
        ["bash", "benchmarks/s2camp_bench/gpu_check/lease.sh"],
        capture_output=True, text=True, env=environment, cwd=REPOSITORY, timeout=HANG_GUARD_S,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    lines = (work / "lease.log").read_text().splitlines()
    assert [line.split(" (")[0] for line in lines if line.startswith(">>> ")] == [
        ">>> gpu-check", ">>> cuda-tests"
    ]  # fmt: skip
    assert all(" exit status 0 at " in line for line in lines if line.startswith("    ")), lines
    assert sorted(path.name for path in out.iterdir()) == ["cuda-tests.md", "gpu-check.md", "lease.tgz"]
    text = (out / "gpu-check.md").read_text()
    assert f"| {NERFACTO_GROUP} | s2camp | cpu |" in text
    assert "| tracks alone (the track prior's anchor, no training) |" in text
    import tarfile

    with tarfile.open(out / "lease.tgz") as archive:
        names = set(archive.getnames())
    kept = {"./gpu-check/stages.jsonl", "./gpu-check/timing/s2camp.jsonl", "./gpu-check/errors/tracks-alone.jsonl"}
    assert kept <= names
    assert not [name for name in names if "/scene/" in name or "/ns-train/" in name]


def test_a_new_check_in_an_old_folder_reports_none_of_the_old_records(tmp_path: Path) -> None:
    """The records of an earlier check in the same folder are removed when a check starts."""
    from s2camp_bench.gpu_check.cli import run

    folder = _cut_check_folder(tmp_path / "check")
    config = GpuCheckConfig(output_dir=folder.root, stages=(), cpu_smoke=True)
    assert run(config) is True
    assert not (folder.root / "timing").exists()
    assert [s.name for s in read_records(folder.stages_path, StageResult)] == ["machine"]
    assert "No timing run left a step log in this folder." in (folder.root / "gpu-check.md").read_text()
