"""Re-triangulation of track points in fixed cameras: each point moved to where its observations put it.

For point x with observations (image i, pixel u) the cost is the plain sum of squared reprojection distances
sum ||pi_i(R_i^T (x - c_i)) - u||^2 (paper eq. 2, distortion included), over the observations whose projection is valid
(``core.camera.project``'s margin). Levenberg-Marquardt in float64, one 3 x 3 system per point; a point's step is
taken only where it lowers that point's cost, so no point ends with a higher cost than it started with. Jacobians
d pixel / d x are exact (forward-mode autodiff, one pass per world axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, project
from s2camp_ns.core.tracks import Tracks, index_in_image

ITERATIONS = 20
"""Levenberg-Marquardt iterations (each point stops improving within a few)."""
_INITIAL_DAMPING = 1e-3


@dataclass(frozen=True)
class _Observations:
    """The fixed data of the observations: each one's camera (rows of [n] ``intrinsics``), its slot among that
    camera's observations (``project`` takes [n, l, 3] points per camera) and its pixel."""

    image: Int[Tensor, " o"]
    slot: Int[Tensor, " o"]
    slots: int
    rotation: Float[Tensor, "o 3 3"]
    centre: Float[Tensor, "o 3"]
    intrinsics: Intrinsics
    pixels: Float[Tensor, "o 2"]

    @classmethod
    def of(cls, tracks: Tracks, c2w: Float[Tensor, "n 3 4"], intrinsics: Intrinsics) -> _Observations:
        device = c2w.device
        image = tracks.image.to(device=device, dtype=torch.long)
        slot, slots = index_in_image(image, c2w.shape[0])
        return cls(
            image, slot, slots, c2w[image, :, :3], c2w[image, :, 3],
            intrinsics.to(device=device, dtype=torch.float64), tracks.pixels.to(device=device, dtype=torch.float64),
        )  # fmt: skip

    def residuals(self, x: Float[Tensor, "o 3"]) -> tuple[Float[Tensor, "o 2"], Float[Tensor, " o"]]:
        """Projected minus observed pixels of each observation's point ``x``, and the projection's margin."""
        points_cam = ((x - self.centre)[:, None, :] @ self.rotation)[:, 0]  # R^T (x - c)
        n = self.intrinsics.num_cameras
        padded = torch.zeros(n, self.slots, 3, dtype=x.dtype, device=x.device)
        padded[..., 2] = 1.0  # unused slots: a point ahead of the camera
        padded = padded.index_put((self.image, self.slot), points_cam)
        projected, margin = project(padded, self.intrinsics)  # [n, l, 2], [n, l]
        return projected[self.image, self.slot] - self.pixels, margin[self.image, self.slot]


def _point_cost(residual: Float[Tensor, "o 2"], valid: Float[Tensor, " o"], point: Int[Tensor, " o"], p: int) -> Tensor:
    """Per point [p]: the sum of squared residuals of its valid observations."""
    squared = residual.square().sum(dim=-1) * valid
    return torch.zeros(p, dtype=torch.float64, device=squared.device).index_add_(0, point, squared)


def retriangulated_points(
    tracks: Tracks, c2w: Float[Tensor, "n 3 4"], intrinsics: Intrinsics, iterations: int = ITERATIONS
) -> Float[Tensor, "p 3"]:
    """``tracks.points`` moved, each by its own damped Gauss-Newton steps, to lower its reprojection cost in the
    cameras ``c2w`` (OpenCV camera-to-world) and ``intrinsics`` (float64, on ``c2w``'s device)."""
    tracks.validate(c2w.shape[0])
    device = c2w.device
    observations = _Observations.of(tracks, c2w.to(torch.float64), intrinsics)
    point = tracks.point.to(device)
    points = tracks.points.detach().to(device=device, dtype=torch.float64).clone()
    p = points.shape[0]
    damping = torch.full((p,), _INITIAL_DAMPING, dtype=torch.float64, device=device)

    def evaluate(x_points: Tensor) -> tuple[Tensor, Tensor]:
        residual, margin = observations.residuals(x_points[point])
        return residual, (margin > 0).to(torch.float64)

    residual, valid = evaluate(points)
    cost = _point_cost(residual, valid, point, p)
    for _ in range(iterations):
        x = points[point]
        columns = []
        for axis in range(3):  # d residual / d x_axis [o, 2], forward mode
            tangent = torch.zeros_like(x)
            tangent[:, axis] = 1.0
            _, column = torch.func.jvp(lambda y: observations.residuals(y)[0], (x,), (tangent,))
            columns.append(column)
        jacobian = torch.stack(columns, dim=-1) * valid[:, None, None]  # [o, 2, 3]
        normal = torch.zeros(p, 3, 3, dtype=torch.float64, device=device).index_add_(
            0, point, jacobian.transpose(1, 2) @ jacobian
        )
        gradient = torch.zeros(p, 3, dtype=torch.float64, device=device).index_add_(
            0, point, (jacobian.transpose(1, 2) @ residual[..., None])[..., 0]
        )
        diagonal = torch.diagonal(normal, dim1=1, dim2=2)
        damped = normal + torch.diag_embed(damping[:, None] * diagonal + 1e-12)
        step = -torch.linalg.solve(damped, gradient[..., None])[..., 0]
        trial = points + step
        trial_residual, trial_valid = evaluate(trial)
        trial_cost = _point_cost(trial_residual, trial_valid, point, p)
        # A step must lower the cost without losing an observation's valid projection.
        lost = torch.zeros(p, dtype=torch.float64, device=device).index_add_(0, point, valid * (1.0 - trial_valid))
        better = (trial_cost < cost) & (lost <= 0) & torch.isfinite(trial_cost)
        points = torch.where(better[:, None], trial, points)
        cost = torch.where(better, trial_cost, cost)
        damping = torch.where(better, damping / 10.0, damping * 10.0).clamp(1e-12, 1e12)
        residual, valid = evaluate(points)
    return points


__all__ = ["ITERATIONS", "retriangulated_points"]
