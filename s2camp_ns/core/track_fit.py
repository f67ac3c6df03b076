"""Robust camera-only bundle adjustment against fixed 3D points: where a scene's SfM tracks put each image.

The track prior (``S2CampCameraOptimizer.apply_track_prior``) anchors each image there. Unknowns are the camera
optimizer's deltas (``core.camera.PARAMETER_NAMES``, paper sec. 4): each image's twist xi, c2w' = c2w exp(xi) in its
OpenCV camera frame, and each physical camera's additive intrinsics deltas (``camera_of_image``); only the ``free``
columns move. The points are fixed (no gauge). Each valid observation (paper eq. 2) costs rho(s) = c^2 log(1 + s / c^2)
of its squared reprojection distance s (px^2), Ceres' Cauchy loss with c = ``LOSS_SCALE_PX``. Levenberg-Marquardt
in float64 minimizes it by iteratively reweighted least squares (weights rho'(s) = 1 / (1 + s / c^2) at the current
residuals; a step is taken only where it lowers the robust cost). Eliminating the poses from the block-sparse normal
equations (Schur complement) leaves one m x m system per camera. Jacobians are exact (autodiff).

Residuals are in pixels, translation deltas in the tracks' world units: a similarity of the world scales the
translation deltas by its scale (``TrackEvidence.world_scale``) and leaves the others unchanged.
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
"""Significance level at which the tracks must call for other intrinsics than the given ones (``fit_anchor``)."""
MIN_OBSERVATIONS = 10
"""Valid observations an image needs to be fitted (fewer barely determine its pose); others keep their given pose
and get RMS NaN (no prior)."""
LOSS_SCALE_PX = 1.0
"""Scale c (px) of the Cauchy loss: residuals well within c count as in least squares, those beyond it about
logarithmically. The bundle adjustments that place the tracks' points use the same loss
(``s2camp_ns.tracks.robust_adjustment.cauchy_adjustment_options``)."""
_MAX_ITERATIONS = 50


@dataclass(frozen=True)
class TrackFit:
    """Result of ``fit_cameras_to_tracks``."""

    deltas: Float[Tensor, "n 16"]
    """Deltas (``PARAMETER_NAMES`` columns, float64) at the minimum of the robust cost; zero in the columns not free
    and in the pose of images with too few observations."""
    rms_px: Float[Tensor, " n"]
    """Plain reprojection RMS (px) per image at the fit, outliers included; NaN below ``MIN_OBSERVATIONS``."""
    rms_given_px: Float[Tensor, " n"]
    """Plain reprojection RMS per image as given (``core.tracks.track_reprojection_rms``)."""
    iterations: int
    """Levenberg-Marquardt iterations taken."""
    observations: Float[Tensor, " n"]
    """Valid observations per image at the fit (0 for an image that was not fitted)."""
    intrinsics_held: Bool[Tensor, " c"] | None = None
    """``fit_anchor`` only: per physical camera, True where the fit kept the given intrinsics (poses only)."""
    squared_px2: Float[Tensor, " o"] | None = None
    """``fit_cameras_to_tracks`` only: each observation's squared residual (px^2) at the fit."""
    valid: Float[Tensor, " o"] | None = None
    """``fit_cameras_to_tracks`` only: 1 where an observation counts at the fit (in front, its image fitted), else 0."""


def cauchy_loss(squared: Float[Tensor, " o"]) -> Float[Tensor, " o"]:
    """rho(s) = c^2 log(1 + s / c^2) of squared pixel distances s, c = ``LOSS_SCALE_PX`` (Ceres' ``CauchyLoss``)."""
    c2 = LOSS_SCALE_PX**2
    return c2 * torch.log1p(squared / c2)


def cauchy_weight(squared: Float[Tensor, " o"]) -> Float[Tensor, " o"]:
    """rho'(s) = 1 / (1 + s / c^2), the reweighting; for this loss rho'(s) + s rho''(s) = rho'(s)^2."""
    return 1.0 / (1.0 + squared / LOSS_SCALE_PX**2)


def _free_mask(free: Bool[Tensor, " 16"] | tuple[int, ...]) -> Bool[Tensor, " 16"]:
    """The ``free`` argument of the fits as a mask over the ``PARAMETER_NAMES`` columns."""
    if isinstance(free, tuple):
        mask = torch.zeros(NUM_CAMERA_PARAMS, dtype=torch.bool)
        mask[list(free)] = True
        return mask
    if free.shape != (NUM_CAMERA_PARAMS,):
        raise ValueError(f"free must mask the {NUM_CAMERA_PARAMS} camera parameters, got shape {tuple(free.shape)}")
    return free.to(device="cpu", dtype=torch.bool)


def reprojection_residuals(
    deltas: Float[Tensor, "o 16"],
    points_cam: Float[Tensor, "o 1 3"],
    intrinsics: Intrinsics,
    pixels: Float[Tensor, "o 2"],
) -> tuple[Float[Tensor, "o 2"], Float[Tensor, " o"]]:
    """Projected minus observed pixels under the deltas (``points_cam``: given camera frame), and validity margins."""
    projected, margin = project(
        apply_pose_delta(points_cam, deltas[:, :NUM_POSE_PARAMS]), intrinsics.with_delta(deltas)
    )
    return projected[:, 0] - pixels, margin[:, 0]


def points_in_given_cameras(tracks: Tracks, c2w: Float[Tensor, "n 3 4"]) -> Float[Tensor, "o 1 3"]:
    """Each observation's point in its image's given camera frame, R^T (x - c) (float64, CPU)."""
    c2w = c2w.detach().to("cpu", torch.float64)
    image = tracks.image.to("cpu", torch.long)
    points = tracks.points.detach().to("cpu", torch.float64)[tracks.point.to("cpu", torch.long)]
    return (points - c2w[image, :, 3])[:, None, :] @ c2w[image, :, :3]


@dataclass(frozen=True)
class _Problem:
    """The fixed data of a fit, one row per observation (float64, CPU), and the free columns."""

    image: Int[Tensor, " o"]
    group: Int[Tensor, " o"]  # physical camera of each observation
    groups: Int[Tensor, " n"]  # physical camera of each image
    num_groups: int
    points_cam: Float[Tensor, "o 1 3"]  # R^T (x - c) in the given camera frame
    intrinsics: Intrinsics
    pixels: Float[Tensor, "o 2"]
    pose_columns: list[int]
    intrinsics_columns: list[int]

    def deltas(self, pose: Float[Tensor, "n p"], intr: Float[Tensor, "c m"]) -> Float[Tensor, "o 16"]:
        deltas = torch.zeros(self.image.shape[0], NUM_CAMERA_PARAMS, dtype=torch.float64)
        deltas[:, self.pose_columns] = pose[self.image]
        deltas[:, self.intrinsics_columns] = intr[self.group]
        return deltas

    def residuals(
        self, pose: Float[Tensor, "n p"], intr: Float[Tensor, "c m"]
    ) -> tuple[Float[Tensor, "o 2"], Float[Tensor, " o"]]:
        """Residuals (px) and validity (1: in front of the camera / inside a fisheye's range, 0: not)."""
        residual, margin = reprojection_residuals(
            self.deltas(pose, intr), self.points_cam, self.intrinsics, self.pixels
        )
        return residual, (margin > 0).to(torch.float64)

    def jacobian(self, pose: Float[Tensor, "n p"], intr: Float[Tensor, "c m"]) -> Float[Tensor, "o 2 k"]:
        """Exact Jacobian of each residual over the free columns (pose first): observation o depends on its own row of
        deltas only, so the gradient of the summed u (then v) residuals over the [O, 16] rows is every Jacobian row."""
        base = self.deltas(pose, intr).requires_grad_(True)
        with torch.enable_grad():
            projected = reprojection_residuals(base, self.points_cam, self.intrinsics, self.pixels)[0]
            rows = [torch.autograd.grad(projected[:, a].sum(), base, retain_graph=a == 0)[0] for a in range(2)]
        return torch.stack(rows, dim=1)[:, :, self.pose_columns + self.intrinsics_columns]


def _problem(
    tracks: Tracks,
    c2w: Float[Tensor, "n 3 4"],
    intrinsics: Intrinsics,
    free: Bool[Tensor, " 16"] | tuple[int, ...],
    camera_of_image: Int[Tensor, " n"] | None,
) -> _Problem:
    """The arguments of ``fit_cameras_to_tracks``, checked, as a ``_Problem``."""
    n = c2w.shape[0]
    tracks.validate(n)
    if intrinsics.num_cameras != n:
        raise ValueError(f"intrinsics must describe the {n} cameras of c2w, got {intrinsics.num_cameras}")
    mask = _free_mask(free)
    groups = torch.arange(n) if camera_of_image is None else camera_of_image.to("cpu", torch.long)
    if groups.shape != (n,):
        raise ValueError(f"camera_of_image must hold one camera per image ({n}), got shape {tuple(groups.shape)}")
    image = tracks.image.to("cpu", torch.long)
    return _Problem(
        image=image,
        group=groups[image],
        groups=groups,
        num_groups=int(groups.max()) + 1 if n else 0,
        points_cam=points_in_given_cameras(tracks, c2w),
        intrinsics=intrinsics.detach().to(device="cpu", dtype=torch.float64)[image],
        pixels=tracks.pixels.detach().to("cpu", torch.float64),
        pose_columns=[j for j in range(NUM_POSE_PARAMS) if mask[j]],
        intrinsics_columns=[j for j in range(NUM_POSE_PARAMS, NUM_CAMERA_PARAMS) if mask[j]],
    )


def _levenberg_marquardt(
    problem: _Problem, fitted: Float[Tensor, " n"], max_iterations: int
) -> tuple[Float[Tensor, "n p"], Float[Tensor, "c m"], Float[Tensor, "o 2"], Float[Tensor, " o"], int]:
    """Robust Levenberg-Marquardt from zero deltas of the images with ``fitted`` 1: pose and intrinsics deltas,
    residuals and validity (0 for images not fitted) there, and the iterations."""
    n, p, m = fitted.shape[0], len(problem.pose_columns), len(problem.intrinsics_columns)

    def evaluate(pose: Tensor, intr: Tensor) -> tuple[Tensor, Tensor, float]:
        residual, valid = problem.residuals(pose, intr)
        valid = valid * fitted[problem.image]
        return residual, valid, float((cauchy_loss(residual.square().sum(-1)) * valid).sum())

    pose = torch.zeros(n, p, dtype=torch.float64)
    intr = torch.zeros(problem.num_groups, m, dtype=torch.float64)
    residual, valid, cost = evaluate(pose, intr)
    damping, iterations = 1e-3, 0
    while iterations < max_iterations:
        iterations += 1
        # Reweighted least squares: rows scaled by sqrt(rho'(s)) at the current residuals (0 where invalid).
        root = (valid * cauchy_weight(residual.square().sum(-1))).sqrt()
        step_pose, step_intr = _solve_normal_equations(
            problem.jacobian(pose, intr) * root[:, None, None],
            residual * root[:, None],
            problem.image,
            problem.group,
            problem.groups,
            problem.num_groups,
            p,
            m,
            damping,
        )
        trial_pose, trial_intr = pose + step_pose, intr + step_intr
        trial_residual, trial_valid, trial_cost = evaluate(trial_pose, trial_intr)
        if trial_cost < cost:
            # Converged: the cost stopped falling (to about its rounding; reweighting converges linearly), or the
            # RMS is below 1e-10 px.
            converged = cost - trial_cost <= 1e-14 * cost or trial_cost <= 1e-20 * problem.image.shape[0]
            pose, intr, residual, valid, cost = trial_pose, trial_intr, trial_residual, trial_valid, trial_cost
            damping = max(damping / 10.0, 1e-12)
            if converged:
                break
        else:
            damping *= 10.0
            if damping > 1e8:
                break
    return pose, intr, residual, valid, iterations


def fit_cameras_to_tracks(
    tracks: Tracks,
    c2w: Float[Tensor, "n 3 4"],
    intrinsics: Intrinsics,
    free: Bool[Tensor, " 16"] | tuple[int, ...],
    camera_of_image: Int[Tensor, " n"] | None = None,
    max_iterations: int = _MAX_ITERATIONS,
) -> TrackFit:
    """Robust fit of the ``free`` deltas to the tracks (module docstring), float64 on the CPU. ``c2w``: OpenCV
    camera-to-world in the tracks' world; ``free``: mask or indices of the 16 ``PARAMETER_NAMES`` columns that move;
    ``camera_of_image``: physical camera 0..C-1 of each image (default: one per image)."""
    problem = _problem(tracks, c2w, intrinsics, free, camera_of_image)
    n, image = c2w.shape[0], problem.image
    no_pose = torch.zeros(n, len(problem.pose_columns), dtype=torch.float64)
    no_intr = torch.zeros(problem.num_groups, len(problem.intrinsics_columns), dtype=torch.float64)
    residual, valid = problem.residuals(no_pose, no_intr)
    rms_given = per_image_rms(residual.square().sum(-1), valid, image, n)
    count = torch.zeros(n, dtype=torch.float64).index_add_(0, image, valid)
    fitted = (count >= MIN_OBSERVATIONS).to(torch.float64)
    pose, intr, residual, valid, iterations = _levenberg_marquardt(problem, fitted, max_iterations)
    deltas = torch.zeros(n, NUM_CAMERA_PARAMS, dtype=torch.float64)
    deltas[:, problem.pose_columns] = pose
    deltas[:, problem.intrinsics_columns] = intr[problem.groups]
    squared = residual.square().sum(-1)
    observations = torch.zeros(n, dtype=torch.float64).index_add_(0, image, valid)
    rms = per_image_rms(squared, valid, image, n)
    return TrackFit(deltas, rms, rms_given, iterations, observations, squared_px2=squared, valid=valid)


def fit_anchor(
    tracks: Tracks,
    c2w: Float[Tensor, "n 3 4"],
    intrinsics: Intrinsics,
    free: Bool[Tensor, " 16"] | tuple[int, ...],
    camera_of_image: Int[Tensor, " n"] | None = None,
) -> TrackFit:
    """The track prior's anchor: ``fit_cameras_to_tracks`` with the intrinsics free (refit) and held (poses only);
    a physical camera takes the refit only where the fall of the robust cost from the held fit is significant at
    ``INTRINSICS_REFIT_LEVEL`` (freeing intrinsics SfM held moves the focal length by noise).

    The test is Schrader and Hettmansperger's robust likelihood ratio (drop in dispersion; exact points, independent
    isotropic pixel errors of one distribution): under the given intrinsics the fall is asymptotically lambda chi2_m
    (m free intrinsics), lambda = E[s rho'(s)^2] / (2 E[rho'(s) + s rho''(s)]) (s: squared residual), estimated per
    camera from the refit's residuals with the factor N / dof (N valid observations, dof residuals less fitted
    parameters); with rho(s) = s it is the unbiased noise variance per axis and the test is Wilks'.
    """
    full = fit_cameras_to_tracks(tracks, c2w, intrinsics, free, camera_of_image)
    full_squared, full_valid = full.squared_px2, full.valid
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
    held_squared, held_valid = held.squared_px2, held.valid
    group = groups[tracks.image.to("cpu", torch.long)]

    def per_group(values: Tensor, index: Tensor = group) -> Tensor:
        return torch.zeros(num_groups, dtype=torch.float64).index_add_(0, index, values)

    p = int(mask[:NUM_POSE_PARAMS].sum())
    count = per_group(full.observations, groups)
    dof = 2.0 * count - p * per_group((full.observations > 0).to(torch.float64), groups) - m
    fall = per_group(cauchy_loss(held_squared) * held_valid) - per_group(cauchy_loss(full_squared) * full_valid)
    fall = fall.clamp(min=0.0)
    # lambda's sample estimate; for the Cauchy loss rho' + s rho'' = rho'^2.
    weight_squared = cauchy_weight(full_squared).square() * full_valid
    spread, curvature = per_group(full_squared * weight_squared), per_group(weight_squared)
    scale = count * spread / (curvature.clamp(min=1e-300) * dof.clamp(min=1.0))
    # Exact tracks leave no noise (scale 0): any fall of the cost is then evidence.
    statistic = torch.where(scale > 0, fall / scale.clamp(min=1e-300), torch.where(fall > 0, torch.inf, 0.0))
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
    """Damped step of the normal equations, poses eliminated per image (Schur complement), one m x m system per
    physical camera (``camera``: each image's); an image without observations gets a zero step."""
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
    """A scene's tracks, the given cameras in the tracks' world, and the scale to the training frame."""

    tracks: Tracks
    c2w: Float[Tensor, "n 3 4"]
    """The training images' poses as given (after any perturbation), OpenCV camera-to-world, tracks' world."""
    world_scale: float
    """Training-frame units per unit of the tracks' world (nerfstudio's ``dataparser_scale``)."""


__all__ = [
    "INTRINSICS_REFIT_LEVEL",
    "LOSS_SCALE_PX",
    "TrackEvidence",
    "TrackFit",
    "cauchy_loss",
    "cauchy_weight",
    "fit_anchor",
    "fit_cameras_to_tracks",
    "points_in_given_cameras",
    "reprojection_residuals",
]
