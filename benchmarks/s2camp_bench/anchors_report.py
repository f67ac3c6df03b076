"""The report of ``s2camp-bench anchors``: per start, the cameras as given, the anchor with detected and with refined
keypoints (mean [min, max] over seeds where there are several), the change, and the keypoint error."""

from __future__ import annotations

import statistics
from pathlib import Path

from .common import write_report

METRICS = {
    "rot_err": "rotation (deg)", "rot_err_relative": "rotation, shared part removed (deg)", "pos_err": "position",
    "focal_err": "focal (px)", "drift_px": "drift (px)",
}  # fmt: skip
"""The camera errors of a row, after a similarity alignment to the true cameras (``evaluation.camera_metrics``,
``anchors.relative_rotation_error``)."""
START_NAMES = {"sfm": "SfM", "perturbed": "CamP's perturbation", "phone": "phone drift"}


def spread(values: list[float]) -> str:
    """``mean`` alone, or ``mean [min, max]`` over several values."""
    mean = statistics.fmean(values)
    if len(values) == 1:
        return f"{mean:.4g}"
    return f"{mean:.4g} [{min(values):.4g}, {max(values):.4g}]"


def _cells(rows: list[dict], key: str) -> str:
    return spread([row[key] for row in rows])


def camera_table(rows: list[dict]) -> str:
    lines = [
        "| start | cameras | " + " | ".join(METRICS.values()) + " | seeds |",
        "|---|---|" + "---|" * len(METRICS) + "---|",
    ]
    for start in dict.fromkeys(row["start"] for row in rows):
        detected = [row for row in rows if row["start"] == start and row["keypoints"] == "detected"]
        refined = [row for row in rows if row["start"] == start and row["keypoints"] == "refined"]
        name, seeds = START_NAMES.get(start, start), len(detected)
        given = " | ".join(_cells(detected, f"start_{key}") for key in METRICS)
        lines.append(f"| {name} | as given | {given} | {seeds} |")
        for label, group in (("tracks, detected keypoints", detected), ("tracks, refined keypoints", refined)):
            lines.append(f"| {name} | {label} | " + " | ".join(_cells(group, key) for key in METRICS) + f" | {seeds} |")
        change = []
        for key in METRICS:
            before, after = statistics.fmean(r[key] for r in detected), statistics.fmean(r[key] for r in refined)
            change.append(f"{100.0 * (after - before) / before:+.0f}%")
        lines.append(f"| {name} | refined against detected | " + " | ".join(change) + " | |")
    return "\n".join(lines)


def keypoint_table(rows: list[dict]) -> str:
    lines = ["| start | keypoints | median (px) | 90th percentile (px) | pairs |", "|---|---|---|---|---|"]
    for row in rows:
        if row["start"] == "phone" and row["seed"] > 0:
            continue  # the phone's tracks differ by seed only through its cameras: one seed shows them
        name = START_NAMES.get(row["start"], row["start"])
        cells = f"{row['keypoint_median']:.3g} | {row['keypoint_p90']:.3g} | {row['keypoint_pairs']}"
        lines.append(f"| {name} | {row['keypoints']} | {cells} |")
    return "\n".join(lines)


def write(rows: list[dict], config) -> Path:
    setup = (
        "Where the tracks alone put the cameras (the anchor: where the default starts every camera with tracks, and "
        "where the regime's \"tracks\" rows keep it), with the keypoints as detected (`--refine-keypoints False`) "
        "and as refined against the images (the default; docs/IMAGE-TRACKS.md), on the real-training regime's "
        "scene and starts ([regime](regime.md)): SfM's tracks for the SfM start, tracks made from the images with the "
        "start's cameras for the others. The pipeline is built, not trained; camera errors after a similarity "
        "alignment of their centres to the true cameras (position in scene units; the rotation error with the part "
        "every camera shares removed is the part a centre alignment cannot misattribute; drift: RMS reprojection "
        "drift of the scene's points, px at the training size). Nothing made from the true cameras reaches the "
        "method. Seeds vary the phone start's drift; SfM and CamP's perturbation are drawn once."
    )
    keypoints = (
        "Keypoint error where the generated scene's truth defines it: for every ordered pair of observations of a "
        "track, the surface point the first keypoint sees through its true camera, projected through the second's "
        "true camera, against the second keypoint (pairs the second camera sees unoccluded)."
    )
    sections = [setup, camera_table(rows), "## Keypoint error", keypoints, keypoint_table(rows)]
    title = "Anchors: detected and refined keypoints"
    return write_report(config.output_dir, "anchors", title, config.command(), sections)
