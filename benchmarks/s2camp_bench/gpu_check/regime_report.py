"""The regime command's report, built from what its folder holds (camera errors logged as the runs go), so that a
cut run still has its figures: the start, the tracks alone, and s2camp and the images alone at each logged step."""

from __future__ import annotations

import math
from pathlib import Path

from s2camp_bench.report import markdown_table, write_report

from .camera_error_log import REFINED, START, ErrorRecord, read_camera_errors
from .records import StageResult, read_records

COMMAND = "python -m s2camp_bench.gpu_check.regime"
LABELS = {"s2camp": "s2camp (tracks and images)", "images-alone": "images alone", "tracks-alone": "tracks alone"}


def read_runs(folder) -> list[StageResult]:
    return read_records(folder.runs_path, StageResult)


def _cell(value: float | None, pattern: str) -> str:
    return "-" if value is None or not math.isfinite(value) else pattern.format(value)


def error_rows(folder, iterations_per_pass: float) -> list[dict]:
    """Table rows: the start, the tracks alone at their anchor, then s2camp and the images alone at every logged
    step (``iterations_per_pass``: steps of one pass over the training pixels)."""
    logs = {variant: read_camera_errors(folder.errors_log(variant)) for variant in LABELS}
    starts = [record for records in logs.values() for record in records if record.label == START]
    rows = [_row("start (CamP's perturbation)", starts[0], None)] if starts else []
    anchor = [record for record in logs["tracks-alone"] if record.label == REFINED]
    if anchor:
        rows.append(_row("tracks alone (the track prior's anchor, no training)", anchor[-1], None))
    for variant in ("s2camp", "images-alone"):
        for record in logs[variant]:
            if record.label == REFINED:
                rows.append(_row(LABELS[variant], record, record.step / iterations_per_pass))
    return rows


def _row(evidence: str, record: ErrorRecord, passes: float | None) -> dict:
    return {
        "evidence": evidence,
        "step": "-" if passes is None else str(record.step),
        "passes": _cell(passes, "{:.2f}"),
        "rot": _cell(record.rot_err, "{:.4f}"),
        "pos": _cell(record.pos_err, "{:.2e}"),
        "focal": _cell(record.focal_err, "{:.3f}"),
        "drift": _cell(record.drift_px, "{:.3f}"),
    }


def progress(folder, variants: tuple[str, ...]) -> str:
    """One line: the last logged step of each variant."""
    parts = []
    for variant in variants:
        refined = [record for record in read_camera_errors(folder.errors_log(variant)) if record.label == REFINED]
        parts.append(f"{variant}: " + (f"step {refined[-1].step}" if refined else "no errors logged yet"))
    return "; ".join(parts)


def setup_text(config) -> str:
    from s2camp_ns.method.schedulers import RunLengthScheduleConfig

    s = config.scene
    smoke = "**CPU smoke run of the command itself (`--cpu-smoke`): the numbers mean nothing.** "
    smoke = smoke if config.cpu_smoke else ""
    warmup = RunLengthScheduleConfig().min_warmup_steps
    return smoke + (
        f"`ns-train s2camp` with nerfacto's own field on a generated scene of {s.num_cameras} images "
        f"{s.width}x{s.height} (every 8th held out: {config.training_pixels:,} training pixels), from CamP's "
        f"perturbation of the training cameras: {config.iterations} steps of {config.rays_per_batch} rays, "
        f"{config.passes:g} pass(es) over the training pixels; the camera learning rate warms up over at least the "
        f"first {warmup} steps (s2camp's schedule). Every variant has the same evidence: tracks made from the images "
        'with the perturbed cameras (`s2camp-data --perturbation.enabled True`, image tracks "auto"); the true '
        "cameras only measure. tracks alone: `--pipeline.model.camera-optimizer.photometric False` (each camera at "
        "its track prior's anchor), read after set-up. images alone: `train_commands.PHOTOMETRIC_ONLY` (no prior, "
        f"no removal of the common rotation). Errors every {config.errors_every} steps, mean over the training "
        "cameras after a similarity alignment to the true ones: rotation (deg), position (scene units), focal (px), "
        "the RMS reprojection drift of the scene's points (px)."
    )


def build(config, folder, command: str) -> Path:
    """Write ``<output_dir>/regime.md`` from the files of ``folder``; return its path."""
    per_pass = config.iterations / config.passes
    rows = error_rows(folder, per_pass)
    runs = read_runs(folder)
    table = markdown_table(
        rows,
        ["evidence", "step", "passes", "rot", "pos", "focal", "drift"],
        ["evidence", "step", "passes", "rotation err (deg)", "position err", "focal err (px)", "drift (px)"],
    )
    run_rows = [
        {"run": r.name, "result": r.outcome, "seconds": _cell(r.seconds, "{:.0f}"), "detail": r.detail} for r in runs
    ]
    sections = [
        setup_text(config),
        "## Camera errors",
        table if rows else "No camera errors were logged.",
        "## Runs",
        markdown_table(run_rows, ["run", "result", "seconds", "detail"]) if run_rows else "No run has ended.",
    ]
    return write_report(config.output_dir, "regime", "The regime at real resolution", command, sections)
