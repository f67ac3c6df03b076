"""The track prior: a Gaussian on the whitened latent about the camera its SfM tracks give, and its proximal step.

Derivation. The prior anchors each camera at a, the deltas phi where its tracks put it (``core.track_fit``'s
camera-only bundle adjustment against the fixed SfM points; zero, the given camera, without a fit), expressed in the
whitened latent as a_hat = P a (paper eq. 15); every camera with tracks starts there (``place_at_anchor``). Its scale
is what the tracks know of the camera, in whitened units: pixels divided by max(W, H), the Gram matrix's pixel unit
(paper eq. 5, docs/EQUATIONS.md eq. 5), in which |phi_hat - a_hat| is the RMS displacement of the camera's proxy
points (paper eqs. 5 and 20; damping only adds to it).

How far the tracks leave a camera uncertain. A unit step of a whitened coordinate moves the camera's proxy points by
an RMS of one, and so each of its O track observations by about one; O observations with pixel noise of RMS r (2-D:
r^2 / 2 per coordinate) determine the camera, in every whitened coordinate, to the standard error r / sqrt(2 O) of
that least-squares fit. Image i's pose therefore gets r_i / sqrt(2 O_i) (``pose_radius``; r_i its reprojection
error at the anchor, O_i its observations), and the intrinsics a physical camera's images share get the standard error
of the fit to all their observations, sqrt(sum_i O_i r_i^2) / (sqrt(2) sum_i O_i) (``pooled_intrinsics_radius``).
Without observation counts each image counts once. The tracks' points are not spread like the proxy points, so a
camera is pinned more tightly than this along some directions and less along others; the radius is their average.

The prior's proximal map with Adam's step size lr is

    phi_hat <- a_hat + (phi_hat - a_hat) / (1 + lr / r)

(decoupled weight decay, as AdamW, towards a_hat). It balances Adam's step lr m / sqrt(v) where each coordinate has
|phi_hat_j - a_hat_j| = r |m_j / sqrt(v_j)| <= r: evidence of constant sign (|m / sqrt(v)| near 1) moves a whitened
coordinate at most r from the anchor, what the tracks leave uncertain; gradient noise (|m / sqrt(v)| near 0.23 for
Adam's beta1 0.9) about a quarter of that. Once the field stops pulling, the camera relaxes back towards the anchor
within about r / lr steps instead of staying where early field errors pushed it. Images without tracks (r NaN) are
untouched.
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
    """What the prior is made of, per training image: the anchor deltas (the layout's columns, training frame), the
    reprojection error there in pixels (NaN: no tracks) and each image's number of track observations (None: each
    image counts once)."""

    anchor: Float[Tensor, "n k"]
    rms_px: Float[Tensor, " n"] | None
    observations: Float[Tensor, " n"] | None


def evidence_from_fit(fit: TrackFit, world_scale: float, layout: ParameterLayout) -> TrackPriorEvidence:
    """The anchor where ``core.track_fit.fit_anchor`` put each camera, its translation scaled from the tracks' world
    into the training frame (``world_scale``), and the fit's reprojection error and observation counts."""
    deltas = fit.deltas.clone()  # [n, 16]
    deltas[:, :3] = deltas[:, :3] * float(world_scale)  # tracks' world -> training frame
    return TrackPriorEvidence(deltas[:, list(layout.indices)], fit.rms_px, fit.observations)


def checked_evidence(
    track_rms_px: Float[Tensor, " n"] | list[float],
    track_observations: Float[Tensor, " n"] | list[float] | None,
    num_images: int,
    layout: ParameterLayout,
) -> TrackPriorEvidence:
    """The given cameras as the anchor (zero deltas) with their reprojection error ``track_rms_px`` (NaN: no prior)
    and observation counts; ValueError for a count of values other than one per image or negative values."""
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
    """Radius of each image's pose latent: the standard error r_i / sqrt(2 O_i) of its fit to its O_i observations
    (module docstring; ``observations`` None: each image counts once). ``exponent`` e in [0, 1] gives
    r_i / (2 O_i)^(e / 2): 1 the standard error, 0 the reprojection error r_i itself, looser by sqrt(2 O_i)."""
    counts = torch.ones_like(radius) if observations is None else observations.to(radius).clamp(min=1.0)
    return radius / (2.0 * counts) ** (0.5 * exponent)


def pooled_intrinsics_radius(
    radius: Float[Tensor, " n"],
    observations: Float[Tensor, " n"] | None,
    camera_of_image: Int[Tensor, " n"],
    num_cameras: int,
) -> Float[Tensor, " c"]:
    """Radius of each physical camera's shared intrinsics latent: the standard error of the pooled fit,
    sqrt(sum_i O_i r_i^2) / (sqrt(2) sum_i O_i) over its images with a prior (module docstring); NaN where none has
    one. ``observations`` None: each image counts once."""
    finite = torch.isfinite(radius)
    weight = torch.ones_like(radius) if observations is None else observations.to(radius)
    weight = torch.where(finite, weight, torch.zeros_like(weight))
    squared = torch.zeros(num_cameras, dtype=torch.float64, device=radius.device)
    counts = torch.zeros_like(squared)
    squared.index_add_(0, camera_of_image, torch.nan_to_num(radius).square() * weight)
    counts.index_add_(0, camera_of_image, weight)
    return torch.where(counts > 0, squared.sqrt() / (math.sqrt(2.0) * counts.clamp(min=1e-12)), torch.nan)


def whitened_anchor(precond: Float[Tensor, "n k k"], anchor: Float[Tensor, "n k"]) -> Float[Tensor, "n k"]:
    """The anchor in the whitened latent, a_hat = P a (paper eq. 15), per image."""
    return (precond @ anchor[..., None])[..., 0]


def inverse_radius(radius: Float[Tensor, " r"]) -> Float[Tensor, "r 1"]:
    """1 / r per row as a column, 0 where the radius is not finite (no prior): the prior's step then leaves the row."""
    return torch.where(torch.isfinite(radius), 1.0 / radius.clamp(min=1e-12), torch.zeros_like(radius))[:, None]


@torch.no_grad()
def apply_track_prior(
    latent: Float[Tensor, "r j"], anchor: Float[Tensor, "r j"], inverse: Float[Tensor, "r 1"], lr: float
) -> None:
    """One proximal step of the prior in place, latent <- a + (latent - a) / (1 + lr / r) (module docstring), as
    latent <- latent + w (a - latent) with w = (lr / r) / (1 + lr / r); ``inverse`` is 1 / r (``inverse_radius``: 0
    leaves a row untouched). Four tensor ops, no host read."""
    scaled = inverse * lr
    latent.lerp_(anchor, scaled / (1.0 + scaled))


@torch.no_grad()
def place_at_anchor(latent: Float[Tensor, "r j"], anchor: Float[Tensor, "r j"], radius: Float[Tensor, " r"]) -> None:
    """The rows with a prior (finite radius) at the anchor; the others are left where they are (the given camera at
    set-up)."""
    finite = torch.isfinite(radius)[:, None]
    latent.copy_(torch.where(finite, anchor.to(latent.dtype), latent))


def describe_anchor_fit(fit: TrackFit) -> str | None:
    """The start-up note on the anchor fit: the cameras' reprojection error as given and at the anchor (None when no
    camera has both)."""
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
    "whitened_anchor",
]
