"""The GPU check's report, built from what its folder holds: rebuilt after every stage of a running check, and by
``--report-from`` for the folder of a check that was cut.

Sections: the machine (``environment.txt``), the stages (``stages.jsonl``), the time per step of the pairs at their
defaults (``timing/<method>.jsonl``), the methods evaluated side by side (``runs/<method>.json``).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from s2camp_bench.report import markdown_table, write_report

from .config import DOCS_REPORT, REST_BASELINE, CheckFolder, GpuCheckConfig
from .records import StageResult, read_records
from .rest import MethodResult, method_result
from .tests_stage import cuda_tests_result, junit_counts
from .timing import TimingRow, timing_rows

MISSING = "-"
TITLE = "GPU check"
COMMAND = "python -m s2camp_bench.gpu_check"


def _number(value: float | None, pattern: str) -> str:
    if value is None or not math.isfinite(value):
        return MISSING
    return pattern.format(value)


def _change(start: float | None, final: float | None, pattern: str) -> str:
    if start is None or final is None:
        return MISSING
    return f"{_number(start, pattern)} → {_number(final, pattern)}"


def _gib(value: int | None) -> str:
    return _number(None if value is None else value / 2**30, "{:.2f}")


def stage_table(stages: list[StageResult]) -> str:
    rows = [
        {"check": s.name, "result": s.outcome, "seconds": _number(s.seconds, "{:.0f}"), "detail": s.detail}
        for s in stages
    ]
    return markdown_table(rows, ["check", "result", "seconds", "detail"])


def timing_table(rows: list[TimingRow]) -> str:
    """Per method of each pair: median ms per ordinary step after the warm-up, its ratio to the pair's baseline,
    P's refresh, peak CUDA memory and how the run ended."""
    cells = [
        {
            "pair": row.pair,
            "method": row.method,
            "device": row.device or MISSING,
            "steps": row.timed_steps,
            "ms": _number(None if row.median_s is None else 1e3 * row.median_s, "{:.2f}"),
            "ratio": _number(row.ratio, "{:.3f}"),
            "refresh": _number(None if row.refresh_s is None else 1e3 * row.refresh_s, "{:.1f}"),
            "memory": _gib(row.peak_memory_bytes),
            "state": row.state,
        }
        for row in rows
    ]
    columns = ["pair", "method", "device", "steps", "ms", "ratio", "refresh", "memory", "state"]
    headers = [
        "pair", "method", "device", "timed steps", "ms / step (median)", "vs baseline", "P refresh (ms)",
        "peak CUDA memory (GiB)", "run",
    ]  # fmt: skip
    return markdown_table(cells, columns, headers)


def method_table(results: list[MethodResult], baseline: str | None) -> str:
    """Mean time per step (and its ratio to ``baseline``'s), peak CUDA memory, camera errors from the perturbed
    start to the end (after similarity alignment to the true cameras), held-out PSNR after test-time alignment."""
    reference = next((r.sec_per_iter for r in results if r.method == baseline and r.error is None), None)
    rows = []
    for result in results:
        ratio = None
        if reference and result.sec_per_iter is not None:
            ratio = result.sec_per_iter / reference
        rows.append(
            {
                "method": result.method,
                "time": _number(None if result.sec_per_iter is None else 1e3 * result.sec_per_iter, "{:.1f}"),
                "ratio": _number(ratio, "{:.2f}x"),
                "memory": _gib(result.peak_memory_bytes),
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


def timing_text(config: GpuCheckConfig) -> str:
    smoke = (
        "**CPU smoke run of the script itself (`--cpu-smoke`): tiny scene, small nerfacto, a few steps on the CPU. "
        "Not a GPU check; the numbers mean nothing.** "
        if config.cpu_smoke
        else ""
    )
    s = config.scene
    return smoke + (
        f"Each pair trains in one process, the baseline first, {config.timing_steps} steps each with the methods' "
        f"default options (ray batch, mixed precision, P's refresh interval) on a generated scene of {s.num_cameras} "
        f"images {s.width}x{s.height} (every 8th held out) whose training cameras are perturbed by CamP's protocol "
        "(`s2camp-data --perturbation.enabled True`, tracks made from the images). ms / step: median of the steps "
        f"after the first {config.warmup_steps} without a refresh of P, each stamped after "
        "`torch.cuda.synchronize()`. P refresh: median seconds of the refreshes timed apart after training (and of "
        "any step that held one); s2camp refreshes P every 1000 steps by default, so its share of a step is that "
        "time / 1000. Peak memory: `torch.cuda.max_memory_allocated()` of the run. run: ended, stopped at the "
        "deadline (its steps so far timed), cut (the process was stopped: its steps so far are kept) or not run."
    )


def rest_text(config: GpuCheckConfig) -> str:
    a = config.alignment
    return (
        f"Each method trains {config.rest_iterations} steps of {config.rays_per_batch} rays from scratch with its "
        "default options on the check's scene, its training cameras perturbed by CamP's protocol; s2camp refreshes P "
        f"every {config.refresh_every} steps. Time "
        f"per iteration: mean over the steps after the first {config.warmup_steps}. Camera errors: perturbed start "
        "→ end, mean over the training cameras after a similarity alignment to the true ones (rotation in degrees, "
        f"position in scene units, focal in px). PSNR: held-out views after {a.steps} test-time alignment steps of "
        f"{a.rays} rays (`s2camp-eval`'s protocol). nerfacto is nerfstudio's stock method, fed the same data by "
        "`s2camp-data`."
    )


def read_stages(folder: CheckFolder) -> list[StageResult]:
    """The stages a check recorded; a folder from before stage records holds only the tests' JUnit file."""
    stages = read_records(folder.stages_path, StageResult)
    if not folder.stages_path.is_file() and folder.junit_path.is_file():
        stages.append(cuda_tests_result(0, junit_counts(folder.junit_path), folder.junit_path.with_suffix(".log"), 0))
    return stages


def rest_results(folder: CheckFolder, config: GpuCheckConfig) -> list[MethodResult]:
    """Rows of the evaluated runs whose measurements the folder holds (a run without evaluation: a failed row)."""
    rows = []
    for method in config.rest_methods:
        path = folder.measurements_path(method)
        if path.is_file():
            rows.append(method_result(method, json.loads(path.read_text()), config.warmup_steps, None))
    return rows


def whole_time(stages: list[StageResult]) -> str:
    timed = [s for s in stages if s.seconds is not None]
    if not timed:
        return "Whole check: its wall time was not recorded."
    first = min(timed, key=lambda s: s.finished)
    minutes = (max(s.finished for s in stages) - first.finished + first.seconds) / 60
    return f"Whole check: {minutes:.1f} minutes, from the machine's stage to the last stage recorded."


def build(config: GpuCheckConfig, folder: CheckFolder, command: str, rebuilt: bool) -> tuple[Path, bool]:
    """Write the report of what ``folder`` holds to ``<output_dir>/gpu-check.md`` (and with ``write_docs`` the
    committed one); (its path, whether every stage that ran passed)."""
    environment = folder.environment_path
    lines = environment.read_text(encoding="utf8").splitlines() if environment.is_file() else []
    lines = lines or ["the machine is not recorded in this folder (no environment.txt)"]
    if rebuilt:
        lines.append(f"Rebuilt from `{folder.root.as_posix()}` (`--report-from`).")
    stages = read_stages(folder)
    timing = [row for pair in config.pairs for row in timing_rows(folder, pair, config.warmup_steps)]
    rest = rest_results(folder, config)
    baseline = REST_BASELINE if REST_BASELINE in config.rest_methods else None
    sections = ["\n".join(f"- {line}" for line in lines), "## Stages", stage_table(stages), whole_time(stages)]
    sections.append("## Time per step at the methods' defaults")
    if any(row.state != "not run" for row in timing):
        sections += [timing_text(config), timing_table(timing)]
    else:
        sections.append("No timing run left a step log in this folder.")
    if rest:
        sections += ["## The methods trained and evaluated side by side", rest_text(config)]
        sections.append(method_table(rest, baseline))
    measured_on = None  # this machine (write_report's environment line)
    if rebuilt:
        measured_on = f"measured on the machine listed below; report rebuilt {time.strftime('%Y-%m-%d')}"
    path = write_report(config.output_dir, "gpu-check", TITLE, command, sections, measured_on)
    if config.write_docs:
        write_report(DOCS_REPORT, "gpu-check", TITLE, command, sections, measured_on)
    passed = all(s.passed is not False for s in stages) and all(r.error is None for r in rest)
    return path, passed
