"""A trained run's evaluation, the same for every method: camera errors, drift, held-out PSNR / SSIM, step time.

Start and final training cameras against the true ones (``reference_cameras``, else as given) after a similarity
alignment, the reprojection drift of the sparse points, then the held-out views after test-time alignment; the model
needs S2CampModel's camera interface. ``load_pipeline`` loads a finished ``ns-train`` run, ``seconds_per_iteration``
reads its step time from its tensorboard events.
"""

from __future__ import annotations

import contextlib
import io
import math
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_bench.drift import reprojection_drift
from s2camp_ns.core.alignment import camera_errors
from s2camp_ns.core.camera import Intrinsics, opengl_to_opencv
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig, evaluate_held_out_views


def camera_metrics(
    model, points: Float[Tensor, "m 3"], c2w_gl: Float[Tensor, "n 3 4"], intrinsics: Intrinsics
) -> dict[str, float]:
    """Mean errors of cameras (OpenGL c2w, ``Intrinsics``) against the true training cameras after a similarity
    alignment: ``rot_err`` (degrees), ``pos_err``, ``focal_err`` (px), ``drift_px`` (RMS), ``drift_behind``."""
    reference = model.reference_cameras()
    if reference is None:
        reference = model._train_cameras
    true_c2w = reference.camera_to_worlds.to(torch.float64).cpu()
    true_intrinsics = intrinsics_from_cameras(reference.to("cpu"))
    errors = camera_errors(c2w_gl, true_c2w, intrinsics.fx, true_intrinsics.fx, align=True)
    drift = reprojection_drift(
        points, opengl_to_opencv(true_c2w), true_intrinsics, opengl_to_opencv(c2w_gl), intrinsics, align=True
    )
    return {
        "rot_err": math.degrees(errors["rot_err_mean"]), "pos_err": errors["pos_err_mean"],
        "focal_err": errors["focal_err_mean"], "drift_px": drift.rms_px, "drift_behind": drift.behind,
    }  # fmt: skip


def estimated_cameras(model) -> tuple[Float[Tensor, "n 3 4"], Intrinsics]:
    """OpenGL c2w [n, 3, 4] and ``Intrinsics`` of the training cameras as the model sees them (float64, CPU)."""
    with torch.no_grad():
        if model.uses_s2camp_optimizer:
            optimizer = model.camera_optimizer
            refiner = optimizer.refiner
            return refiner.refined_c2w(opengl=True).cpu(), refiner.refined_intrinsics().detach().to("cpu")
        c2w, _ = model.refined_train_cameras()  # nerfstudio's pose optimizer leaves the intrinsics alone
        return c2w, intrinsics_from_cameras(model._train_cameras)


def evaluate_pipeline(pipeline, alignment: AlignmentConfig) -> dict:
    """``camera_metrics`` of the final cameras (and of the start ones as ``start_<name>``), means over the
    ``eval_views`` held-out views of ``psnr``, ``ssim`` and ``psnr_unaligned``, and ``eval_seconds``."""
    began = time.perf_counter()
    model = pipeline.model
    points = pipeline.datamanager.train_dataparser_outputs.metadata["points3D_xyz"].to(torch.float64)
    start_cameras = model._train_cameras
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # points behind a camera: counted in drift_behind
        start = camera_metrics(
            model, points, start_cameras.camera_to_worlds.to(torch.float64), intrinsics_from_cameras(start_cameras)
        )
        final = camera_metrics(model, points, *estimated_cameras(model))
    views = evaluate_held_out_views(pipeline, alignment)
    result = {key: value for key, value in final.items()}
    result |= {f"start_{key}": value for key, value in start.items()}
    result["psnr"] = statistics.fmean(view.psnr for view in views)
    result["ssim"] = statistics.fmean(view.ssim for view in views)
    result["psnr_unaligned"] = statistics.fmean(view.psnr_unaligned for view in views)
    result["eval_views"] = len(views)
    result["eval_seconds"] = time.perf_counter() - began
    return result


SKIPPED_TIMING_STEPS = 5
"""Logged steps left out of ``seconds_per_iteration`` (start-up: caches, first allocations)."""


def load_pipeline(run: Path):
    """The pipeline of the finished ``ns-train`` run folder ``run`` (nerfstudio's ``eval_setup``, latest checkpoint),
    its start-up chatter kept off the terminal unless loading fails."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured), contextlib.redirect_stderr(captured), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from nerfstudio.utils.eval_utils import eval_setup

            _, pipeline, _, _ = eval_setup(run / "config.yml", test_mode="test")
    except Exception:
        print(captured.getvalue(), file=sys.stderr, flush=True)
        raise
    return pipeline


def seconds_per_iteration(run: Path) -> float:
    """Mean wall-clock seconds per training step of the run folder ``run``, from nerfstudio's per-step tensorboard
    events after the first ``SKIPPED_TIMING_STEPS`` logged ones; NaN without events."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = sorted(run.glob("events.out.tfevents.*"))
    if not events:
        return math.nan
    accumulator = EventAccumulator(str(events[-1]), size_guidance={"scalars": 0})
    accumulator.Reload()
    stamps = accumulator.Scalars("Train Iter (time)")
    stamps = stamps[SKIPPED_TIMING_STEPS:] if len(stamps) > SKIPPED_TIMING_STEPS + 1 else stamps
    if len(stamps) < 2:
        return math.nan
    return (stamps[-1].wall_time - stamps[0].wall_time) / (stamps[-1].step - stamps[0].step)


__all__ = ["camera_metrics", "estimated_cameras", "evaluate_pipeline", "load_pipeline", "seconds_per_iteration"]
