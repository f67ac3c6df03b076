"""The timing stage: each pair ``baseline/method`` trained in one process at the methods' defaults, one after the
other on the same scene, every step timed (``measured_train``, ``step_log``).

Each method's time per step is the median of its ordinary steps after the warm-up; the steps in which P was refreshed
are kept apart, and P's refresh is also timed after training, since the runs are shorter than its default interval.
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .config import STOP_RESERVE_S, GpuCheckConfig, parse_pair
from .measured_train import TrainPlan, TrainSpec
from .processes import Deadline, failure, run_logged
from .records import StageResult
from .step_log import StepTimes, read_step_log
from .train_arguments import timing_arguments

S2CAMP_PREFIX = "s2camp"


@dataclass
class TimingRow:
    """One method of a pair, as its step log says."""

    pair: str
    method: str
    device: str | None = None
    timed_steps: int = 0
    """Ordinary steps after the warm-up."""
    median_s: float | None = None
    ratio: float | None = None
    """Median over the baseline's median (None for the baseline, or without both)."""
    refresh_s: float | None = None
    """Median seconds of P's refreshes (None: none timed)."""
    peak_memory_bytes: int | None = None
    state: str = "not run"
    """"ended", "stopped at the deadline", "cut" (the process died: steps so far kept) or "not run"."""


def pair_plan(config: GpuCheckConfig, pair: str, scene: Path, stop_at: float | None) -> TrainPlan:
    """Both methods of ``pair``, baseline first, each with its step log; P's refresh timed after S2CamP's runs."""
    runs = []
    for method in parse_pair(pair):
        repeats = config.refresh_repeats if method.startswith(S2CAMP_PREFIX) else 0
        runs.append(
            TrainSpec(
                timing_arguments(config, method, scene),
                steps_log=str(config.folder.steps_log(method)),
                log_every=config.log_every,
                refresh_repeats=repeats,
            )
        )
    return TrainPlan(runs, stop_at)


def run_pair(config: GpuCheckConfig, pair: str, scene: Path, deadline: Deadline) -> StageResult:
    """Train ``pair`` in one process until it ends or the deadline nears; the stage's result from its step logs."""
    name = f"timing {pair}"
    folder = config.folder
    began = time.perf_counter()
    for method in parse_pair(pair):
        folder.steps_log(method).unlink(missing_ok=True)
    stop_at = None if deadline.end is None else deadline.end - STOP_RESERVE_S
    plan = pair_plan(config, pair, scene, stop_at).write(folder.logs_dir / f"plan-{pair.replace('/', '-')}.json")
    log_path = folder.logs_dir / f"timing-{pair.replace('/', '-')}.log"
    timeout_s = deadline.limit(config.run_timeout_s)
    command = [sys.executable, "-m", "s2camp_bench.gpu_check.measured_train", str(plan)]
    status = run_logged(command, log_path, timeout_s, progress=lambda: progress(folder, pair))
    remove_checkpoints(folder.ns_train_dir)
    rows = timing_rows(folder, pair, config.warmup_steps)
    seconds = time.perf_counter() - began
    problem = None if status == 0 else failure(f"the {pair} process", status, log_path, timeout_s)
    missing = [row.method for row in rows if row.median_s is None]
    if missing:
        problem = (problem + "; " if problem else "") + f"no time per step of {', '.join(missing)}; log {log_path}"
    return StageResult(name, problem is None, problem or summary(rows), seconds)


def progress(folder, pair: str) -> str:
    """Steps logged so far by each method of ``pair``."""
    parts = []
    for method in parse_pair(pair):
        times = read_step_log(folder.steps_log(method))
        parts.append(f"{method}: {'not started' if times is None else f'{len(times.steps)} steps timed'}")
    return "; ".join(parts)


def summary(rows: list[TimingRow]) -> str:
    """``method / baseline`` of a pair's medians, and how each run ended."""
    baseline, method = rows
    ended = "; ".join(f"{row.method} {row.state} after {row.timed_steps} timed steps" for row in rows)
    return f"{method.method} / {baseline.method} = {method.ratio:.3f} (median ms per step); {ended}"


def timing_rows(folder, pair: str, warmup_steps: int) -> list[TimingRow]:
    """The rows of ``pair`` from its step logs (a run without a log is "not run")."""
    rows = [timing_row(pair, m, read_step_log(folder.steps_log(m)), warmup_steps) for m in parse_pair(pair)]
    baseline, method = rows
    if baseline.median_s and method.median_s is not None:
        method.ratio = method.median_s / baseline.median_s
    return rows


def timing_row(pair: str, method: str, times: StepTimes | None, warmup_steps: int) -> TimingRow:
    if times is None:
        return TimingRow(pair, method)
    refreshes = sorted(times.refresh_seconds())
    end = times.end
    state = "cut" if end is None else ("stopped at the deadline" if end.stopped_early else "ended")
    return TimingRow(
        pair, method, times.device, len(times.ordinary_seconds(warmup_steps)), times.median_seconds(warmup_steps),
        refresh_s=refreshes[len(refreshes) // 2] if refreshes else None,
        peak_memory_bytes=None if end is None else end.peak_memory_bytes, state=state,
    )  # fmt: skip


def remove_checkpoints(ns_train_dir: Path) -> None:
    """ns-train's checkpoints of the check's runs (nerfacto-sized, with Adam's moments): not needed afterwards."""
    for checkpoints in ns_train_dir.glob("*/*/*/nerfstudio_models"):
        shutil.rmtree(checkpoints)
