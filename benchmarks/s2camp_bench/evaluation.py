"""A trained pipeline's evaluation, the same for every method: camera errors, drift and held-out PSNR / SSIM.

Start and final training cameras against the true ones (``reference_cameras``, else as given) after a similarity
alignment, the reprojection drift of the sparse points (``points3D_xyz``), then the held-out views after test-time
alignment. The model needs S2CampModel's camera interface: ``_train_cameras``, ``reference_cameras()``,
``uses_s2camp_optimizer`` and (nerfstudio's pose optimizer) ``refined_train_cameras()``.
"""

from __future__ import annotations

import math
import statistics
import time
import warnings

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.alignment import camera_errors
from s2camp_ns.core.camera import Intrinsics, opengl_to_opencv
from s2camp_bench.drift import reprojection_drift
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
        "rot_err": math.degrees(errors["rot_err_mean"]),
        "pos_err": errors["pos_err_mean"],
        "focal_err": errors["focal_err_mean"],
        "drift_px": drift.rms_px,
        "drift_behind": drift.behind,
    }


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


__all__ = ["camera_metrics", "evaluate_pipeline", "estimated_cameras"]
