"""The report of ``s2camp-bench splat``: rows summarized over seeds (errors against the start, PSNR against SO3xR3
and refinement off, time per step against SO3xR3's) and the results (rows of names that no longer run apart). It
renders any committed row, of a variant that no longer runs included."""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from s2camp_bench.report import markdown_table

from . import grid
from .common import write_report
from .grid import SFM_FOCAL_PRIOR
from .grid_report import Spread, in_report_order, no_longer_run_section, seeds_cell, split_runnable
from .splat_bench import BASELINE, RECOVERY_STARTS, RUNNABLE_VARIANTS, SCENES, STARTS, SplatBenchConfig

TITLE = "Splatting: s2camp-splat against splatfacto with SO3xR3 and without refinement"
SUMMARY_METRICS = (*grid.METRICS, "sec_per_iter", "gaussians")


def summarize(rows: list[dict]) -> list[dict]:
    """One entry per scene, start and variant: the metrics over seeds (``Spread``); the start errors (equal for
    every seed); for a recovery start the fraction of each start error removed (1 - mean final / start), for the
    others the change final - start; the PSNR differences against SO3xR3 and splat-off; the ratio of the mean
    seconds per iteration to SO3xR3's from the same start and invocation (``time_ratio``). Sorted by scene, start
    and variant in the order the benchmark lists them."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["scene"], row["start"], row["variant"]), []).append(row)
    summary = []
    for (scene, start, variant), chosen in groups.items():
        entry = {"scene": scene, "start": start, "variant": variant, "seeds": len(chosen)}
        entry["seed_list"] = sorted(row["seed"] for row in chosen)
        entry["passes"] = statistics.fmean(row["passes"] for row in chosen)
        entry |= {key: Spread.of([float(row[key]) for row in chosen]) for key in SUMMARY_METRICS}
        for key in grid.ERRORS:
            start_value = entry[f"start_{key}"] = statistics.fmean(row[f"start_{key}"] for row in chosen)
            removable = start in RECOVERY_STARTS and start_value > 0
            entry[f"removed_{key}"] = 1.0 - entry[key].mean / start_value if removable else math.nan
            entry[f"change_{key}"] = entry[key].mean - start_value
        summary.append(entry)
    by_key = {(e["scene"], e["start"], e["variant"]): e for e in summary}
    for entry in summary:
        for other, label in ((BASELINE, "so3xr3"), ("splat-off", "off")):
            reference = by_key.get((entry["scene"], entry["start"], other))
            entry[f"psnr_vs_{label}"] = math.nan if reference is None else entry["psnr"].mean - reference["psnr"].mean
        baseline = groups.get((entry["scene"], entry["start"], BASELINE), [])
        entry["time_ratio"] = time_ratio(groups[(entry["scene"], entry["start"], entry["variant"])], baseline)
    return in_report_order(summary, tuple(SCENES), STARTS, RUNNABLE_VARIANTS)


def time_ratio(rows: list[dict], baseline: list[dict]) -> float:
    """Mean seconds per iteration over the baseline's, from the rows of the invocations both have runs in: the
    machine is shared, so seconds from different invocations are not comparable. Rows from before invocations were
    recorded share the invocation ''."""
    shared = {row.get("invocation", "") for row in rows} & {row.get("invocation", "") for row in baseline}
    mine = [row["sec_per_iter"] for row in rows if row.get("invocation", "") in shared]
    theirs = [row["sec_per_iter"] for row in baseline if row.get("invocation", "") in shared]
    if not mine or not theirs:
        return math.nan
    return statistics.fmean(mine) / statistics.fmean(theirs)


def _errors_cell(entry: dict) -> str:
    if entry["start"] in RECOVERY_STARTS:
        return ", ".join(f"{key.split('_')[0]} {entry[f'removed_{key}']:.0%}" for key in grid.ERRORS)
    return ", ".join(f"{key.split('_')[0]} {entry[f'change_{key}']:+.3g}" for key in grid.ERRORS)


def _signed(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:+.2f}"


def _summary_rows(summary: list[dict]) -> list[dict]:
    table = []
    for entry in summary:
        row = {key: entry[key] for key in ("scene", "start", "variant")}
        row["seeds"] = seeds_cell(entry["seed_list"])
        row |= {key: entry[key].cell() for key in grid.METRICS}
        gaussians = entry["gaussians"]
        spread = f" [{gaussians.low:.0f}, {gaussians.high:.0f}]" if gaussians.count > 1 else ""
        row["gaussians"] = f"{gaussians.mean:.0f}{spread}"
        row["sec_per_iter"] = entry["sec_per_iter"].cell(2)
        row["passes"] = f"{entry['passes']:.1f}"
        row["start_errors"] = " / ".join(f"{entry[f'start_{key}']:.3g}" for key in grid.ERRORS)
        row["against_start"] = _errors_cell(entry)
        row["psnr_vs"] = " / ".join(_signed(entry[f"psnr_vs_{label}"]) for label in ("so3xr3", "off"))
        row["time_ratio"] = "" if math.isnan(entry["time_ratio"]) else f"{entry['time_ratio']:.2f}"
        table.append(row)
    return table


def _setup_text(rows: list[dict], config: SplatBenchConfig) -> str:
    """How every run trained and was measured, and what each column means."""
    seeds = ", ".join(str(value) for value in sorted({row["seed"] for row in rows}))
    setup = (
        f"Every run: `ns-train <method>` from scratch with the method's defaults and only what a CPU run needs "
        f"(`--machine.device-type cpu`: the reference rasterizer; no evaluation or camera-error logging during "
        f"training), `--machine.seed` {seeds}. 'splat-off' is `ns-train s2camp-splat "
        f"--pipeline.model.camera-optimizer.mode off`. Starts: 'accurate' the true cameras, 'perturbed' the data "
        f"parser's CamP perturbation, 'sfm' pycolmap SfM on the full-size images (focal prior {SFM_FOCAL_PRIOR} x the "
        f"true focal). Errors of the final cameras after a similarity alignment to the true ones: rotation (deg), "
        f"position (normalized scene units), focal (px at the training resolution); drift = RMS pixel displacement "
        f"of the scene's points between the true and the aligned refined cameras. PSNR / SSIM: held-out views "
        f"(every 8th image) after {config.alignment.steps} test-time alignment steps (docs/SPLAT.md sec. 5); "
        f"'unaligned' before them. Cells: mean [min, max] over seeds. 'against start': for the perturbed start the "
        f"fraction of each start error removed (1 - final / start; negative: the error grew), for the others "
        f"final - start (rot / pos / focal / drift; positive: worse). 'PSNR vs': difference of the mean PSNR "
        f"against s2camp-splat-so3xr3 / splat-off ('-': no such run). 'time ratio': mean seconds per iteration "
        f"over s2camp-splat-so3xr3's from the same start and the same invocation of the benchmark (empty where "
        f"none ran in one: the machine is shared, so seconds of different invocations are not comparable; runs "
        f"that trained side by side share the CPU: compare ratios only between runs of the same `--workers`; "
        f"`--workers 1` on an idle machine times cleanest)."
    )
    rebuilt = [row for row in rows if row.get("reconstructed")]
    if rebuilt:
        setup += (
            f" {len(rebuilt)} row(s) were rebuilt from their run's log line (their `reconstructed` field says why): "
            f"their unaligned PSNR was not logged, so it is nan and so is every mean that includes it."
        )
    return setup


def _header(rows: list[dict]) -> str:
    iterations = ", ".join(str(value) for value in sorted({row["iterations"] for row in rows}))
    run_passes = ", ".join(f"{value:.1f}" for value in sorted({row["passes"] for row in rows}))
    return (
        f"**Regime: {iterations} steps = {run_passes} passes over each training pixel** (one whole training image per "
        "step; a 30k-step splatfacto run over ~300 images makes ~100). splatfacto's step-counted schedule scaled to "
        "the run length (`SCHEDULE_STEPS`); densification off (the start's sparse points only)."
    )


def _timing_text(rows: list[dict], config: SplatBenchConfig) -> str:
    def average(key: str) -> float:
        return statistics.fmean(row[key] for row in rows)

    workers = ", ".join(str(value) for value in sorted({row.get("workers", config.workers) for row in rows}))
    timing = (
        f"{len(rows)} runs; per run on average: training {average('train_seconds'):.0f} s (start-up included), "
        f"evaluation {average('eval_seconds'):.0f} s; {workers} run(s) side by side, one thread each"
    )
    if config.rows_from is not None:
        timing += f"; rows read from `{config.rows_from.name}` of an earlier run"
    return timing + "."


def write(rows: list[dict], config: SplatBenchConfig) -> Path:
    """Write ``<output_dir>/splat.md`` from ``rows``; return its path."""
    summary = summarize(rows)
    scene_rows = [
        {
            "scene": name, "images": SCENES[name].scene.num_cameras, "fov": f"{SCENES[name].fov_degrees:g} deg",
            "size": f"{SCENES[name].scene.width // SCENES[name].downscale}x"
            f"{SCENES[name].scene.height // SCENES[name].downscale}", "what": SCENES[name].varies,
        }
        for name in dict.fromkeys(row["scene"] for row in rows)
    ]  # fmt: skip
    columns = [
        "start", "variant", "seeds", "passes", "start_errors", *grid.METRICS, "against_start", "psnr_vs", "gaussians",
        "sec_per_iter", "time_ratio",
    ]  # fmt: skip
    headers = [
        "start", "variant", "seeds", "passes", "start rot / pos / focal / drift", "rot err (deg)", "pos err",
        "focal err (px)", "drift (px)", "PSNR", "SSIM", "PSNR unaligned", "against start", "PSNR vs so3xr3 / off",
        "Gaussians", "s / iteration", "time ratio vs so3xr3",
    ]  # fmt: skip
    current, old = split_runnable(_summary_rows(summary), RUNNABLE_VARIANTS, STARTS)
    sections = [
        "s2camp-splat against splatfacto with SO3xR3 and without camera refinement (issue 20). Protocol and "
        "metrics: `benchmarks/s2camp_bench/splat_bench.py`.",
        _header(rows),
        "## Scenes",
        markdown_table(scene_rows, ["scene", "images", "size", "fov", "what"]),
        "## Results",
        _setup_text(rows, config),
        markdown_table(current, columns, headers),
        _timing_text(rows, config),
        *(no_longer_run_section(markdown_table(old, columns, headers)) if old else []),
    ]
    return write_report(config.output_dir, "splat", TITLE, config.command(), sections, config.rows_from)
