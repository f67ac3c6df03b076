"""What a training run appends to JSON-lines files while it trains (``records``), and how they are read back: a step
log (one ``RunStart``, ``StepTime`` lines every few steps, so a cut run keeps the steps written before, one ``RunEnd``;
a step's time runs from the end of the previous step to its own end; steps that refreshed P are kept apart) and a
camera-error log (``ErrorRecord`` lines after a similarity alignment to the true cameras, ``evaluation``).
"""

from __future__ import annotations

import statistics
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from .records import append_record, as_record, read_lines, read_records

START = "start"
REFINED = "refined"


@dataclass
class RunStart:
    method: str
    device: str
    started: float = field(default_factory=time.time)
    kind: str = "start"


@dataclass
class StepTime:
    step: int
    seconds: float
    refresh: bool = False
    """P was refreshed during this step."""
    kind: str = "step"


@dataclass
class RunEnd:
    steps: int
    """Steps trained."""
    peak_memory_bytes: int | None
    """``torch.cuda.max_memory_allocated()`` of the run (None on the CPU)."""
    stopped_early: bool = False
    """Stopped before its last step to end before the deadline."""
    refresh_seconds: list[float] = field(default_factory=list)
    """P's refresh timed apart after training (S2CamP methods), once per repetition."""
    kind: str = "end"


class StepLog:
    """Writes a run's ``RunStart`` at once, its ``StepTime`` lines every ``every`` steps, and its ``RunEnd``."""

    def __init__(self, path: Path, method: str, device: str, every: int) -> None:
        self.path, self.every, self.pending = path, every, []
        path.unlink(missing_ok=True)
        append_record(path, RunStart(method, device))

    def add(self, step: int, seconds: float, refresh: bool) -> None:
        self.pending.append(StepTime(step, seconds, refresh))
        if len(self.pending) >= self.every:
            self.flush()

    def flush(self) -> None:
        for record in self.pending:
            append_record(self.path, record)
        self.pending = []

    def end(self, record: RunEnd) -> None:
        self.flush()
        append_record(self.path, record)


@dataclass
class StepTimes:
    """A run's step log as read back; ``end`` None: the run was cut before it ended (its steps so far are kept)."""

    method: str
    device: str
    steps: list[StepTime]
    end: RunEnd | None

    def ordinary_seconds(self, warmup_steps: int) -> list[float]:
        """Seconds of the steps from ``warmup_steps`` on, without those that refreshed P."""
        return [s.seconds for s in self.steps if s.step >= warmup_steps and not s.refresh]

    def median_seconds(self, warmup_steps: int) -> float | None:
        """Median of ``ordinary_seconds`` (None with fewer than two)."""
        timed = self.ordinary_seconds(warmup_steps)
        return statistics.median(timed) if len(timed) >= 2 else None

    def refresh_seconds(self) -> list[float]:
        """P's refreshes: the steps that held one, then those timed apart after training."""
        return [s.seconds for s in self.steps if s.refresh] + (self.end.refresh_seconds if self.end else [])


def read_step_log(path: Path) -> StepTimes | None:
    """The step log at ``path``; None when there is none (the run never started)."""
    lines = read_lines(path)
    starts = [as_record(RunStart, line) for line in lines if line.get("kind") == "start"]
    if not starts:
        return None
    steps = [as_record(StepTime, line) for line in lines if line.get("kind") == "step"]
    ends = [as_record(RunEnd, line) for line in lines if line.get("kind") == "end"]
    return StepTimes(starts[-1].method, starts[-1].device, steps, ends[-1] if ends else None)


@dataclass
class ErrorRecord:
    """Mean errors of the training cameras: rotation (deg), position (scene units), focal (px), drift (RMS px)."""

    label: str
    """``START``: the given cameras; ``REFINED``: the cameras as refined after ``step`` steps."""
    step: int
    rot_err: float | None
    pos_err: float | None
    focal_err: float | None
    drift_px: float | None


def log_camera_errors(path: Path, pipeline, label: str, step: int) -> None:
    """Append the errors of ``pipeline``'s training cameras now (``REFINED``) or as given (``START``) to ``path``."""
    import torch

    from s2camp_bench.evaluation import camera_metrics, estimated_cameras
    from s2camp_ns.data.camera_conversion import intrinsics_from_cameras

    model = pipeline.model
    points = pipeline.datamanager.train_dataparser_outputs.metadata["points3D_xyz"].to(torch.float64)
    given = model._train_cameras
    start = (given.camera_to_worlds.to(torch.float64).cpu(), intrinsics_from_cameras(given.to("cpu")))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # points behind a camera: left out of the drift, as in the evaluation
        metrics = camera_metrics(model, points, *(start if label == START else estimated_cameras(model)))
    errors = [metrics[key] for key in ("rot_err", "pos_err", "focal_err", "drift_px")]
    append_record(path, ErrorRecord(label, step, *errors))


def read_camera_errors(path: Path) -> list[ErrorRecord]:
    return read_records(path, ErrorRecord)
