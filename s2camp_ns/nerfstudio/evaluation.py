"""A trained pipeline's evaluation, identical for every method: camera errors, drift and held-out PSNR / SSIM.

``evaluate_pipeline`` measures the training cameras the run started from and those it ended with against the true
cameras (the model's ``reference_cameras``, else the training cameras as given), after a similarity alignment
(``core.alignment.camera_errors``): rotation (degrees), position (normalized scene units) and focal (px) errors,
means over the training cameras, and the reprojection drift of the scene's sparse points (``core.drift``, the data
parser's ``points3D_xyz``). Then the held-out views after test-time alignment
(``test_time_alignment.evaluate_held_out_views``, CamP's protocol). The benchmarks (``s2camp-bench robustness``,
``splat``) evaluate every run with it, and ``make gpu-check`` in the training process.

The pipeline needs ``datamanager.train_dataparser_outputs.metadata["points3D_xyz"]`` and a model with S2CampModel's
camera interface: ``_train_cameras``, ``reference_cameras()``, ``uses_s2camp_optimizer`` and, for nerfstudio's own
pose optimizer, ``refined_train_cameras()`` (stock nerfacto gets it from
``s2camp_ns.benchmarks.gpu_check.stock_nerfacto``).
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
from s2camp_ns.core.drift import reprojection_drift
from s2camp_ns.nerfstudio.camera_conversion import intrinsics_from_cameras
from s2camp_ns.nerfstudio.test_time_alignment import AlignmentConfig, evaluate_held_out_views


def camera_metrics(
    model, points: Float[Tensor, "m 3"], c2w_gl: Float[Tensor, "n 3 4"], intrinsics: Intrinsics
) -> dict[str, float]:
    """Errors of cameras (OpenGL c2w, ``Intrinsics``) against the model's true training cameras, after a similarity
    alignment, and their drift: ``rot_err`` (degrees), ``pos_err``, ``focal_err`` (px), ``drift_px`` (RMS) and
    ``drift_behind`` (points behind a camera, left out of the drift)."""
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


def refined_cameras(model) -> tuple[Float[Tensor, "n 3 4"], Intrinsics]:
    """OpenGL c2w and ``Intrinsics`` of the training cameras as the model sees them at the end (float64, CPU):
    S2CamP's refined cameras, or nerfstudio's pose refinement with the intrinsics as given."""
    with torch.no_grad():
        if model.uses_s2camp_optimizer:
            optimizer = model.camera_optimizer
            refiner = optimizer.refiner
            return refiner.refined_c2w(opengl=True).cpu(), refiner.refined_intrinsics().detach().to("cpu")
        c2w, _ = model.refined_train_cameras()  # nerfstudio's pose optimizer leaves the intrinsics alone
        return c2w, intrinsics_from_cameras(model._train_cameras)


def evaluate_pipeline(pipeline, alignment: AlignmentConfig) -> dict:
    """The evaluation of a trained pipeline in memory (module docstring): ``camera_metrics`` of the final cameras
    under their names and of the start cameras as ``start_<name>``; ``psnr``, ``ssim`` and ``psnr_unaligned``, means
    over the held-out views (``eval_views`` of them); ``eval_seconds``, the evaluation's wall time."""
    began = time.perf_counter()
    model = pipeline.model
    points = pipeline.datamanager.train_dataparser_outputs.metadata["points3D_xyz"].to(torch.float64)
    start_cameras = model._train_cameras
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the drift's warning about points behind a camera: counted in the row
        start = camera_metrics(
            model, points, start_cameras.camera_to_worlds.to(torch.float64), intrinsics_from_cameras(start_cameras)
        )
        final = camera_metrics(model, points, *refined_cameras(model))
    views = evaluate_held_out_views(pipeline, alignment)
    result = {key: value for key, value in final.items()}
    result |= {f"start_{key}": value for key, value in start.items()}
    result["psnr"] = statistics.fmean(view.psnr for view in views)
    result["ssim"] = statistics.fmean(view.ssim for view in views)
    result["psnr_unaligned"] = statistics.fmean(view.psnr_unaligned for view in views)
    result["eval_views"] = len(views)
    result["eval_seconds"] = time.perf_counter() - began
    return result


__all__ = ["camera_metrics", "evaluate_pipeline", "refined_cameras"]
