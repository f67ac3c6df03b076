"""The path of the training cameras through a run (``s2camp-bench robustness --trace-every N``): what moves first,
along which direction, and how the camera gradient relates to the field's fit.

For every checkpoint of a finished run (one each ``trace_every`` steps), from the camera optimizer's state:

- ``rot_err`` / ``pos_err`` / ``focal_err``: errors against the true cameras after similarity alignment (degrees,
  normalized units, px), as the robustness rows;
- ``moved_rot`` / ``moved_pos`` / ``moved_focal``: how far the refined cameras are from the given ones, without any
  alignment (degrees, normalized units, px; means over cameras);
- ``gauge_scale`` / ``gauge_rot`` / ``gauge_shift``: the similarity that best maps the given camera centres onto the
  refined ones (Umeyama): the part of the motion the photometric loss cannot see (scale - 1, degrees, normalized
  units);
- ``forward_shift``: mean move of the centres along their own optical axes (normalized units, + forward), and
  ``focal_forward_corr``: the correlation over cameras of the relative focal change with the forward move divided by
  the camera's distance to the scene centre (focal against depth: a camera that zooms in and backs away keeps the
  centre's image). With one focal length shared by all images (one physical camera) the focal change has no
  spread over cameras and the correlation is 0: compare ``moved_focal`` with ``gauge_scale`` instead (all centres
  moving in together is the depth change of every camera at once);
- ``rot_err_pitch`` / ``rot_err_yaw`` / ``rot_err_roll``, ``rot_err_common``, ``pitch_y_corr`` / ``yaw_x_corr``:
  where the aligned rotation error lies (``error_structure``): per camera axis, shared by all cameras, and along the
  rotation-translation ambiguity (correlations near +1 / -1);
- ``pose_consistency`` / ``intrinsics_consistency``: Adam's |m| / sqrt(v) over the whitened latent, the RMS over
  coordinates (the bias-corrected moments; about 0.23 for pure noise with beta1 0.9, 1 for a gradient of constant
  sign);
- ``train_loss``: nerfstudio's logged training loss at the nearest logged step (the field's fit).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.alignment import relative_rotation


def rotation_vector(r_a: Float[Tensor, "n 3 3"], r_b: Float[Tensor, "n 3 3"]) -> Float[Tensor, "n 3"]:
    """Axis-angle vector (rad) of r_a^T r_b, the rotation from r_a to r_b in r_a's frame, for angles below pi."""
    skew, angle = relative_rotation(r_a, r_b)
    norm = torch.linalg.norm(skew, dim=-1, keepdim=True)
    return torch.where(norm > 0, skew * (angle[:, None] / norm.clamp(min=torch.finfo(skew.dtype).tiny)), 0.0)


def _checkpoints(run: Path) -> list[Path]:
    return sorted((run / "nerfstudio_models").glob("step-*.ckpt"), key=lambda p: int(p.stem.split("-")[1]))


def _train_losses(run: Path) -> dict[int, float]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = sorted(run.glob("events.out.tfevents.*"))
    if not events:
        return {}
    accumulator = EventAccumulator(str(events[-1]), size_guidance={"scalars": 0})
    accumulator.Reload()
    if "Train Loss" not in accumulator.Tags().get("scalars", []):
        return {}
    return {event.step: event.value for event in accumulator.Scalars("Train Loss")}


def _nearest(values: dict[int, float], step: int) -> float:
    if not values:
        return math.nan
    return values[min(values, key=lambda s: abs(s - step))]


def _consistency(state: dict, beta1: float, beta2: float) -> float:
    """RMS over coordinates of Adam's bias-corrected |m| / sqrt(v)."""
    if not state or "exp_avg" not in state:
        return math.nan
    step = float(state["step"])
    m = state["exp_avg"].double() / (1 - beta1**step)
    v = state["exp_avg_sq"].double() / (1 - beta2**step)
    ratio = m.abs() / (v.sqrt() + 1e-30)
    return float(ratio.square().mean().sqrt())


def _correlation(x: torch.Tensor, y: torch.Tensor) -> float:
    """Pearson correlation over cameras; 0 where either has no spread."""
    x, y = x - x.mean(), y - y.mean()
    return float((x * y).sum() / ((x.square().sum() * y.square().sum()).sqrt() + 1e-30))


def error_structure(aligned_cv: torch.Tensor, reference_cv: torch.Tensor) -> dict[str, float]:
    """Where the aligned cameras' errors lie, each in its own reference camera's frame (OpenCV: x right, y down, z
    forward): the RMS rotation error about each axis (pitch about x, yaw about y, roll about z; degrees), the norm
    of the mean rotation error (the part every camera shares; degrees), and the correlation over cameras of the
    pitch error with the y position error and of the yaw error with the x position error. A rotation and a
    translation whose image shifts cancel for content at depth D (pitch theta with y = +D theta, yaw theta with
    x = -D theta) give +1 and -1: the rotation-translation ambiguity, which the photometric loss sees only through
    the parallax between depths."""

    error = rotation_vector(reference_cv[:, :, :3], aligned_cv[:, :, :3])
    offset = ((aligned_cv[:, :, 3] - reference_cv[:, :, 3])[:, None, :] @ reference_cv[:, :, :3])[:, 0]
    rms = torch.rad2deg(error.square().mean(dim=0).sqrt())
    return {
        "rot_err_pitch": float(rms[0]),
        "rot_err_yaw": float(rms[1]),
        "rot_err_roll": float(rms[2]),
        "rot_err_common": math.degrees(float(error.mean(dim=0).norm())),
        "pitch_y_corr": _correlation(error[:, 0], offset[:, 1]),
        "yaw_x_corr": _correlation(error[:, 1], offset[:, 0]),
    }


def camera_path_point(optimizer, reference_c2w_gl, reference_fx) -> dict[str, float]:
    """The trace quantities (module docstring) of an S2CamP camera optimizer's current cameras."""
    from s2camp_ns.core.alignment import align_cameras, camera_errors, rotation_angle, umeyama
    from s2camp_ns.core.camera import opengl_to_opencv

    with torch.no_grad():
        refiner = optimizer.refiner
        given = refiner.base_c2w_cv.cpu()
        refined = refiner.refined_c2w().cpu()
        given_fx = refiner.base_intrinsics[:, 0].cpu()
        refined_fx = refiner.refined_intrinsics().fx.detach().cpu()
    errors = camera_errors(opengl_to_opencv(refined), reference_c2w_gl, refined_fx, reference_fx, align=True)
    reference_cv = opengl_to_opencv(reference_c2w_gl.to(torch.float64))
    structure = error_structure(align_cameras(refined, reference_cv).apply_to_poses(refined), reference_cv)
    gauge = umeyama(given[:, :, 3], refined[:, :, 3])
    identity = torch.eye(3, dtype=torch.float64)[None]
    forward = ((refined[:, :, 3] - given[:, :, 3]) * given[:, :, 2]).sum(dim=-1)
    distance = given[:, :, 3].norm(dim=-1).clamp(min=1e-9)
    focal_change = refined_fx / given_fx - 1.0
    return {
        "rot_err": math.degrees(errors["rot_err_mean"]),
        "pos_err": errors["pos_err_mean"],
        "focal_err": errors["focal_err_mean"],
        "moved_rot": math.degrees(float(rotation_angle(given[:, :, :3], refined[:, :, :3]).mean())),
        "moved_pos": float((refined[:, :, 3] - given[:, :, 3]).norm(dim=-1).mean()),
        "moved_focal": float((refined_fx - given_fx).abs().mean()),
        "gauge_scale": float(gauge.scale) - 1.0,
        "gauge_rot": math.degrees(float(rotation_angle(identity, gauge.rotation[None])[0])),
        "gauge_shift": float(gauge.translation.norm()),
        "forward_shift": float(forward.mean()),
        "focal_forward_corr": _correlation(focal_change, forward / distance),
        **structure,
    }


def trace_run(run: Path) -> list[dict]:
    """One row per checkpoint of ``run`` (module docstring); [] for a run without S2CamP's camera optimizer."""
    from s2camp_ns.data.camera_conversion import intrinsics_from_cameras

    from .evaluation import load_pipeline

    pipeline = load_pipeline(run)
    model = pipeline.model
    if not model.uses_s2camp_optimizer or not model.camera_optimizer.enabled:
        return []
    reference = model.reference_cameras()
    reference = model._train_cameras if reference is None else reference
    reference_c2w = reference.camera_to_worlds.to(torch.float64).cpu()
    reference_fx = intrinsics_from_cameras(reference.to("cpu")).fx
    losses = _train_losses(run)
    rows = []
    for path in _checkpoints(run):
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
        step = int(checkpoint["step"])
        pipeline.load_pipeline(checkpoint["pipeline"], step)
        optimizer = model.camera_optimizer
        row = {"step": step, **camera_path_point(optimizer, reference_c2w, reference_fx)}
        camera_state = checkpoint["optimizers"].get("camera_opt", {})
        states = camera_state.get("state", {})
        groups = camera_state.get("param_groups", [{}])
        beta1, beta2 = groups[0].get("betas", (0.9, 0.999))
        row["pose_consistency"] = _consistency(states.get(0, {}), beta1, beta2)
        row["intrinsics_consistency"] = _consistency(states.get(1, {}), beta1, beta2)
        row["train_loss"] = _nearest(losses, step)
        rows.append(row)
    return rows


__all__ = ["camera_path_point", "error_structure", "trace_run"]
