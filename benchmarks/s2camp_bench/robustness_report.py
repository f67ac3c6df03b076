"""The report of ``s2camp-bench robustness``: rows summarized over seeds, the scene table, the results (rows of names
that no longer run apart), and the cameras' paths of committed rows traced by an option that no longer runs. It
renders any committed row, of a variant, start or scene that no longer runs included."""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from s2camp_bench.report import markdown_table

from . import grid, robustness
from .common import write_report
from .grid import SFM_FOCAL_PRIOR
from .grid_report import Spread, in_report_order, no_longer_run_section, seeds_cell, split_runnable

TITLE = "Robustness: default camera refinement from accurate and perturbed cameras"
TRACE_COLUMNS = (
    "step", "train_loss", "rot_err", "moved_rot", "moved_pos", "moved_focal", "gauge_scale", "gauge_rot",
    "forward_shift", "focal_forward_corr", "rot_err_common", "pitch_y_corr", "yaw_x_corr", "pose_consistency",
    "intrinsics_consistency",
)  # fmt: skip


def summarize(rows: list[dict]) -> list[dict]:
    """One entry per scene, start, variant, SfM build and passes per pixel: the metrics over seeds (``Spread``), the
    PSNR difference against "off" of the same start, build and passes (labelled "no difference" when smaller than the
    larger of the two seed ranges) and, for a start refinement must correct, the fraction of each start error removed
    (1 - mean final / start). In report order (``report_order``)."""
    groups: dict[tuple[str, ...], list[dict]] = {}
    for row in rows:
        key = (row["scene"], row["start"], row["variant"], _start_build(row), f"{row.get('passes', math.nan):.3g}")
        groups.setdefault(key, []).append(row)
    summary = []
    for (scene, start, variant, build, passes), chosen in groups.items():
        entry = {"scene": scene, "start": start, "variant": variant, "build": build, "seeds": len(chosen)}
        entry["seed_list"] = sorted(row["seed"] for row in chosen)
        entry["passes_key"] = passes
        entry["passes"] = statistics.fmean(row.get("passes", math.nan) for row in chosen)
        entry |= {key: Spread.of([row[key] for row in chosen]) for key in grid.METRICS}
        for key in grid.ERRORS:
            start_value = entry[f"start_{key}"] = statistics.fmean(row[f"start_{key}"] for row in chosen)
            removable = start in robustness.RECOVERY_STARTS and start_value > 0
            entry[f"removed_{key}"] = 1.0 - entry[key].mean / start_value if removable else math.nan
        summary.append(entry)
    by_key = {_summary_key(entry): entry for entry in reversed(summary)}
    for entry in summary:
        start = robustness.OFF_REFERENCE_START.get(entry["start"], entry["start"])
        off = by_key.get((entry["scene"], start, "off", entry["build"], entry["passes_key"]))
        entry["psnr_vs_off"] = math.nan if off is None else entry["psnr"].mean - off["psnr"].mean
        entry["psnr_vs_off_label"] = _difference_label(entry, off)
    return report_order(summary, then=("passes_key", "build"))


def report_order(entries: list[dict], then: tuple[str, ...] = ()) -> list[dict]:
    """``entries`` by scene, start and variant in the order the benchmark lists them (names no longer run after
    them), then by the keys ``then``."""
    return in_report_order(entries, tuple(robustness.SCENES), robustness.STARTS, robustness.VARIANTS, then)


def _summary_key(entry: dict) -> tuple[str, ...]:
    return entry["scene"], entry["start"], entry["variant"], entry["build"], entry["passes_key"]


def _start_build(row: dict) -> str:
    """Which SfM reconstruction an sfm row started from (its start rotation error; pycolmap's builds differ between
    work folders, and rows of different builds are different starts), "" for the other starts."""
    return f"{row['start_rot_err']:.4g}" if row["start"] == "sfm" else ""


def _difference_label(entry: dict, off: dict | None) -> str:
    if off is None or entry["variant"] == "off":
        return ""
    difference = entry["psnr"].mean - off["psnr"].mean
    spread = max(entry["psnr"].width, off["psnr"].width)
    text = f"{difference:+.2f} dB"
    if min(entry["seeds"], off["seeds"]) < 2:
        return f"{text} (1 seed, no spread)"
    return f"{text} (no difference)" if abs(difference) < spread else f"{text} (beyond the seed range {spread:.2f})"


def _scene_table(summary: list[dict]) -> str:
    rows = []
    for name in dict.fromkeys(entry["scene"] for entry in summary):
        preset = {**robustness.SCENES, **robustness.RETIRED_SCENES}[name]
        s = preset.scene
        perturbed = {e["start"]: e for e in summary if e["scene"] == name}.get("perturbed")
        start = "" if perturbed is None else (
            f"rot {perturbed['start_rot_err']:.3f} deg, pos {perturbed['start_pos_err']:.2e}, focal "
            f"{perturbed['start_focal_err']:.3f} px, drift {perturbed['start_drift_px']:.3f} px"
        )  # fmt: skip
        rows.append({
            "scene": name, "images": s.num_cameras, "size": f"{s.width}x{s.height}",
            "fov": f"{preset.fov_degrees:g} deg (f {s.focal:.1f} px)", "ring": s.ring_radius,
            "seed": preset.perturbation_seed, "start": start, "varies": preset.varies,
        })  # fmt: skip
    columns = ["scene", "images", "size", "fov", "ring", "seed", "start", "varies"]
    headers = ["scene", "images", "size", "fov", "ring radius", "perturbation seed", "perturbed start errors", "what"]
    return markdown_table(rows, columns, headers)


def _summary_rows(summary: list[dict]) -> list[dict]:
    table = []
    for entry in summary:
        row = {key: entry[key] for key in ("scene", "start", "variant")}
        row["seeds"] = seeds_cell(entry["seed_list"])
        row |= {key: entry[key].cell() for key in grid.METRICS}
        row["psnr_vs_off"] = entry["psnr_vs_off_label"]
        row["passes"] = f"{entry['passes']:.2f}"
        row["start_errors"] = " / ".join(f"{entry[f'start_{key}']:.3g}" for key in grid.ERRORS)
        short = {key: key.replace("_err", "").replace("_px", "") for key in grid.ERRORS}
        removed = (f"{short[key]} {entry[f'removed_{key}']:.0%}" for key in grid.ERRORS)
        row["removed"] = ", ".join(removed) if entry["start"] in robustness.RECOVERY_STARTS else ""
        table.append(row)
    return table


def _setup_text(rows: list[dict], config: robustness.RobustnessConfig) -> str:
    """How every run trained and was measured, and what each column means."""
    iterations = ", ".join(str(value) for value in sorted({row["iterations"] for row in rows}))
    seeds = ", ".join(str(value) for value in sorted({row["seed"] for row in rows}))
    a = config.alignment
    return (
        f"Every run: `ns-train <method>` from scratch with the method's default options (camera learning rate and "
        f"schedule included) and only what a CPU run needs: the small nerfacto field "
        f"(`s2camp_bench.train_commands.SMALL_MODEL`), `--machine.device-type cpu`, `--max-num-iterations "
        f"{iterations}`, {config.rays_per_batch} rays per step, no evaluation or camera-error logging during "
        f"training; `--machine.seed` {seeds}. 'off' is `ns-train s2camp --pipeline.model.camera-optimizer.mode off`. "
        f"'perturbed' is the data parser's CamP perturbation (CamP's sigmas, the scene's perturbation seed), "
        f"'accurate' the true cameras, 'sfm' pycolmap SfM on the full-size images (focal prior {SFM_FOCAL_PRIOR} x "
        f"the true focal; built once per work folder; builds in different work folders differ, so the start "
        f"column gives each row's SfM errors and rows of different builds are different rows; the prior's anchor "
        f"is fitted to SfM's points re-adjusted with its robust loss, `s2camp_ns/tracks/robust_adjustment.py`), "
        f"'phone' `PHONE_PROFILE` without SfM tracks, 'accurate-untracked' the true cameras without SfM tracks "
        f"(`benchmarks/s2camp_bench/robustness.py`); both train with tracks made from their images (`--image-tracks "
        f"always`, `s2camp_ns/tracks/image_tracks.py`). Errors of the final checkpoint after a similarity alignment "
        f"to the true cameras: rotation in degrees, position in normalized scene units (the cameras fit in [-1, "
        f"1]^3), focal in px; drift = RMS pixel displacement of the scene's 3D points between the true and the "
        f"aligned refined cameras (`s2camp_bench.drift`). PSNR / SSIM: held-out views (every 8th image) after "
        f"{a.steps} test-time alignment steps of {a.rays} rays. Cells: mean [min, max] over the runs, one per seed "
        f"unless the seeds cell names a seed run twice. 'PSNR vs off': difference of the means, 'no difference' "
        f"when smaller than the larger seed range of the two. 'removed': 1 - final / start error for perturbed and "
        f"phone starts."
    )


def _timing_text(rows: list[dict], config: robustness.RobustnessConfig) -> str:
    def average(key: str) -> float:
        return statistics.fmean(row[key] for row in rows)

    timing = (
        f"{len(rows)} runs; per run on average: training {average('train_seconds'):.0f} s (start-up included, "
        f"{average('sec_per_iter'):.3f} s / iteration), evaluation {average('eval_seconds'):.0f} s; "
        f"{config.workers} runs side by side"
    )
    if config.rows_from is not None:
        seed_count = len({row["seed"] for row in rows})
        timing += f"; rows read from `{config.rows_from.name}` of an earlier run ({seed_count} seed(s)"
        stopped = f"; the command runs {config.seeds}: that run was stopped early"
        timing += ")" if seed_count >= config.seeds else stopped + ")"
    return timing + "."


def write(rows: list[dict], config: robustness.RobustnessConfig) -> Path:
    """Write ``<output_dir>/<preset>.md`` from ``rows``; return its path."""
    summary, name, metrics = summarize(rows), config.preset, grid.METRICS
    columns = ["scene", "start", "variant", "seeds", "passes", "start_errors", *metrics, "psnr_vs_off", "removed"]
    headers = [
        "scene", "start", "variant", "seeds", "passes", "start rot / pos / focal / drift", "rot err (deg)",
        "pos err", "focal err (px)", "drift (px)", "PSNR", "SSIM", "PSNR unaligned", "PSNR vs off",
        "start error removed",
    ]  # fmt: skip
    current, old = split_runnable(_summary_rows(summary), robustness.VARIANTS, robustness.STARTS)
    sections = [
        "Does camera refinement with each method's default options help or hurt, from accurate and from perturbed "
        "cameras? Protocol and metrics: `benchmarks/s2camp_bench/robustness.py`. passes = steps x rays / training "
        "pixels.",
        "## Scenes",
        _scene_table(summary),
        "## Results",
        _setup_text(rows, config),
        markdown_table(current, columns, headers),
        _timing_text(rows, config),
        *(no_longer_run_section(markdown_table(old, columns, headers)) if old else []),
        *trace_sections(rows),
    ]
    return write_report(config.output_dir, name, TITLE, config.command(), sections, config.rows_from)


def trace_sections(rows: list[dict]) -> list[str]:
    """One table per committed row with a "trace": the cameras' path through its training, recorded by an option
    that no longer runs (its columns: docs/RESULTS.md, "Names that no longer run")."""
    sections = []
    for row in report_order(rows, then=("seed",)):
        if not row.get("trace"):
            continue
        title = f"### Camera path: {row['scene']}, {row['start']} start, {row['variant']}, seed {row['seed']}"
        cells = [{key: f"{point.get(key, math.nan):.4g}" for key in TRACE_COLUMNS} for point in row["trace"]]
        sections += [title, markdown_table(cells, list(TRACE_COLUMNS), list(TRACE_COLUMNS))]
    if sections:
        columns = 'columns: docs/RESULTS.md, "Names that no longer run"'
        heading = f"## The mechanism: camera paths (`--trace-every`, an option that no longer runs; {columns})"
        sections.insert(0, heading)
    return sections
