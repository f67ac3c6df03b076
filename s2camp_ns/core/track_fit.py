"""The cameras that agree best with a scene's SfM tracks: a camera-only bundle adjustment against fixed 3D points.

The track prior (``S2CampCameraOptimizer.apply_track_prior``) anchors each camera where its tracks put it, with the
tracks' own noise as its scale. For cameras straight out of SfM that is where they already are (SfM's bundle
adjustment left them there) and the noise is SfM's reprojection error. For cameras changed after SfM (perturbed,
edited, re-estimated elsewhere) the tracks still say where the camera is: anchoring at the given camera would hold
a wrong camera in place with the strength of a large reprojection error, which blocks recovery instead of guiding
it. This module finds the anchor.

Unknowns are the camera optimizer's own deltas (``core.camera.PARAMETER_NAMES``, paper sec. 4): the twist xi of each
image's pose, c2w' = c2w exp(xi) in its OpenCV camera frame, and the additive intrinsics deltas of each physical
camera (``camera_of_image``; per-image intrinsics are one camera per image). Only the ``free`` columns move. The
points stay fixed, so there is no gauge: the problem is a least-squares fit of reprojection residuals (paper eq. 2),
solved by Levenberg-Marquardt in float64. The normal equations are block-sparse (a 6x6 block per image, an m x m
block per physical camera and their coupling); eliminating the poses (Schur complement) leaves one m x m system per
physical camera, so the cost is linear in the number of images. Jacobians are exact (reverse-mode autodiff of the
projection, two backward passes: each observation depends on its own camera only).

The residuals are in pixels; a camera's translation deltas are in the units of the world the tracks live in. A
similarity of points and cameras (nerfstudio's normalization) leaves the rotation and intrinsics deltas unchanged and
scales the translation deltas by the similarity's scale (``TrackEvidence.world_scale``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from s2camp_ns.core.camera import NUM_CAMERA_PARAMS, Intrinsics, apply_pose_delta, project
from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS
from s2camp_ns.core.tracks import Tracks, per_image_rms

INTRINSICS_REFIT_LEVEL = 1e-3
"""Significance level at which the tracks must call for other intrinsics than the given ones before the anchor takes
them (``fit_anchor``): a fixed statistical level, the same for every scene."""
MIN_OBSERVATIONS = 10
"""Valid observations an image needs to be fitted: with fewer its six pose parameters are barely determined (three
points fit any pose exactly), so the RMS at the fit would say nothing of the noise and a prior of that scale would pin
the camera to an arbitrary pose. Such images keep their given camera and get no RMS (NaN: no prior)."""


@dataclass(frozen=True)
class TrackFit:
    """Result of ``fit_cameras_to_tracks``."""

    deltas: Float[Tensor, "n 16"]
    """Deltas (``PARAMETER_NAMES`` columns, float64) that move each given camera to its best agreement with the tracks;
    zero in the columns that were not free and in the pose of images with too few observations."""
    rms_px: Float[Tensor, " n"]
    """Reprojection RMS per image at the fit (pixels; NaN with fewer than ``MIN_OBSERVATIONS`` valid observations):
    the tracks' own noise."""
    rms_given_px: Float[Tensor, " n"]
    """Reprojection RMS per image of the given cameras, for comparison."""
    iterations: int
    """Levenberg-Marquardt iterations taken."""
    observations: Float[Tensor, " n"]
    """Valid observations per image at the fit (0 for an image that was not fitted)."""
    intrinsics_held: Bool[Tensor, " c"] | None = None
    """``fit_anchor`` only: per physical camera, True where the tracks do not call for other intrinsics than the given
    ones (``INTRINSICS_REFIT_LEVEL``), so the fit kept them and moved only the poses."""


def _free_mask(free: Bool[Tensor, " 16"] | tuple[int, ...]) -> Bool[Tensor, " 16"]:
    """The ``free`` argument of the fits as a mask over the ``PARAMETER_NAMES`` columns."""
    if isinstance(free, tuple):
        mask = torch.zeros(NUM_CAMERA_PARAMS, dtype=torch.bool)
        mask[list(free)] = True
        return mask
    if free.shape != (NUM_CAMERA_PARAMS,):
        raise ValueError(f"free must mask the {NUM_CAMERA_PARAMS} camera parameters, got shape {tuple(free.shape)}")
    return free.to(device="cpu", dtype=torch.bool)


def _residuals(
    deltas: Float[Tensor, "o 16"],
    points_cam: Float[Tensor, "o 1 3"],
    intrinsics: Intrinsics,
    pixels: Float[Tensor, "o 2"],
) -> tuple[Float[Tensor, "o 2"], Float[Tensor, " o"]]:
    """Projected minus observed pixel of each observation under its refined camera (``points_cam``: the point in the
    given camera's frame, moved by c2w' = c2w exp(xi) as in ``core.camera.project_with_delta``), and the validity
    margin."""
    projected, margin = project(
        apply_pose_delta(points_cam, deltas[:, :NUM_POSE_PARAMS]), intrinsics.with_delta(deltas)
    )
    return projected[:, 0] - pixels, margin[:, 0]


def fit_cameras_to_tracks(
    tracks: Tracks,
    c2w: Float[Tensor, "n 3 4"],
    intrinsics: Intrinsics,
    free: Bool[Tensor, " 16"] | tuple[int, ...],
    camera_of_image: Int[Tensor, " n"] | None = None,
    max_iterations: int = 50,
) -> TrackFit:
    """Levenberg-Marquardt fit of the ``free`` deltas of every camera to its tracks (module docstring).

    ``c2w``: OpenCV camera-to-world in the tracks' world; ``free``: a mask over, or the indices of, the 16
    ``PARAMETER_NAMES`` columns that move (pose columns per image, intrinsics columns per physical camera);
    ``camera_of_image``: physical camera 0..C-1 of each image (default: one per image). Runs in float64 on the CPU.
    """
    n = c2w.shape[0]
    tracks.validate(n)
    if intrinsics.num_cameras != n:
        raise ValueError(f"intrinsics must describe the {n} cameras of c2w, got {intrinsics.num_cameras}")
    mask = _free_mask(free)
    pose_columns = [j for j in range(NUM_POSE_PARAMS) if mask[j]]
    intrinsics_columns = [j for j in range(NUM_POSE_PARAMS, NUM_CAMERA_PARAMS) if mask[j]]
    groups = torch.arange(n) if camera_of_image is None else camera_of_image.to("cpu", torch.long)
    if groups.shape != (n,):
        raise ValueError(f"camera_of_image must hold one camera per image ({n}), got shape {tuple(groups.shape)}")
    num_groups = int(groups.max()) + 1 if n else 0

    c2w = c2w.detach().to("cpu", torch.float64)
    intrinsics = intrinsics.detach().to(device="cpu", dtype=torch.float64)
    image = tracks.image.to("cpu", torch.long)
    group = groups[image]
    points = tracks.points.detach().to("cpu", torch.float64)[tracks.point.to("cpu", torch.long)]
    pixels = tracks.pixels.detach().to("cpu", torch.float64)
    # Each observed point in its given camera's frame, R^T (x - c): fixed over the iterations.
    points_cam = (points - c2w[image, :, 3])[:, None, :] @ c2w[image, :, :3]
    intrinsics_obs = intrinsics[image]
    p, m = len(pose_columns), len(intrinsics_columns)
    pose = torch.zeros(n, p, dtype=torch.float64)
    intr = torch.zeros(num_groups, m, dtype=torch.float64)

    def full(pose_values: Tensor, intr_values: Tensor) -> Tensor:
        deltas = torch.zeros(image.shape[0], NUM_CAMERA_PARAMS, dtype=torch.float64)
        deltas[:, pose_columns] = pose_values[image]
        deltas[:, intrinsics_columns] = intr_values[group]
        return deltas

    def evaluate(pose_values: Tensor, intr_values: Tensor) -> tuple[Tensor, Tensor]:
        residual, margin = _residuals(full(pose_values, intr_values), points_cam, intrinsics_obs, pixels)
        return residual, (margin > 0).to(torch.float64) * fitted[image]

    def rms_of(residual: Tensor, weight: Tensor) -> Tensor:
        return per_image_rms(residual.square().sum(-1), weight, image, n)

    fitted = torch.ones(n, dtype=torch.float64)
    residual, weight = evaluate(pose, intr)
    rms_given = rms_of(residual, weight)
    valid = torch.zeros(n, dtype=torch.float64).index_add_(0, image, weight)
    fitted = (valid >= MIN_OBSERVATIONS).to(torch.float64)
    weight = weight * fitted[image]
    cost = float((residual.square().sum(-1) * weight).sum())
    damping, iterations = 1e-3, 0
    columns = pose_columns + intrinsics_columns
    while iterations < max_iterations:
        iterations += 1
        # Exact Jacobian: observation o's residual depends on its own row of deltas only, so the gradient of the sum
        # of the u (then v) residuals with respect to the [O, 16] rows is every observation's Jacobian row.
        base = full(pose, intr).requires_grad_(True)
        with torch.enable_grad():
            projected = _residuals(base, points_cam, intrinsics_obs, pixels)[0]
            rows = [torch.autograd.grad(projected[:, a].sum(), base, retain_graph=a == 0)[0] for a in range(2)]
        jacobian = torch.stack(rows, dim=1)[:, :, columns]
        jacobian = jacobian * weight[:, None, None]
        step_pose, step_intr = _solve_normal_equations(
            jacobian, residual * weight[:, None], image, group, groups, num_groups, p, m, damping
        )
        trial_pose, trial_intr = pose + step_pose, intr + step_intr
        trial_residual, trial_weight = evaluate(trial_pose, trial_intr)
        trial_cost = float((trial_residual.square().sum(-1) * trial_weight).sum())
        if trial_cost < cost:
            # Converged: the cost stopped falling, or the RMS is below 1e-10 px (beyond any meaning in pixels).
            converged = cost - trial_cost <= 1e-10 * cost or trial_cost <= 1e-20 * image.shape[0]
            pose, intr, residual, weight, cost = trial_pose, trial_intr, trial_residual, trial_weight, trial_cost
            damping = max(damping / 10.0, 1e-12)
            if converged:
                break
        else:
            damping *= 10.0
            if damping > 1e8:
                break
    deltas = torch.zeros(n, NUM_CAMERA_PARAMS, dtype=torch.float64)
    deltas[:, pose_columns] = pose
    deltas[:, intrinsics_columns] = intr[groups]
    observations = torch.zeros(n, dtype=torch.float64).index_add_(0, image, weight)
    return TrackFit(deltas, rms_of(residual, weight), rms_given, iterations, observations)


def fit_anchor(
    tracks: Tracks,
    c2w: Float[Tensor, "n 3 4"],
    intrinsics: Intrinsics,
    free: Bool[Tensor, " 16"] | tuple[int, ...],
    camera_of_image: Int[Tensor, " n"] | None = None,
) -> TrackFit:
    """The track prior's anchor: ``fit_cameras_to_tracks``, with each physical camera's intrinsics moved from the
    given ones only where the tracks call for it.

    Cameras straight out of SfM sit at the optimum of SfM's own camera model, in which some intrinsics were held
    (COLMAP's SIMPLE_RADIAL refines neither the principal point nor a second distortion term). Freeing those in a
    camera-only refit moves the focal length a little along with them, by noise: on the regime scene's SfM cameras
    (49 images, 16k observations) by 0.024 px, further from the truth, for a fall of the cost that six parameters
    fitted to noise explain. So the intrinsics are refitted (with the poses) and kept fixed (poses only), and the
    refit is the anchor of a physical camera only where its likelihood-ratio statistic, the fall of the cost over the
    refit's noise variance per residual, is beyond ``INTRINSICS_REFIT_LEVEL`` of a chi-square with one degree of
    freedom per free intrinsic (Wilks' theorem for nested least squares with Gaussian noise). Cameras changed after
    SfM (a perturbation, another tool's calibration) fail that test by orders of magnitude and get the refit.
    """
    full = fit_cameras_to_tracks(tracks, c2w, intrinsics, free, camera_of_image)
    mask = _free_mask(free)
    m = int(mask[NUM_POSE_PARAMS:].sum())
    n = c2w.shape[0]
    groups = torch.arange(n) if camera_of_image is None else camera_of_image.to("cpu", torch.long)
    num_groups = int(groups.max()) + 1 if n else 0
    if m == 0 or num_groups == 0:
        return full
    pose_mask = mask.clone()
    pose_mask[NUM_POSE_PARAMS:] = False
    held = fit_cameras_to_tracks(tracks, c2w, intrinsics, pose_mask, camera_of_image)

    def per_group(values: Tensor) -> Tensor:
        return torch.zeros(num_groups, dtype=torch.float64).index_add_(0, groups, values)

    def cost(fit: TrackFit) -> Tensor:
        return per_group(torch.nan_to_num(fit.rms_px).square() * fit.observations)

    p = int(mask[:NUM_POSE_PARAMS].sum())
    fitted_images = per_group((full.observations > 0).to(torch.float64))
    residuals = 2.0 * per_group(full.observations)
    dof = residuals - p * fitted_images - m
    cost_full, cost_held = cost(full), cost(held)
    fall = (cost_held - cost_full).clamp(min=0.0)
    variance = cost_full / dof.clamp(min=1.0)
    # Exact tracks leave no noise (variance 0): any fall of the cost is then evidence.
    statistic = torch.where(variance > 0, fall / variance.clamp(min=1e-300), torch.where(fall > 0, torch.inf, 0.0))
    p_value = torch.special.gammaincc(torch.full_like(statistic, m / 2.0), statistic / 2.0)
    held_groups = (p_value >= INTRINSICS_REFIT_LEVEL) | (dof <= 0)
    take_held = held_groups[groups]
    return TrackFit(
        deltas=torch.where(take_held[:, None], held.deltas, full.deltas),
        rms_px=torch.where(take_held, held.rms_px, full.rms_px),
        rms_given_px=full.rms_given_px,
        iterations=full.iterations + held.iterations,
        observations=torch.where(take_held, held.observations, full.observations),
        intrinsics_held=held_groups,
    )


def _solve_normal_equations(
    jacobian: Float[Tensor, "o 2 k"],
    residual: Float[Tensor, "o 2"],
    image: Int[Tensor, " o"],
    group: Int[Tensor, " o"],
    camera: Int[Tensor, " n"],
    num_groups: int,
    p: int,
    m: int,
    damping: float,
) -> tuple[Float[Tensor, "n p"], Float[Tensor, "c m"]]:
    """Levenberg-Marquardt step of the block-sparse normal equations: poses eliminated per image (Schur complement),
    one m x m system per physical camera (``camera``: each image's). Marquardt's scaling (damping times the
    diagonal) keeps the pixel, radian and scene units comparable; an image without observations gets a zero step."""
    num_images = camera.shape[0]
    j_pose, j_intr = jacobian[..., :p], jacobian[..., p:]
    a = torch.zeros(num_images, p, p, dtype=torch.float64).index_add_(0, image, j_pose.transpose(1, 2) @ j_pose)
    b = torch.zeros(num_images, p, m, dtype=torch.float64).index_add_(0, image, j_pose.transpose(1, 2) @ j_intr)
    d = torch.zeros(num_groups, m, m, dtype=torch.float64).index_add_(0, group, j_intr.transpose(1, 2) @ j_intr)
    g_pose = torch.zeros(num_images, p, dtype=torch.float64).index_add_(
        0, image, (j_pose.transpose(1, 2) @ residual[..., None])[..., 0]
    )
    g_intr = torch.zeros(num_groups, m, dtype=torch.float64).index_add_(
        0, group, (j_intr.transpose(1, 2) @ residual[..., None])[..., 0]
    )
    eye_p, eye_m = torch.eye(p, dtype=torch.float64), torch.eye(m, dtype=torch.float64)
    # An unobserved image's block is zero: the identity there gives it a zero step (its gradient is zero).
    a = a + damping * torch.diag_embed(torch.diagonal(a, dim1=1, dim2=2)) + 1e-12 * eye_p
    d = d + damping * torch.diag_embed(torch.diagonal(d, dim1=1, dim2=2)) + 1e-12 * eye_m
    a_inv_b = torch.linalg.solve(a, b)
    a_inv_g = torch.linalg.solve(a, g_pose[..., None])[..., 0]
    if m:
        schur = d - torch.zeros_like(d).index_add_(0, camera, b.transpose(1, 2) @ a_inv_b)
        rhs = g_intr - torch.zeros_like(g_intr).index_add_(0, camera, (b.transpose(1, 2) @ a_inv_g[..., None])[..., 0])
        step_intr = -torch.linalg.solve(schur, rhs[..., None])[..., 0]
    else:
        step_intr = g_intr.new_zeros(num_groups, 0)
    # A dp + B dc = -g_pose  =>  dp = -(A^-1 g_pose + A^-1 B dc)
    step_pose = -(a_inv_g + (a_inv_b @ step_intr[camera][..., None])[..., 0])
    return step_pose, step_intr


@dataclass(frozen=True)
class TrackEvidence:
    """A scene's tracks with the given cameras in the tracks' world: what ``fit_cameras_to_tracks`` needs, and the
    scale that takes its translation deltas to the training frame."""

    tracks: Tracks
    c2w: Float[Tensor, "n 3 4"]
    """The training cameras as given (after any perturbation), OpenCV camera-to-world in the tracks' world."""
    world_scale: float
    """Training-frame units per unit of the tracks' world (nerfstudio's ``dataparser_scale``)."""


__all__ = ["INTRINSICS_REFIT_LEVEL", "TrackEvidence", "TrackFit", "fit_anchor", "fit_cameras_to_tracks"]
