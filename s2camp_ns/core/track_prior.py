"""The track prior: a Gaussian on the whitened latent about each image's SfM track anchor, and its proximal step.

The anchor a is the deltas phi where the tracks put the image (``core.track_fit.fit_anchor``; zero, the given camera,
without a fit), a_hat = P a in the whitened latent (paper eq. 15); every image with tracks starts there
(``place_at_anchor``). Radii are in whitened units, pixels over max(W, H) (the Gram matrix's unit, paper eq. 5), in
which |phi_hat - a_hat| is the RMS displacement of the proxy points (paper eqs. 5, 20).

Radius. A unit whitened step moves an image's proxy points by an RMS of one, so each of its O observations by about
one; with noise of RMS r (r^2 / 2 per axis) they fix each whitened coordinate to the standard error r / sqrt(2 O).
Image i's pose gets r_i / (2 O_i)^(e/2) (``pose_radius``; r_i its reprojection RMS at the anchor, O_i its
observations, e = ``pose_prior_exponent``): the standard error at e = 1, r_i itself at e = 0. A physical camera's
shared intrinsics get the pooled fit's standard error sqrt(sum_i O_i r_i^2) / (sqrt(2) sum_i O_i)
(``pooled_intrinsics_radius``). Without counts each image counts once. The radius averages over directions: the
tracks' points are not spread like the proxy points.

Step. With Adam's step size lr the proximal map is

    phi_hat <- a_hat + (phi_hat - a_hat) / (1 + lr / r)

(decoupled weight decay towards a_hat, as AdamW). Against Adam's step lr m / sqrt(v) it balances at
|phi_hat_j - a_hat_j| = r |m_j / sqrt(v_j)| <= r: consistent evidence moves a coordinate at most r from the anchor,
and without a pull the image relaxes back within about r / lr steps. Images without tracks (r NaN) are untouched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from s2camp_ns.core.camera import ParameterLayout
from s2camp_ns.core.proxy_range import span
from s2camp_ns.core.track_fit import TrackFit


@dataclass(frozen=True)
class TrackPriorEvidence:
    """Per training image: the anchor deltas (layout columns, training frame), the reprojection RMS there (px; NaN:
    no tracks) and the track observation count (None: each image counts once)."""

    anchor: Float[Tensor, "n k"]
    rms_px: Float[Tensor, " n"] | None
    observations: Float[Tensor, " n"] | None


def evidence_from_fit(fit: TrackFit, world_scale: float, layout: ParameterLayout) -> TrackPriorEvidence:
    """``fit_anchor``'s deltas, translation scaled into the training frame, with its RMS and observation counts."""
    deltas = fit.deltas.clone()  # [n, 16]
    deltas[:, :3] = deltas[:, :3] * float(world_scale)  # tracks' world -> training frame
    return TrackPriorEvidence(deltas[:, list(layout.indices)], fit.rms_px, fit.observations)


def checked_evidence(
    track_rms_px: Float[Tensor, " n"] | list[float],
    track_observations: Float[Tensor, " n"] | list[float] | None,
    num_images: int,
    layout: ParameterLayout,
) -> TrackPriorEvidence:
    """The given cameras as the anchor (zero deltas) with their reprojection RMS (NaN: no prior) and observation
    counts; ValueError unless one value >= 0 per image."""
    rms = torch.as_tensor(track_rms_px, dtype=torch.float64).reshape(-1)
    if rms.shape[0] != num_images:
        raise ValueError(f"track_rms_px must hold {num_images} values (one per training image), got {rms.shape[0]}")
    if bool((rms < 0).any()):
        raise ValueError(f"track_rms_px must be >= 0 (pixels), got minimum {float(rms.min())}")
    observations = None
    if track_observations is not None:
        observations = torch.as_tensor(track_observations, dtype=torch.float64).reshape(-1)
        if observations.shape[0] != num_images or bool((observations < 0).any()):
            raise ValueError(
                f"track_observations must hold {num_images} counts >= 0 (one per training image), got "
                f"{observations.shape[0]} with minimum {float(observations.min())}"
            )
    anchor = torch.zeros(num_images, layout.num_params, dtype=torch.float64)
    return TrackPriorEvidence(anchor, rms, observations)


def pose_radius(
    radius: Float[Tensor, " n"], observations: Float[Tensor, " n"] | None, exponent: float = 1.0
) -> Float[Tensor, " n"]:
    """Radius of each image's pose latent, r_i / (2 O_i)^(e/2) with e = ``exponent`` in [0, 1] (module docstring):
    the standard error at 1, r_i at 0. ``observations`` None: each image counts once."""
    counts = torch.ones_like(radius) if observations is None else observations.to(radius).clamp(min=1.0)
    return radius / (2.0 * counts) ** (0.5 * exponent)


def pooled_intrinsics_radius(
    radius: Float[Tensor, " n"],
    observations: Float[Tensor, " n"] | None,
    camera_of_image: Int[Tensor, " n"],
    num_cameras: int,
) -> Float[Tensor, " c"]:
    """Radius of each physical camera's intrinsics latent, sqrt(sum_i O_i r_i^2) / (sqrt(2) sum_i O_i) over its images
    with a prior; NaN where none has one. ``observations`` None: each image counts once."""
    finite = torch.isfinite(radius)
    weight = torch.ones_like(radius) if observations is None else observations.to(radius)
    weight = torch.where(finite, weight, torch.zeros_like(weight))
    squared = torch.zeros(num_cameras, dtype=torch.float64, device=radius.device)
    counts = torch.zeros_like(squared)
    squared.index_add_(0, camera_of_image, torch.nan_to_num(radius).square() * weight)
    counts.index_add_(0, camera_of_image, weight)
    return torch.where(counts > 0, squared.sqrt() / (math.sqrt(2.0) * counts.clamp(min=1e-12)), torch.nan)


def inverse_radius(radius: Float[Tensor, " r"]) -> Float[Tensor, "r 1"]:
    """1 / r per row as a column, 0 where the radius is not finite (no prior): the prior's step then leaves the row."""
    return torch.where(torch.isfinite(radius), 1.0 / radius.clamp(min=1e-12), torch.zeros_like(radius))[:, None]


@torch.no_grad()
def apply_track_prior(
    latent: Float[Tensor, "r j"], anchor: Float[Tensor, "r j"], inverse: Float[Tensor, "r 1"], lr: float
) -> None:
    """One proximal step in place, latent <- a + (latent - a) / (1 + lr / r), as a lerp with weight
    (lr / r) / (1 + lr / r); ``inverse``: 1 / r (0 leaves a row untouched). No host read."""
    scaled = inverse * lr
    latent.lerp_(anchor, scaled / (1.0 + scaled))


@torch.no_grad()
def place_at_anchor(latent: Float[Tensor, "r j"], anchor: Float[Tensor, "r j"], radius: Float[Tensor, " r"]) -> None:
    """Rows with a prior (finite radius) set to the anchor, the others left as they are."""
    finite = torch.isfinite(radius)[:, None]
    latent.copy_(torch.where(finite, anchor.to(latent.dtype), latent))


def describe_anchor_fit(fit: TrackFit) -> str | None:
    """The start-up note on the anchor fit: RMS as given and at the anchor (None when no image has both)."""
    moved = torch.isfinite(fit.rms_given_px) & torch.isfinite(fit.rms_px)
    if not bool(moved.any()):
        return None
    held = fit.intrinsics_held
    kept = "" if held is None else f"; given intrinsics kept: {int(held.sum())} of {held.numel()} camera(s)"
    return (
        f"[dim]Track prior: the cameras' reprojection error against the tracks is "
        f"{span(fit.rms_given_px[moved])} px as given and {span(fit.rms_px[moved])} px where the tracks "
        f"put them (the anchor{kept}; {fit.iterations} Levenberg-Marquardt iterations)"
    )


__all__ = [
    "describe_anchor_fit",
    "TrackPriorEvidence",
    "apply_track_prior",
    "inverse_radius",
    "checked_evidence",
    "evidence_from_fit",
    "place_at_anchor",
    "pooled_intrinsics_radius",
    "pose_radius",
]
