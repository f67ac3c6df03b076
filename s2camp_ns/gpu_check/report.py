"""The GPU check's results as markdown: one table of the checks, one of the training runs side by side."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from s2camp_ns.report import markdown_table, write_report

MISSING = "-"


@dataclass
class StageResult:
    """One check: ``passed`` is None when it did not run (``detail`` says why)."""

    name: str
    passed: bool | None
    detail: str


@dataclass
class MethodResult:
    """One method's training run and its evaluation; ``error`` is None when both succeeded."""

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


def _number(value: float | None, pattern: str) -> str:
    if value is None or not math.isfinite(value):
        return MISSING
    return pattern.format(value)


def _change(start: float | None, final: float | None, pattern: str) -> str:
    if start is None or final is None:
        return MISSING
    return f"{_number(start, pattern)} → {_number(final, pattern)}"


def stage_table(stages: list[StageResult]) -> str:
    rows = [
        {
            "check": stage.name,
            "result": "not run" if stage.passed is None else ("passed" if stage.passed else "FAILED"),
            "detail": stage.detail,
        }
        for stage in stages
    ]
    return markdown_table(rows, ["check", "result", "detail"])


def method_table(results: list[MethodResult], baseline: str | None) -> str:
    """Per-iteration time (and its ratio to ``baseline``'s), peak CUDA memory, camera errors from the perturbed
    start to the end (after similarity alignment to the true cameras), held-out PSNR after test-time alignment."""
    reference = next((r.sec_per_iter for r in results if r.method == baseline and r.error is None), None)
    rows = []
    for result in results:
        ratio = None
        if reference and result.sec_per_iter is not None:
            ratio = result.sec_per_iter / reference
        memory = None if result.peak_memory_bytes is None else result.peak_memory_bytes / 2**30
        rows.append(
            {
                "method": result.method,
                "time": _number(None if result.sec_per_iter is None else 1e3 * result.sec_per_iter, "{:.1f}"),
                "ratio": _number(ratio, "{:.2f}x"),
                "memory": _number(memory, "{:.2f}"),
                "rot": _change(result.start_rot_deg, result.rot_deg, "{:.3f}"),
                "pos": _change(result.start_pos, result.pos, "{:.2e}"),
                "focal": _change(result.start_focal_px, result.focal_px, "{:.2f}"),
                "psnr": _number(result.psnr, "{:.2f}"),
                "result": "passed" if result.error is None else f"FAILED: {result.error}",
            }
        )
    columns = ["method", "time", "ratio", "memory", "rot", "pos", "focal", "psnr", "result"]
    headers = [
        "method", "ms / iter", f"vs {baseline or 'baseline'}", "peak CUDA memory (GiB)", "rotation err (deg)",
        "position err", "focal err (px)", "held-out PSNR (dB)", "result",
    ]  # fmt: skip
    return markdown_table(rows, columns, headers)


def write(
    path: Path,
    environment_lines: list[str],
    stages: list[StageResult],
    results: list[MethodResult],
    setup: str,
    baseline: str | None,
    minutes: float,
    budget_minutes: float,
) -> Path:
    """Write the report to ``path`` (a ``<name>.md`` file) and return it."""
    timing = f"Whole check: {minutes:.1f} minutes"
    if minutes > budget_minutes:
        timing += f", over its budget of {budget_minutes:g} minutes"
    sections = [
        "\n".join(f"- {line}" for line in environment_lines),
        "## Checks",
        stage_table(stages),
        "## Training side by side",
        setup,
        method_table(results, baseline) if results else "No method was trained.",
        timing + ".",
    ]
    return write_report(path.parent, path.stem, "GPU check", "make gpu-check", sections)


def all_passed(stages: list[StageResult], results: list[MethodResult]) -> bool:
    """True when no check failed and every method trained and evaluated (checks that did not run fail nothing)."""
    return all(stage.passed is not False for stage in stages) and all(result.error is None for result in results)
