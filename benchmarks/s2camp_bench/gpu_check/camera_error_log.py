"""Camera errors against the true cameras, appended to a JSON-lines file as a run goes, and read back.

Each line is one ``ErrorRecord``: the errors of the training cameras as the model holds them after ``step`` steps
(``label`` "start": the cameras the run was given, before any refinement), after a similarity alignment to the true
cameras (``s2camp_bench.evaluation.camera_metrics``, as the benchmarks compute them).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

from .records import append_record, read_records

START = "start"
REFINED = "refined"


@dataclass
class ErrorRecord:
    label: str
    """``START``: the given cameras; ``REFINED``: the cameras as refined after ``step`` steps."""
    step: int
    rot_err: float | None
    """Degrees, mean over the training cameras."""
    pos_err: float | None
    """Scene units (the data parser's normalized world)."""
    focal_err: float | None
    """Pixels."""
    drift_px: float | None
    """RMS reprojection drift of the scene's points."""


def camera_error_record(pipeline, label: str, step: int) -> ErrorRecord:
    """The errors of ``pipeline``'s training cameras now (``REFINED``) or as given (``START``)."""
    import torch

    from s2camp_bench.evaluation import camera_metrics, estimated_cameras
    from s2camp_ns.data.camera_conversion import intrinsics_from_cameras

    model = pipeline.model
    points = pipeline.datamanager.train_dataparser_outputs.metadata["points3D_xyz"].to(torch.float64)
    if label == START:
        given = model._train_cameras
        cameras = (given.camera_to_worlds.to(torch.float64).cpu(), intrinsics_from_cameras(given.to("cpu")))
    else:
        cameras = estimated_cameras(model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # points behind a camera: left out of the drift, as in the evaluation
        metrics = camera_metrics(model, points, *cameras)
    return ErrorRecord(label, step, metrics["rot_err"], metrics["pos_err"], metrics["focal_err"], metrics["drift_px"])


def log_camera_errors(path: Path, pipeline, label: str, step: int) -> ErrorRecord:
    """Append the errors of ``pipeline``'s cameras (``camera_error_record``) to ``path``; return them."""
    record = camera_error_record(pipeline, label, step)
    append_record(path, record)
    return record


def read_camera_errors(path: Path) -> list[ErrorRecord]:
    return read_records(path, ErrorRecord)
