"""The timing stage: each group ``baseline/method/...`` trained in one process at the methods' defaults, one after
the other on the perturbed scene, every step timed (``measured_train``, ``run_logs``): each method's median time per
ordinary step after the warm-up and its ratio to the baseline's (refinement off) from the same process on the same
card; P's refresh timed apart after training (the runs are shorter than its default interval).
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from s2camp_bench.train_commands import DATAPARSER_SUBCOMMAND, SMALL_MODEL, ns_train_base_arguments

from .config import METHODS, STOP_RESERVE_S, CheckFolder, GpuCheckConfig, parse_group
from .measured_train import TrainPlan, TrainSpec
from .processes import Deadline, failure, run_logged
from .records import StageResult
from .run_logs import read_step_log

PERTURBED = [DATAPARSER_SUBCOMMAND, "--perturbation.enabled", "True"]
"""The data parser with CamP's perturbation of the training cameras (its default seed and sigmas): the tracks of the
perturbed start are made from the images (the parser's ``image_tracks`` "auto")."""


def run_arguments(scene: Path, output_dir: Path, experiment: str, timestamp: str, iterations: int) -> list[str]:
    """What every run shares (``train_commands.ns_train_base_arguments`` without the executable: data and output
    places, one checkpoint at the end, no evaluation during training) and tensorboard instead of the viewer."""
    base = ns_train_base_arguments("-", scene, output_dir, experiment, timestamp, iterations, iterations)
    return [*base[2:], "--vis", "tensorboard"]


def cpu_arguments(cpu_smoke: bool) -> list[str]:
    """``--cpu-smoke``: the CPU and the small nerfacto field (``train_commands.SMALL_MODEL``); nothing otherwise."""
    return ["--machine.device-type", "cpu", *SMALL_MODEL] if cpu_smoke else []


def timing_arguments(config: GpuCheckConfig, method: str, scene: Path) -> list[str]:
    """A timing run: the method's defaults (its ray batch and P's refresh interval included) for ``timing_steps``,
    on the perturbed scene."""
    ns_method, options = METHODS[method]
    output = config.output_dir / "ns-train"
    return [
        ns_method, *run_arguments(scene, output, "timing", method, config.timing_steps), *options,
        *cpu_arguments(config.cpu_smoke), *PERTURBED,
    ]  # fmt: skip


def group_plan(config: GpuCheckConfig, group: str, scene: Path, stop_at: float | None) -> TrainPlan:
    """Every method of ``group``, baseline first, each with its step log; P's refresh timed after S2CamP's runs;
    the time left shared among them."""
    runs = [
        TrainSpec(
            timing_arguments(config, method, scene), steps_log=str(config.folder.steps_log(method)),
            log_every=config.log_every, refresh_repeats=config.refresh_repeats,
        )
        for method in parse_group(group)
    ]  # fmt: skip
    return TrainPlan(runs, stop_at, share=True)


@dataclass
class TimingRow:
    """One method of a group, as its step log says: its ordinary steps after the warm-up and their median, the ratio
    of that median to the baseline's, P's median refresh, peak memory, and whether the run "ended", was "stopped at
    the deadline", "cut" (the process died: its steps so far kept) or "not run"."""

    group: str
    method: str
    device: str | None = None
    timed_steps: int = 0
    median_s: float | None = None
    ratio: float | None = None
    refresh_s: float | None = None
    peak_memory_bytes: int | None = None
    state: str = "not run"


def timing_rows(folder: CheckFolder, group: str, warmup_steps: int) -> list[TimingRow]:
    """The rows of ``group`` from its step logs (a run without a log is "not run")."""
    rows = []
    for method in parse_group(group):
        times = read_step_log(folder.steps_log(method))
        if times is None:
            rows.append(TimingRow(group, method))
            continue
        refreshes = sorted(times.refresh_seconds())
        end = times.end
        state = "cut" if end is None else ("stopped at the deadline" if end.stopped_early else "ended")
        rows.append(TimingRow(
            group, method, times.device, len(times.ordinary_seconds(warmup_steps)), times.median_seconds(warmup_steps),
            refresh_s=refreshes[len(refreshes) // 2] if refreshes else None,
            peak_memory_bytes=None if end is None else end.peak_memory_bytes, state=state,
        ))  # fmt: skip
    baseline = rows[0].median_s
    for row in rows[1:]:
        row.ratio = row.median_s / baseline if baseline and row.median_s is not None else None
    return rows


def run_group(config: GpuCheckConfig, group: str, scene: Path, deadline: Deadline) -> StageResult:
    """Train ``group`` in one process until it ends or the deadline nears; the stage's result from its step logs."""
    folder, began, name = config.folder, time.perf_counter(), f"timing {group}"
    for method in parse_group(group):
        folder.steps_log(method).unlink(missing_ok=True)
    label = group.replace("/", "-")
    plan = group_plan(config, group, scene, deadline.stop_at(STOP_RESERVE_S))
    plan_path = plan.write(folder.root / "logs" / f"plan-{label}.json")
    log_path = folder.root / "logs" / f"timing-{label}.log"
    timeout_s = deadline.limit(config.run_timeout_s)
    command = [sys.executable, "-m", "s2camp_bench.gpu_check.measured_train", str(plan_path)]
    status = run_logged(command, log_path, timeout_s)
    for checkpoints in (folder.root / "ns-train").glob("*/*/*/nerfstudio_models"):
        shutil.rmtree(checkpoints)  # nerfacto-sized, with Adam's moments: not needed afterwards
    rows = timing_rows(folder, group, config.warmup_steps)
    problem = None if status == 0 else failure(f"the {group} process", status, log_path, timeout_s)
    missing = [row.method for row in rows if row.median_s is None]
    if missing:
        problem = (problem + "; " if problem else "") + f"no time per step of {', '.join(missing)}; log {log_path}"
    ratios = ", ".join(f"{row.method} {row.ratio:.3f}" for row in rows[1:] if row.ratio is not None)
    ended = "; ".join(f"{row.method} {row.state} after {row.timed_steps} timed steps" for row in rows)
    detail = problem or f"median ms per step over {rows[0].method}'s: {ratios}; {ended}"
    return StageResult(name, problem is None, detail, time.perf_counter() - began)
