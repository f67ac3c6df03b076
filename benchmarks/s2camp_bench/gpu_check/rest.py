"""The check's later stages, run while time remains: the methods trained and evaluated side by side (``rest``) and
two processes over NCCL (``nccl``).

``rest``: nerfacto, s2camp-so3xr3, s2camp and s2camp-camp, one process each, ``rest_iterations`` steps of
``rays_per_batch`` rays from the perturbed start (s2camp's P refreshed every ``refresh_every``), each evaluated in
its training process (``measured_train``): mean time per step, peak memory, camera errors, held-out PSNR after
test-time alignment. ``nccl``: ``ns-train s2camp --machine.num-devices 2``, passed when it exits cleanly with a
finite, non-zero camera latent in its final checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from s2camp_bench.train_commands import ns_train_executable

from .config import STOP_RESERVE_S, GpuCheckConfig
from .measured_train import TrainPlan, TrainSpec
from .processes import Deadline, failure, run_logged
from .records import StageResult
from .timing import remove_checkpoints
from .train_arguments import NCCL_REFRESH_EVERY, nccl_arguments, rest_arguments

NCCL_STAGE = "2-process NCCL training (s2camp)"


@dataclass
class MethodResult:
    """One method's evaluated run; ``error`` is None when it trained and evaluated."""

    method: str
    error: str | None = None
    sec_per_iter: float | None = None
    peak_memory_bytes: int | None = None
    start_rot_deg: float | None = None
    rot_deg: float | None = None
    start_pos: float | None = None
    pos: float | None = None
    start_focal_px: float | None = None
    focal_px: float | None = None
    psnr: float | None = None


def seconds_per_iteration(step_seconds: list[float], warmup_steps: int) -> float | None:
    """Mean seconds of the steps after ``warmup_steps`` (refreshes of P included); None without two of them."""
    timed = step_seconds[warmup_steps:]
    return statistics.fmean(timed) if len(timed) >= 2 else None


def method_result(method: str, measured: dict | None, warmup_steps: int, problem: str | None) -> MethodResult:
    """A row from ``measured_train``'s result JSON (possibly without its evaluation) and the failure, if any."""
    result = MethodResult(method, error=problem)
    if measured is None:
        result.error = result.error or "no measurements written"
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


def train_and_evaluate(config: GpuCheckConfig, method: str, scene: Path, deadline: Deadline) -> StageResult:
    """One ``rest`` run in a process of its own; the stage's result names its measurements."""
    folder = config.folder
    result_path = folder.measurements_path(method)
    result_path.unlink(missing_ok=True)
    stop_at = None if deadline.end is None else deadline.end - STOP_RESERVE_S
    spec = TrainSpec(
        rest_arguments(config, method, scene), result=str(result_path), alignment=dataclasses.asdict(config.alignment)
    )
    plan = TrainPlan([spec], stop_at).write(folder.logs_dir / f"plan-rest-{method}.json")
    log_path = folder.logs_dir / f"train-{method}.log"
    timeout_s = deadline.limit(config.run_timeout_s)
    began = time.perf_counter()
    command = [sys.executable, "-m", "s2camp_bench.gpu_check.measured_train", str(plan)]
    status = run_logged(command, log_path, timeout_s, progress=lambda: f"{method}: {last_line(log_path)}")
    remove_checkpoints(folder.ns_train_dir)
    problem = None if status == 0 else failure(f"ns-train {method}", status, log_path, timeout_s)
    row = method_result(method, read_json(result_path), config.warmup_steps, problem)
    detail = row.error or f"trained and evaluated; {result_path}"
    return StageResult(f"rest: {method}", row.error is None, detail, time.perf_counter() - began)


def read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def last_line(log_path: Path) -> str:
    """The last progress line of a training log (``measured_train`` prints one every 100 steps)."""
    text = log_path.read_text(encoding="utf8", errors="replace") if log_path.is_file() else ""
    steps = [line for line in text.splitlines() if line.startswith(("step ", ">>> ", "stopped "))]
    return steps[-1][:80] if steps else "starting"


def nccl_checkpoint(config: GpuCheckConfig) -> Path:
    run = config.folder.ns_train_dir / "nccl" / "s2camp" / "s2camp"
    return run / "nerfstudio_models" / f"step-{config.nccl_iterations - 1:09d}.ckpt"


def check_nccl_checkpoint(path: Path) -> str | None:
    """None if the checkpoint's camera latents are finite and moved away from zero, else what is wrong."""
    import torch

    if not path.is_file():
        return f"no final checkpoint {path}"
    state = torch.load(path, map_location="cpu", weights_only=False)["pipeline"]
    latents = {key: value for key, value in state.items() if key.endswith("camera_optimizer.refiner.whitened_delta")}
    if len(latents) != 1:
        return f"{path} holds {len(latents)} camera latents (whitened_delta), expected 1"
    latent = next(iter(latents.values()))
    if not torch.isfinite(latent).all():
        return f"the camera latent in {path} is not finite"
    if not latent.abs().max() > 0:
        return f"the camera latent in {path} is still zero: the cameras were not refined"
    return None


def run_nccl(config: GpuCheckConfig, scene: Path, device_count: int, deadline: Deadline) -> StageResult:
    if device_count < 2:
        return StageResult(NCCL_STAGE, None, f"needs 2 CUDA devices, this machine has {device_count}")
    log_path = config.folder.logs_dir / "nccl.log"
    timeout_s = deadline.limit(config.run_timeout_s)
    began = time.perf_counter()
    status = run_logged(nccl_arguments(config, scene, ns_train_executable()), log_path, timeout_s)
    seconds = time.perf_counter() - began
    if status != 0:
        what = "ns-train s2camp --machine.num-devices 2"
        return StageResult(NCCL_STAGE, False, failure(what, status, log_path, timeout_s), seconds)
    problem = check_nccl_checkpoint(nccl_checkpoint(config))
    if problem is not None:
        return StageResult(NCCL_STAGE, False, problem, seconds)
    detail = f"{config.nccl_iterations} steps on 2 GPUs, P refreshed every {NCCL_REFRESH_EVERY}"
    return StageResult(NCCL_STAGE, True, detail, seconds)
