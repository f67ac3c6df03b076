"""The tracks as a loss term beside the photometric loss: a benchmark candidate for fusing the two evidences.

Model. Each training pixel's colour is observed with independent Gaussian noise of variance sigma_c^2 per channel; each
track observation's pixel with independent noise of variance sigma_t^2 per axis, gross mismatches aside, which the
Cauchy cost of ``core.track_fit`` bounds (rho(s) = c^2 log(1 + s / c^2) of the squared distance s, equal to s for
small s). The negative log-likelihood of both, up to constants,

    NLL = sum_pixels |c - c_hat|^2 / (2 sigma_c^2) + sum_obs rho(s_o) / (2 sigma_t^2),

divided by the photometric term's factor 3 N / (2 sigma_c^2) (N training pixels, 3 channels; nerfacto's rgb loss is
the mean over a batch's rays and channels, an unbiased estimate of the mean over all pixels), is

    L = L_rgb + w sum_obs rho(s_o),     w = sigma_c^2 / (3 N sigma_t^2)                                    (1)

whose minimum over the cameras is their most probable value under both evidences: the photometric gradient and the
tracks' pull cancel there, each weighed by its information, along every direction separately (the tracks' J^T J /
sigma_t^2, not a radius). Adam's normalization changes the path to that point, not the point: its steps vanish where
the summed gradient does.

- sigma_t^2 is estimated from the residuals at the anchor (``core.track_fit``), robustly: the median of s over
  2 ln 2, the median of a chi-square with two degrees of freedom (``noise_variance``).
- sigma_c^2 is the field's own mean squared error, a running mean of L_rgb (``photometric_weight``'s caller): while
  the field fits the images poorly, their weight is small, and it grows as the fit improves, so early field errors
  (which bias the camera gradient) count for less.
- The 3D points are fixed in the tracks' world, or free (``points_free``): a joint photometric and geometric
  adjustment. Free points are not parameters of the optimizer: every step moves each point by one robust Gauss-Newton
  step towards its optimum at the current cameras (``refine_points``), so the cameras' gradient is that of the cost
  with the points eliminated (the reduced cost's gradient equals the partial one at the points' optimum). With fixed
  points the tracks pin every camera as resection does, including the directions the bundle adjustment that made the
  points could not fix (a rotation all cameras share about their centres, focal length against depth); with free points
  the tracks pin only what they determine jointly, and the images decide the rest.
- The refiner's deltas are in the training frame: rotation and intrinsics deltas are the same in both, the translation
  deltas are divided by ``world_scale`` (training-frame units per unit of the tracks' world,
  ``core.track_fit.TrackEvidence``).
- splatfacto's loss is mostly L1 (its ``main_loss``), whose likelihood is Laplace with scale b, the mean absolute
  error: the same division gives w = b / (6 N sigma_t^2), half eq. (1)'s with b for sigma_c^2 (the camera optimizer's
  ``get_loss_dict``).

Independent pixel noise overstates the images' information: the field's errors are correlated over neighbouring
pixels and views. The benchmark measures whether the weight of eq. (1) helps or hurts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from s2camp_ns.core.camera import NUM_CAMERA_PARAMS, Intrinsics
from s2camp_ns.core.track_fit import (
    TrackEvidence,
    cauchy_loss,
    cauchy_weight,
    points_in_given_cameras,
    reprojection_residuals,
)

CHI2_2_MEDIAN = 2.0 * math.log(2.0)
"""Median of a chi-square with two degrees of freedom: s / sigma_t^2 of a 2D observation with isotropic noise."""


@dataclass(frozen=True)
class TrackTerm:
    """The fixed data of the track loss, one row per valid observation."""

    image: Int[Tensor, " o"]
    """Observing training image."""
    points_cam: Float[Tensor, "o 1 3"]
    """The observed point in its given camera's frame, R^T (x - c), in the tracks' world units."""
    pixels: Float[Tensor, "o 2"]
    """Observed pixel (u, v), the intrinsics' pixel convention."""
    world_scale: float
    """Training-frame units per unit of the tracks' world."""
    noise_variance: float
    """sigma_t^2: the observations' noise variance per axis (px^2)."""
    num_pixels: int
    """N of eq. (1): the training pixels, all images at their intrinsics' size."""
    point: Int[Tensor, " o"] | None = None
    """Points free (candidate): the observed point (row of ``points``); None: the points are fixed."""
    points: Float[Tensor, "p 3"] | None = None
    """Points free: their starting positions in the tracks' world."""
    rotation: Float[Tensor, "o 3 3"] | None = None
    """Points free: the observing given camera's rotation R (camera to world)."""
    center: Float[Tensor, "o 3"] | None = None
    """Points free: the observing given camera's centre c, tracks' world."""


def noise_variance(squared: Float[Tensor, " o"]) -> float:
    """sigma_t^2 per axis from squared 2D residuals s (px^2): median(s) / (2 ln 2), robust to gross mismatches; a
    floor of 1e-6 px^2 keeps exact tracks finite."""
    if squared.numel() == 0:
        raise ValueError("the track loss needs at least one valid track observation, got none")
    return max(float(squared.median()) / CHI2_2_MEDIAN, 1e-6)


def track_term(
    evidence: TrackEvidence, intrinsics: Intrinsics, anchor: Float[Tensor, "n 16"], points_free: bool = False
) -> TrackTerm:
    """The track loss's data: ``evidence``'s observations in their given cameras' frames, keeping those in front of
    the camera, and sigma_t^2 from their residuals under the ``anchor`` deltas (tracks' world, as
    ``core.track_fit.fit_anchor`` returns them)."""
    tracks, c2w = evidence.tracks, evidence.c2w
    tracks.validate(c2w.shape[0])
    image = tracks.image.to("cpu", torch.long)
    points_cam = points_in_given_cameras(tracks, c2w)  # [o, 1, 3]
    pixels = tracks.pixels.detach().to("cpu", torch.float64)
    intrinsics = intrinsics.detach().to(device="cpu", dtype=torch.float64)
    squared, valid = _squared_residuals(anchor.to("cpu", torch.float64)[image], points_cam, intrinsics[image], pixels)
    free = {}
    if points_free:
        c2w = c2w.detach().to("cpu", torch.float64)
        point = tracks.point.to("cpu", torch.long)[valid]
        used, point = torch.unique(point, return_inverse=True)
        free = {
            "point": point,
            "points": tracks.points.detach().to("cpu", torch.float64)[used],
            "rotation": c2w[image[valid], :, :3],
            "center": c2w[image[valid], :, 3],
        }
    return TrackTerm(
        image=image[valid],
        points_cam=points_cam[valid],
        pixels=pixels[valid],
        world_scale=float(evidence.world_scale),
        noise_variance=noise_variance(squared[valid]),
        num_pixels=int((intrinsics.width * intrinsics.height).sum()),
        **free,
    )


def points_cam_of(term: TrackTerm, points: Float[Tensor, "p 3"]) -> Float[Tensor, "o 1 3"]:
    """Points free: each observation's point in its given camera's frame, R^T (x - c)."""
    return _in_given_frames(term, points[term.point])


def _in_given_frames(term: TrackTerm, observed: Float[Tensor, "o 3"]) -> Float[Tensor, "o 1 3"]:
    """Points free: each observation's own copy of its point, ``observed``, in its given camera's frame."""
    return (observed - term.center)[:, None, :] @ term.rotation


def _tracks_world(term: TrackTerm, deltas: Float[Tensor, "n 16"]) -> Float[Tensor, "o 16"]:
    """Each observation's training-frame deltas in the tracks' world (translation divided by ``world_scale``)."""
    scale = torch.ones(NUM_CAMERA_PARAMS, dtype=deltas.dtype, device=deltas.device)
    scale[:3] = 1.0 / term.world_scale
    return (deltas * scale)[term.image.to(deltas.device)]


@torch.no_grad()
def refine_points(
    term: TrackTerm, points: Float[Tensor, "p 3"], deltas: Float[Tensor, "n 16"], intrinsics: Intrinsics
) -> Float[Tensor, "p 3"]:
    """Points free: one robust Gauss-Newton step of every point against its observations at the cameras' current
    training-frame ``deltas`` (float64; Cauchy weights rho'(s) as in ``core.track_fit``; a point's 3 x 3 normal
    equations damped by 1e-3 of their diagonal). Stepping the points to their optimum each step makes the cameras'
    gradient of ``track_cost`` that of the cost with the points eliminated (the envelope theorem): the joint
    adjustment's camera information, soft directions included, instead of resection against fixed points."""
    per_observation = _tracks_world(term, deltas.detach().to(torch.float64))
    base = intrinsics.to(device=points.device, dtype=torch.float64)[term.image]
    pixels = term.pixels.to(torch.float64)
    with torch.enable_grad():
        x = points[term.point].clone().requires_grad_(True)  # [o, 3]
        residual, margin = reprojection_residuals(per_observation, _in_given_frames(term, x), base, pixels)
        rows = [torch.autograd.grad(residual[:, k].sum(), x, retain_graph=k == 0)[0] for k in range(2)]
    jac = torch.stack(rows, dim=1)  # [o, 2, 3]
    residual = residual.detach()
    weight = torch.where(margin > 0, cauchy_weight(residual.square().sum(-1)), 0.0)  # [o]
    wj = weight[:, None, None] * jac
    hessian = torch.zeros(points.shape[0], 3, 3, dtype=torch.float64, device=points.device)
    gradient = torch.zeros(points.shape[0], 3, dtype=torch.float64, device=points.device)
    hessian.index_add_(0, term.point, wj.transpose(1, 2) @ jac)
    gradient.index_add_(0, term.point, (wj.transpose(1, 2) @ residual[:, :, None])[:, :, 0])
    diag = torch.diagonal(hessian, dim1=1, dim2=2)
    damped = hessian + torch.diag_embed(1e-3 * diag + 1e-12)
    # A point seen by fewer than two valid observations is left where it is (its normal equations are singular).
    seen = torch.zeros(points.shape[0], dtype=torch.float64, device=points.device)
    seen.index_add_(0, term.point, (weight > 0).to(torch.float64))
    step = torch.linalg.solve(damped, -gradient[:, :, None])[:, :, 0]
    return points + torch.where((seen >= 2)[:, None], step, torch.zeros_like(step))


def _squared_residuals(
    deltas: Float[Tensor, "o 16"], points_cam: Float[Tensor, "o 1 3"], intrinsics: Intrinsics, pixels: Tensor
) -> tuple[Float[Tensor, " o"], Tensor]:
    """Squared pixel distance of each observation under its deltas (tracks' world) and whether it is valid (in
    front of the camera, inside a fisheye's range): ``core.track_fit.reprojection_residuals``."""
    residual, margin = reprojection_residuals(deltas, points_cam, intrinsics, pixels)  # [o, 2], [o]
    return residual.square().sum(dim=-1), margin > 0


def track_cost(
    term: TrackTerm, deltas: Float[Tensor, "n 16"], intrinsics: Intrinsics, points: Tensor | None = None
) -> Float[Tensor, ""]:
    """sum_obs rho(s_o) (eq. 1's sum, px^2) at the training-frame ``deltas`` of every image, differentiable;
    ``intrinsics`` the base intrinsics of every image; ``points`` the free points' current positions (held fixed in
    the derivative). Observations that fall behind their camera count zero."""
    if deltas.shape[-1] != NUM_CAMERA_PARAMS:
        raise ValueError(f"deltas must hold the {NUM_CAMERA_PARAMS} camera parameters, got {deltas.shape[-1]}")
    device = deltas.device
    per_observation = _tracks_world(term, deltas)  # [o, 16]
    base = intrinsics.to(device=device, dtype=deltas.dtype)[term.image.to(device)]
    points_cam = term.points_cam if points is None else points_cam_of(term, points.detach())
    squared, valid = _squared_residuals(
        per_observation, points_cam.to(device, deltas.dtype), base, term.pixels.to(device, deltas.dtype)
    )
    return torch.where(valid, cauchy_loss(squared), torch.zeros_like(squared)).sum()


def photometric_weight(mse: Tensor, num_pixels: int, noise_variance: float) -> Tensor:
    """w of eq. (1): sigma_c^2 / (3 N sigma_t^2) with sigma_c^2 the field's mean squared error ``mse`` (per channel)
    over N training pixels."""
    return mse / (3.0 * num_pixels * noise_variance)


__all__ = [
    "CHI2_2_MEDIAN", "TrackTerm", "noise_variance", "photometric_weight", "points_cam_of", "refine_points",
    "track_cost", "track_term",
]  # fmt: skip
