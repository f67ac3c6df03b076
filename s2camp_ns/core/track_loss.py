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
- The 3D points are fixed in the tracks' world. The refiner's deltas are in the training frame: rotation and
  intrinsics deltas are the same in both, the translation deltas are divided by ``world_scale`` (training-frame units
  per unit of the tracks' world, ``core.track_fit.TrackEvidence``).

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
from s2camp_ns.core.track_fit import TrackEvidence, cauchy_loss, points_in_given_cameras, reprojection_residuals

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


def noise_variance(squared: Float[Tensor, " o"]) -> float:
    """sigma_t^2 per axis from squared 2D residuals s (px^2): median(s) / (2 ln 2), robust to gross mismatches; a
    floor of 1e-6 px^2 keeps exact tracks finite."""
    if squared.numel() == 0:
        raise ValueError("the track loss needs at least one valid track observation, got none")
    return max(float(squared.median()) / CHI2_2_MEDIAN, 1e-6)


def track_term(evidence: TrackEvidence, intrinsics: Intrinsics, anchor: Float[Tensor, "n 16"]) -> TrackTerm:
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
    return TrackTerm(
        image=image[valid],
        points_cam=points_cam[valid],
        pixels=pixels[valid],
        world_scale=float(evidence.world_scale),
        noise_variance=noise_variance(squared[valid]),
        num_pixels=int((intrinsics.width * intrinsics.height).sum()),
    )


def _squared_residuals(
    deltas: Float[Tensor, "o 16"], points_cam: Float[Tensor, "o 1 3"], intrinsics: Intrinsics, pixels: Tensor
) -> tuple[Float[Tensor, " o"], Tensor]:
    """Squared pixel distance of each observation under its deltas (tracks' world) and whether it is valid (in
    front of the camera, inside a fisheye's range): ``core.track_fit.reprojection_residuals``."""
    residual, margin = reprojection_residuals(deltas, points_cam, intrinsics, pixels)  # [o, 2], [o]
    return residual.square().sum(dim=-1), margin > 0


def track_cost(term: TrackTerm, deltas: Float[Tensor, "n 16"], intrinsics: Intrinsics) -> Float[Tensor, ""]:
    """sum_obs rho(s_o) (eq. 1's sum, px^2) at the training-frame ``deltas`` of every image, differentiable;
    ``intrinsics`` the base intrinsics of every image. Observations that fall behind their camera count zero."""
    if deltas.shape[-1] != NUM_CAMERA_PARAMS:
        raise ValueError(f"deltas must hold the {NUM_CAMERA_PARAMS} camera parameters, got {deltas.shape[-1]}")
    device = deltas.device
    image = term.image.to(device)
    scale = torch.ones(NUM_CAMERA_PARAMS, dtype=deltas.dtype, device=device)
    scale[:3] = 1.0 / term.world_scale  # translation: training frame -> tracks' world
    per_observation = (deltas * scale)[image]  # [o, 16]
    base = intrinsics.to(device=device, dtype=deltas.dtype)[image]
    squared, valid = _squared_residuals(
        per_observation, term.points_cam.to(device, deltas.dtype), base, term.pixels.to(device, deltas.dtype)
    )
    return torch.where(valid, cauchy_loss(squared), torch.zeros_like(squared)).sum()


def photometric_weight(mse: Tensor, num_pixels: int, noise_variance: float) -> Tensor:
    """w of eq. (1): sigma_c^2 / (3 N sigma_t^2) with sigma_c^2 the field's mean squared error ``mse`` (per channel)
    over N training pixels."""
    return mse / (3.0 * num_pixels * noise_variance)


__all__ = ["CHI2_2_MEDIAN", "TrackTerm", "noise_variance", "photometric_weight", "track_cost", "track_term"]
