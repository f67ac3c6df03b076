"""Least-squares matching of image patches: where a reference patch lands in another view, to a small part of a pixel.

For each pair b, a reference window R_b and a target window W_b (square crops of equal size, each centred on a
keypoint, its position at the window's centre c), the template is R_b on the grid x of integer offsets in
[-``radius``, ``radius``]^2 about c, and the model (Gruen's least-squares matching, with a photometric gain and offset)

    g W_b(c + A x + t) + o = R_b(c + x)

with A [2, 2], t [2], g, o found by Gauss-Newton, the residuals reweighted by the Cauchy loss at a robust scale (1.4826
times their median absolute value, so that an occluded part of the patch counts little). ``t`` is where the reference
keypoint lands in the target window, less its centre: the target keypoint moves by ``t``. Coarse to fine: ``levels``
halvings of both windows (a [1, 2, 1] blur and a 2x2 mean, which maps continuous coordinates u to u / 2), the template
grid covering 2^l times the area at level l, t halved going down and doubled going up, A kept.

Pixel convention: continuous, a window of side S covers [0, S]^2 and its pixel (i, j) has its centre at
(i + 0.5, j + 0.5); its centre c = (S / 2, S / 2). Batched over pairs; float32 or float64; any device.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

CAUCHY_MAD = 1.4826
"""Median absolute deviation to standard deviation of a normal distribution: the residuals' robust scale."""
RADIUS = 5
"""Half side of the template (px): 11 x 11 samples, covering 2^l times that at level l."""
LEVELS = 2
"""Coarse-to-fine levels (each halves the windows)."""
ITERATIONS = 6
"""Gauss-Newton steps per level at most."""
TOLERANCE_PX = 0.03
"""A pair has converged when its last step moves t by less than this (px of the finest level)."""
PARAMETERS = 8
"""[A | t] row-major (a11, a12, t1, a21, a22, t2), gain, offset."""


@dataclass(frozen=True)
class PatchAlignment:
    """The alignment of each pair b (``align_patches``), at the finest level (px of the windows)."""

    shift: Float[Tensor, "b 2"]
    """t: the reference keypoint's position in the target window, less the window's centre."""
    affine: Float[Tensor, "b 2 2"]
    """A: template offsets to target offsets."""
    gain: Float[Tensor, " b"]
    offset: Float[Tensor, " b"]
    converged: Bool[Tensor, " b"]
    """The last step moved t by less than ``tolerance``, every sample stayed inside the window, all finite."""
    correlation: Float[Tensor, " b"]
    """Normalised cross-correlation of the template and the aligned target samples (1: equal up to gain and offset)."""


def template_offsets(radius: int, dtype: torch.dtype, device: torch.device) -> Float[Tensor, "k 2"]:
    """The integer offsets [-radius, radius]^2 (x fastest), K = (2 radius + 1)^2."""
    steps = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    y, x = torch.meshgrid(steps, steps, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1)], dim=-1)


def halved(windows: Float[Tensor, "b s s"]) -> Float[Tensor, "b h h"]:
    """One level coarser: a [1, 2, 1] / 4 blur (edges replicated), then 2x2 means (u -> u / 2)."""
    padded = F.pad(windows[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    rows = 0.25 * padded[:, :, :-2] + 0.5 * padded[:, :, 1:-1] + 0.25 * padded[:, :, 2:]
    blurred = 0.25 * rows[:, :-2] + 0.5 * rows[:, 1:-1] + 0.25 * rows[:, 2:]
    size = blurred.shape[-1] // 2
    return blurred.reshape(-1, size, 2, size, 2).mean(dim=(2, 4))


def with_gradients(windows: Float[Tensor, "b s s"]) -> Float[Tensor, "b 3 s s"]:
    """Each window with its x and y derivatives (central differences, one-sided at the edges) as channels."""
    padded = F.pad(windows[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = 0.5 * (padded[:, 1:-1, 2:] - padded[:, 1:-1, :-2])
    gy = 0.5 * (padded[:, 2:, 1:-1] - padded[:, :-2, 1:-1])
    return torch.stack([windows, gx, gy], dim=1)


def sample(channels: Float[Tensor, "b c s s"], points: Float[Tensor, "b k 2"]) -> Float[Tensor, "b c k"]:
    """Bilinear samples of the channels at continuous window coordinates (zero outside)."""
    size = channels.shape[-1]
    grid = points / size * 2.0 - 1.0  # align_corners=False: [0, S] -> [-1, 1]
    return F.grid_sample(channels, grid[:, None], mode="bilinear", padding_mode="zeros", align_corners=False)[:, :, 0]


def _cauchy_weights(residual: Float[Tensor, "b k"]) -> Float[Tensor, "b k"]:
    scale = CAUCHY_MAD * residual.abs().median(dim=1, keepdim=True).values
    scale = scale.clamp(min=1e-6 * (1.0 + residual.abs().amax(dim=1, keepdim=True)))
    return 1.0 / (1.0 + (residual / scale).square())


def _warp(params: Float[Tensor, "b 8"], offsets: Float[Tensor, "k 2"], centre: float) -> Float[Tensor, "b k 2"]:
    """Target window coordinates c + A x + t of the template offsets x (params: [A | t] row-major, gain, offset)."""
    rows = params[:, :6].view(-1, 2, 3)  # [A | t]
    return centre + offsets @ rows[:, :, :2].transpose(1, 2) + rows[:, None, :, 2]


def _gauss_newton_step(
    template: Float[Tensor, "b k"],
    target: Float[Tensor, "b 3 s s"],
    offsets: Float[Tensor, "k 2"],
    centre: float,
    params: Float[Tensor, "b 8"],
) -> tuple[Float[Tensor, "b 8"], Bool[Tensor, " b"]]:
    """One reweighted, lightly damped Gauss-Newton step of every pair, and whether its samples lay in the window."""
    points = _warp(params, offsets, centre)  # [b, k, 2]
    size = target.shape[-1]
    inside = ((points >= 0.5) & (points <= size - 0.5)).flatten(1).all(dim=1)
    value, gx, gy = sample(target, points).unbind(dim=1)  # [b, k] each
    gain = params[:, 6:7]
    residual = gain * value + params[:, 7:8] - template
    homogeneous = F.pad(offsets, (0, 1), value=1.0)  # [k, 3]: x, y, 1
    gradient = torch.stack([gx, gy], dim=-1) * gain[..., None]  # [b, k, 2]
    geometric = (gradient[..., :, None] * homogeneous[:, None, :]).flatten(2)  # [b, k, 6]: d r / d [A | t]
    jacobian = torch.cat([geometric, value[..., None], torch.ones_like(value)[..., None]], dim=-1)  # [b, k, 8]
    weighted = jacobian * _cauchy_weights(residual)[..., None]
    normal = weighted.transpose(1, 2) @ jacobian  # [b, 8, 8]
    damping = 1e-6 * normal.diagonal(dim1=1, dim2=2).mean(dim=1).clamp(min=1e-12)
    normal = normal + damping[:, None, None] * torch.eye(PARAMETERS, dtype=normal.dtype, device=normal.device)
    step = -torch.linalg.solve(normal, (weighted * residual[..., None]).sum(dim=1))
    return step, inside


def _correlation(
    template: Float[Tensor, "b k"], target: Float[Tensor, "b 3 s s"], offsets: Tensor, centre: float, params: Tensor
) -> Float[Tensor, " b"]:
    value = sample(target[:, :1], _warp(params, offsets, centre))[:, 0]
    a, b = template - template.mean(dim=1, keepdim=True), value - value.mean(dim=1, keepdim=True)
    return (a * b).sum(dim=1) / (a.norm(dim=1) * b.norm(dim=1)).clamp(min=1e-12)


def _iterate(
    template: Tensor,
    channels: Tensor,
    offsets: Tensor,
    centre: float,
    params: Tensor,
    iterations: int,
    tolerance: float,
) -> tuple[Tensor, Bool[Tensor, " b"]]:
    """Gauss-Newton at one level until a step after the first moves t by less than ``tolerance`` (its level's px), a
    pair leaving the set of those still iterating when it does; returns the parameters and which pairs converged."""
    converged = torch.zeros(params.shape[0], dtype=torch.bool, device=params.device)
    active = torch.arange(params.shape[0], device=params.device)
    for iteration in range(iterations):
        step, inside = _gauss_newton_step(template[active], channels[active], offsets, centre, params[active])
        finite = torch.isfinite(step).all(dim=1)
        params[active] = params[active] + torch.where(finite[:, None], step, torch.zeros_like(step))
        # never on the first step: its weights come from the start's residuals, and it can be short far from the optimum
        done = finite & inside & (step[:, [2, 5]].norm(dim=1) < tolerance) & (iteration > 0)
        converged[active[done]] = True
        active = active[~done & finite & inside]
        if active.numel() == 0:
            break
    return params, converged


def align_patches(
    reference: Float[Tensor, "b s s"],
    target: Float[Tensor, "b s s"],
    affine: Float[Tensor, "b 2 2"],
    radius: int = RADIUS,
    levels: int = LEVELS,
    iterations: int = ITERATIONS,
    tolerance: float = TOLERANCE_PX,
) -> PatchAlignment:
    """Align each reference template to its target window (module docstring), starting from ``affine`` [b, 2, 2]
    (the expected map of reference offsets to target offsets), t = 0, and the gain and offset that match the patches'
    means and spreads there (coarsest level). ``tolerance``: the last
    step's movement of t (px of the finest level) below which a pair has converged; a pair that left the window or
    met a singular system stops there, not converged."""
    if reference.shape != target.shape or reference.shape[-1] != reference.shape[-2]:
        shapes = f"{tuple(reference.shape)}, {tuple(target.shape)}"
        raise ValueError(f"reference and target must be square windows of one shape [b, s, s], got {shapes}")
    size = reference.shape[-1]
    if size / 2 ** (levels - 1) < 2 * radius + 3:
        raise ValueError(f"windows of side {size} cannot hold a template of radius {radius} at {levels} levels")
    pyramid = [(reference, target)]
    for _ in range(levels - 1):
        pyramid.append((halved(pyramid[-1][0]), halved(pyramid[-1][1])))
    batch = reference.shape[0]
    params = torch.zeros(batch, PARAMETERS, dtype=reference.dtype, device=reference.device)
    params[:, [0, 1, 3, 4]] = affine.reshape(batch, 4).to(params)
    params[:, 6] = 1.0
    offsets = template_offsets(radius, reference.dtype, reference.device)
    for level in reversed(range(levels)):
        level_reference, level_target = pyramid[level]
        centre = level_reference.shape[-1] / 2.0
        template = sample(level_reference[:, None], (centre + offsets).expand(batch, -1, -1))[:, 0]
        channels = with_gradients(level_target)
        if level == levels - 1:  # gain and offset that match the patches' means and spreads at the start
            start = sample(channels[:, :1], _warp(params, offsets, centre))[:, 0]
            params[:, 6] = template.std(dim=1) / start.std(dim=1).clamp(min=1e-12)
            params[:, 7] = template.mean(dim=1) - params[:, 6] * start.mean(dim=1)
        params, converged = _iterate(template, channels, offsets, centre, params, iterations, tolerance / 2**level)
        if level > 0:
            params[:, [2, 5]] = params[:, [2, 5]] * 2.0
    finite = torch.isfinite(params).all(dim=1)
    return PatchAlignment(
        shift=params[:, [2, 5]],
        affine=params[:, [0, 1, 3, 4]].view(-1, 2, 2),
        gain=params[:, 6],
        offset=params[:, 7],
        converged=converged & finite,
        correlation=_correlation(template, channels, offsets, centre, params),
    )


__all__ = ["PatchAlignment", "align_patches", "halved", "sample", "template_offsets", "with_gradients"]
