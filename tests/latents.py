"""The refiner's latent as one [n, K] tensor per image, for tests written against it: the pose latent [n, 6] and the
intrinsics latent [rows, K - 6] are its storage (``s2camp_ns.core.refiner``)."""

from __future__ import annotations

import torch

from s2camp_ns.core.refiner import CameraRefiner
from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS


@torch.no_grad()
def write_latent(refiner: CameraRefiner, values: torch.Tensor) -> None:
    """Store the per-image latent ``values`` [n, K] (broadcast): poses per image, intrinsics from each row's first
    image (per image, every image is its own row)."""
    values = values.expand(refiner.num_images, refiner.layout.num_params).to(refiner.whitened_delta)
    refiner.whitened_delta.copy_(values[:, :NUM_POSE_PARAMS])
    if hasattr(refiner, "whitened_intrinsics"):
        refiner.whitened_intrinsics.copy_(values[refiner.first_image_of_each_row(), NUM_POSE_PARAMS:])


def latent_grad(refiner: CameraRefiner) -> torch.Tensor:
    """The latent's gradient per image [n, K] (a row's intrinsics gradient repeated for each of its images)."""
    parts = [refiner.whitened_delta.grad]
    if hasattr(refiner, "whitened_intrinsics"):
        parts.append(refiner.whitened_intrinsics.grad[refiner.row_of_image])
    return torch.cat(parts, dim=-1)


def latent_moment(adam: torch.optim.Optimizer, refiner: CameraRefiner, key: str) -> torch.Tensor:
    """Adam's ``key`` ("exp_avg", "exp_avg_sq") of the latent per image [n, K] (a row's repeated for its images)."""
    parts = [adam.state[refiner.whitened_delta][key]]
    if hasattr(refiner, "whitened_intrinsics"):
        parts.append(adam.state[refiner.whitened_intrinsics][key][refiner.row_of_image])
    return torch.cat(parts, dim=-1)


def set_latent_column(refiner: CameraRefiner, column: int, value: float) -> None:
    """Column ``column`` of every image's latent set to ``value`` (the others kept)."""
    latent = refiner.latent().detach()
    latent[:, column] = value
    write_latent(refiner, latent)
