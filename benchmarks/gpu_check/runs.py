"""The GPU check's stages that run something: the ``cuda`` tests, the scene, the training runs, the NCCL run.

Every command runs in its own process group with its output in ``<output_dir>/logs``; one that overruns
``run_timeout_minutes`` is killed with its children (data-loader workers, the ranks of a 2-process run) and counted
as failed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import statistics
import subprocess
import sys
import time
import xml.etree.ElementTree as ElementTree
from dataclasses import replace
from pathlib import Path

from s2camp_ns.nerfstudio.train_commands import (
    DATAPARSER_SUBCOMMAND,
    SMALL_MODEL,
    ns_train_executable,
    training_environment,
)
from s2camp_ns.scene.make_scene import make_scene

from .config import GpuCheckConfig
from .report import MethodResult, StageResult

EXPERIMENT = "gpu-check"
NCCL_TIMESTAMP = "s2camp-2-processes"
NCCL_REFRESH_EVERY = 20


def run_logged(command: list[str], log_path: Path, timeout_s: float) -> int | None:
    """Run ``command`` with stdout and stderr in ``log_path``; its exit status, or None when it was killed for
    running past ``timeout_s``."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w", encoding="utf8") as output:
        process = subprocess.Popen(
            command, stdout=output, stderr=subprocess.STDOUT, env=training_environment(), start_new_session=True
        )
        try:
            return process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _kill_group(process)
            return None
        except BaseException:  # Ctrl-C does not reach the command's own session: stop it here, then stop
            _kill_group(process)
            raise


def _kill_group(process: subprocess.Popen) -> None:
    """Kill the command and everything it started (data-loader workers, the ranks of a multi-process run)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    process.wait()


def log_tail(log_path: Path, lines: int = 20) -> str:
    return "\n".join(log_path.read_text(encoding="utf8", errors="replace").splitlines()[-lines:])


def _failure(what: str, status: int | None, log_path: Path, timeout_s: float) -> str:
    if status is None:
        return f"{what} ran past {timeout_s / 60:g} minutes and was stopped; log {log_path}"
    return f"{what} exited with status {status}; log {log_path}"


# ------------------------------------------------------------------------------------------------ cuda tests
def pytest_command(config: GpuCheckConfig, junit_path: Path) -> list[str]:
    return [
        sys.executable, "-m", "pytest", "-m", "cuda", str(config.tests_dir), "-q", "-rA", "-p", "no:cacheprovider",
        f"--junitxml={junit_path}",
    ]  # fmt: skip


def junit_counts(junit_path: Path) -> dict[str, int]:
    """Totals of a pytest JUnit XML file: tests, failures, errors, skipped, and passed (the rest)."""
    root = ElementTree.parse(junit_path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
    keys = ("tests", "failures", "errors", "skipped")
    counts = {key: sum(int(suite.get(key, 0)) for suite in suites) for key in keys}
    counts["passed"] = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    return counts


def cuda_tests_result(
    status: int | None, counts: dict[str, int] | None, log_path: Path, timeout_s: float
) -> StageResult:
    """Passed only if pytest succeeded, ran at least one test and skipped none (on CUDA nothing may skip)."""
    name = "`pytest -m cuda`"
    if status is None or counts is None:
        return StageResult(name, False, _failure("pytest", status, log_path, timeout_s))
    summary = ", ".join(f"{counts[key]} {key}" for key in ("passed", "failures", "errors", "skipped") if counts[key])
    if counts["tests"] == 0:
        return StageResult(name, False, f"no test marked cuda was collected; log {log_path}")
    passed = status == 0 and counts["passed"] == counts["tests"]
    return StageResult(name, passed, summary + ("" if passed else f"; log {log_path}"))


def run_cuda_tests(config: GpuCheckConfig) -> StageResult:
    junit_path = config.junit_path
    junit_path.unlink(missing_ok=True)
    log_path = config.logs_dir / "cuda-tests.log"
    timeout_s = 60 * config.run_timeout_minutes
    status = run_logged(pytest_command(config, junit_path), log_path, timeout_s)
    counts = junit_counts(junit_path) if junit_path.is_file() else None
    return cuda_tests_result(status, counts, log_path, timeout_s)


# ------------------------------------------------------------------------------------------------------ scene
def scene_is_current(config: GpuCheckConfig) -> bool:
    """Whether ``scene_dir`` holds a finished scene generated with exactly ``config.scene`` (then it is reused)."""
    info_path = config.scene_dir / "scene_info.json"
    if not info_path.is_file():
        return False
    wanted = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(scene_config(config)).items()}
    stored = json.loads(info_path.read_text())["config"]
    return json.loads(json.dumps(wanted)) == stored


def scene_config(config: GpuCheckConfig):
    return replace(config.scene, output_dir=config.scene_dir)


def generate_scene(config: GpuCheckConfig) -> StageResult:
    """Generate ``config.scene`` into ``config.scene_dir``, or reuse the one there if it has the same settings."""
    s = config.scene
    name = "scene"
    what = f"{s.num_cameras} images {s.width}x{s.height}"
    if scene_is_current(config):
        return StageResult(name, True, f"{what}, reused from {config.scene_dir}")
    began = time.perf_counter()
    try:
        make_scene(scene_config(config))
    except (ValueError, RuntimeError) as error:
        return StageResult(name, False, f"s2camp-make-scene failed: {error}")
    return StageResult(name, True, f"{what}, generated in {time.perf_counter() - began:.0f} s")


# --------------------------------------------------------------------------------------------------- training
def _run_arguments(config: GpuCheckConfig, scene: Path, timestamp: str, iterations: int) -> list[str]:
    """What every run of the check shares: its output place, length (one checkpoint, at the end), no evaluation
    during training, tensorboard instead of the viewer."""
    return [
        "--data", str(scene),
        "--output-dir", str(config.runs_dir),
        "--experiment-name", EXPERIMENT,
        "--timestamp", timestamp,
        "--max-num-iterations", str(iterations),
        "--steps-per-save", str(iterations),
        "--steps-per-eval-batch", "0",
        "--steps-per-eval-image", "0",
        "--steps-per-eval-all-images", "0",
        "--vis", "tensorboard",
    ]  # fmt: skip


def train_arguments(config: GpuCheckConfig, method: str, scene: Path) -> list[str]:
    """``ns-train`` arguments of one method: its defaults, the run length and batch, no evaluation during training,
    tensorboard instead of the viewer, s2camp's refresh interval, CamP's perturbation of the training cameras."""
    arguments = [
        method,
        *_run_arguments(config, scene, method, config.iterations),
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.rays_per_batch),
    ]  # fmt: skip
    if method == "s2camp":
        arguments += ["--pipeline.model.camera-optimizer.refresh-every", str(config.refresh_every)]
    if config.cpu_smoke:
        arguments += ["--machine.device-type", "cpu", *SMALL_MODEL]
    return [*arguments, DATAPARSER_SUBCOMMAND, "--perturbation.enabled", "True"]


def measured_train_command(config: GpuCheckConfig, method: str, scene: Path, result_path: Path) -> list[str]:
    alignment = json.dumps(dataclasses.asdict(config.alignment))
    return [
        sys.executable, "-m", "s2camp_ns.benchmarks.gpu_check.measured_train", "--result", str(result_path),
        "--alignment", alignment, "--", *train_arguments(config, method, scene),
    ]  # fmt: skip


def seconds_per_iteration(step_seconds: list[float], warmup_steps: int) -> float | None:
    """Mean seconds of the steps after ``warmup_steps`` (refreshes of P included); None without two of them.

    ``step_seconds[i]`` is the time from the end of step i to the end of step i + 1, so the first ``warmup_steps``
    entries are the warm-up."""
    timed = step_seconds[warmup_steps:]
    return statistics.fmean(timed) if len(timed) >= 2 else None


def method_result(method: str, measured: dict | None, warmup_steps: int, failure: str | None) -> MethodResult:
    """A table row from measured_train's JSON (possibly without evaluation) and the failure, if any."""
    result = MethodResult(method, error=failure)
    if measured is None:
        if result.error is None:
            result.error = "no measurements written"
        return result
    result.sec_per_iter = seconds_per_iteration(measured["step_seconds"], warmup_steps)
    result.peak_memory_bytes = measured.get("peak_memory_bytes")
    evaluation = measured.get("evaluation")
    if evaluation is None:
        result.error = result.error or "no evaluation written"
        return result
    result.start_rot_deg, result.rot_deg = evaluation["start_rot_err"], evaluation["rot_err"]
    result.start_pos, result.pos = evaluation["start_pos_err"], evaluation["pos_err"]
    result.start_focal_px, result.focal_px = evaluation["start_focal_err"], evaluation["focal_err"]
    result.psnr = evaluation["psnr"]
    return result


def train_method(config: GpuCheckConfig, method: str, scene: Path) -> tuple[MethodResult, dict | None]:
    result_path = config.measurements_path(method)
    result_path.unlink(missing_ok=True)
    log_path = config.logs_dir / f"train-{method}.log"
    timeout_s = 60 * config.run_timeout_minutes
    status = run_logged(measured_train_command(config, method, scene, result_path), log_path, timeout_s)
    measured = json.loads(result_path.read_text()) if result_path.is_file() else None
    failure = None if status == 0 else _failure(f"ns-train {method}", status, log_path, timeout_s)
    return method_result(method, measured, config.warmup_steps, failure), measured


# --------------------------------------------------------------------------------------------------- NCCL
def nccl_arguments(config: GpuCheckConfig, scene: Path) -> list[str]:
    """``ns-train s2camp`` on two GPUs with nerfstudio's own launcher (one process per GPU, NCCL)."""
    return [
        ns_train_executable(), "s2camp",
        *_run_arguments(config, scene, NCCL_TIMESTAMP, config.nccl_iterations),
        "--machine.num-devices", "2",
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.rays_per_batch),
        "--pipeline.model.camera-optimizer.refresh-every", str(NCCL_REFRESH_EVERY),
        DATAPARSER_SUBCOMMAND, "--perturbation.enabled", "True",
    ]  # fmt: skip


def nccl_checkpoint(config: GpuCheckConfig) -> Path:
    run = config.runs_dir / EXPERIMENT / "s2camp" / NCCL_TIMESTAMP
    return run / "nerfstudio_models" / f"step-{config.nccl_iterations - 1:09d}.ckpt"


def check_nccl_checkpoint(path: Path) -> str | None:
    """None if the checkpoint's camera latents are finite and moved away from zero, else what is wrong."""
    import torch

    if not path.is_file():
        return f"no final checkpoint {path}"
    state = torch.load(path, map_location="cpu", weights_only=False)["pipeline"]
    latents = {key: value for key, value in state.items() if key.endswith("camera_optimizer.whitened_delta")}
    if len(latents) != 1:
        return f"{path} holds {len(latents)} camera latents (whitened_delta), expected 1"
    latent = next(iter(latents.values()))
    if not torch.isfinite(latent).all():
        return f"the camera latent in {path} is not finite"
    if not latent.abs().max() > 0:
        return f"the camera latent in {path} is still zero: the cameras were not refined"
    return None


def run_nccl(config: GpuCheckConfig, scene: Path, device_count: int) -> StageResult:
    name = "2-process NCCL training (s2camp)"
    if device_count < 2:
        return StageResult(name, None, f"needs 2 CUDA devices, this machine has {device_count}")
    log_path = config.logs_dir / "nccl.log"
    timeout_s = 60 * config.run_timeout_minutes
    status = run_logged(nccl_arguments(config, scene), log_path, timeout_s)
    if status != 0:
        failure = _failure("ns-train s2camp --machine.num-devices 2", status, log_path, timeout_s)
        return StageResult(name, False, failure)
    problem = check_nccl_checkpoint(nccl_checkpoint(config))
    if problem is not None:
        return StageResult(name, False, problem)
    return StageResult(name, True, f"{config.nccl_iterations} steps on 2 GPUs, P refreshed every {NCCL_REFRESH_EVERY}")
