"""The GPU check's report, built from what its folder holds: rebuilt after every stage of a running check, and by
``--report-from`` for the folder of a check that was cut. Sections: the machine (``environment.txt``), the stages
(``stages.jsonl``), the time per step of each group at the methods' defaults (``timing/<method>.jsonl``), the regime
(``errors/<variant>.jsonl``)."""

from __future__ import annotations

import math
import time
from pathlib import Path

from s2camp_bench.report import markdown_table, write_report

from .config import CheckFolder, GpuCheckConfig
from .records import StageResult, read_records
from .regime import regime_section
from .timing import TimingRow, timing_rows

MISSING = "-"
COMMAND = "python -m s2camp_bench.gpu_check"


def _number(value: float | None, pattern: str, scale: float = 1.0) -> str:
    return MISSING if value is None or not math.isfinite(value) else pattern.format(scale * value)


def stage_table(stages: list[StageResult]) -> str:
    rows = [{"check": s.name, "result": s.outcome, "seconds": _number(s.seconds, "{:.0f}"), "detail": s.detail}
            for s in stages]  # fmt: skip
    return markdown_table(rows, ["check", "result", "seconds", "detail"])


def timing_table(rows: list[TimingRow]) -> str:
    """Per method of each group: median ms per ordinary step after the warm-up, its ratio to the group's baseline,
    P's refresh, peak CUDA memory and how the run ended."""
    cells = [
        {"group": row.group, "method": row.method, "device": row.device or MISSING, "steps": row.timed_steps,
         "ms": _number(row.median_s, "{:.2f}", 1e3), "ratio": _number(row.ratio, "{:.3f}"),
         "refresh": _number(row.refresh_s, "{:.1f}", 1e3), "memory": _number(row.peak_memory_bytes, "{:.2f}", 2**-30),
         "state": row.state}
        for row in rows
    ]  # fmt: skip
    headers = [
        "group", "method", "device", "timed steps", "ms / step (median)", "vs baseline", "P refresh (ms)",
        "peak CUDA memory (GiB)", "run",
    ]  # fmt: skip
    columns = ["group", "method", "device", "steps", "ms", "ratio", "refresh", "memory", "state"]
    return markdown_table(cells, columns, headers)


def timing_text(config: GpuCheckConfig) -> str:
    s, smoke = config.scene, "**CPU smoke run (`--cpu-smoke`): not a GPU check; the numbers mean nothing.** "
    return (smoke if config.cpu_smoke else "") + (
        f"Each group trains in one process, the baseline (camera refinement off) first, {config.timing_steps} steps "
        "each at the methods' defaults (ray batch, mixed precision, P's refresh interval) on the scene "
        f"({s.num_cameras} images {s.width}x{s.height}), its training cameras perturbed by CamP's protocol. ms / step: "
        "median of the "
        f"steps after the first {config.warmup_steps} without a refresh of P, each stamped after "
        "`torch.cuda.synchronize()`. P refresh: median of the refreshes timed apart after training (s2camp refreshes "
        "every 1000 steps). Peak memory: `torch.cuda.max_memory_allocated()`. run: ended, stopped at the deadline, cut "
        "(the process was stopped: its steps so far are kept) or not run."
    )


def whole_time(stages: list[StageResult]) -> str:
    timed = [s for s in stages if s.seconds is not None]
    if not timed:
        return "Whole check: its wall time was not recorded."
    first = min(timed, key=lambda s: s.finished)
    minutes = (max(s.finished for s in stages) - first.finished + first.seconds) / 60
    return f"Whole check: {minutes:.1f} minutes, from the machine's stage to the last stage recorded."


def build(config: GpuCheckConfig, folder: CheckFolder, command: str, rebuilt: bool) -> tuple[Path, bool]:
    """Write the report of what ``folder`` holds to ``<output_dir>/gpu-check.md``; (its path, whether every stage
    that ran passed)."""
    environment = folder.environment_path
    lines = environment.read_text(encoding="utf8").splitlines() if environment.is_file() else []
    lines = lines or ["the machine is not recorded in this folder (no environment.txt)"]
    if rebuilt:
        lines.append(f"Rebuilt from `{folder.root.as_posix()}` (`--report-from`).")
    stages = read_records(folder.stages_path, StageResult)
    timing = [row for group in config.groups for row in timing_rows(folder, group, config.warmup_steps)]
    sections = ["\n".join(f"- {line}" for line in lines), "## Stages", stage_table(stages), whole_time(stages)]
    sections.append("## Time per step at the methods' defaults")
    if any(row.state != "not run" for row in timing):
        sections += [timing_text(config), timing_table(timing)]
    else:
        sections.append("No timing run left a step log in this folder.")
    sections += regime_section(config, folder)
    measured_on = None
    if rebuilt:  # not this machine: write_report's environment line would name the one it is rebuilt on
        measured_on = f"measured on the machine listed below; report rebuilt {time.strftime('%Y-%m-%d')}"
    path = write_report(config.output_dir, "gpu-check", "GPU check", command, sections, measured_on)
    return path, all(s.passed is not False for s in stages)
