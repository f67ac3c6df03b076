"""The refiner's two latent layouts, one interface (``LatentLayout``): ``PerImageIntrinsics`` (intrinsics refined per
image, CamP's way: P the symmetric root per image, paper eq. 20) and ``PerCameraIntrinsics`` (shared by the images of
one physical camera: a pose latent per image, an intrinsics latent per camera, P the block-triangular factor of
``core.shared_intrinsics``). Each reads and writes the tensors of the ``CameraRefiner`` it is given.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from s2camp_ns.core.preconditioner import Preconditioner, compute_preconditioner, reexpress_latent
from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS, compute_shared_preconditioner, reexpress_shared_latents
from s2camp_ns.core.track_prior import pooled_intrinsics_radius, whitened_anchor

if TYPE_CHECKING:
    from s2camp_ns.core.refiner import CameraRefiner


@dataclass(frozen=True)
class PriorBlock:
    """One latent under the track prior: its rows, their anchor in the whitened latent and their radius."""

    latent: nn.Parameter
    anchor: Tensor
    radius: Tensor


class LatentLayout(Protocol):
    """What ``CameraRefiner`` asks of a latent layout (``PerImageIntrinsics``, ``PerCameraIntrinsics``)."""

    def pose_columns(self, k: int) -> int:
        """Columns of the per-image latent ``whitened_delta`` when the layout refines ``k`` parameters."""
        ...

    def latent(self, refiner: CameraRefiner, images: Tensor | None) -> Float[Tensor, "m k"]:
        """The whitened latent of every image (or of ``images``), all K columns, float64."""
        ...

    def base(self, refiner: CameraRefiner, base: Float[Tensor, "n 13"]) -> Float[Tensor, "n 13"]:
        """The base intrinsics the layout refines from, given those of every image."""
        ...

    def recompute(self, refiner: CameraRefiner, optimizer: torch.optim.Optimizer | None) -> None:
        """Recompute P at the refined intrinsics, re-expressing the latents and Adam's moments (no camera moves)."""
        ...

    def anchor_mask(self, refiner: CameraRefiner, finite: Tensor) -> Tensor:
        """[n, K] bool: the columns the track prior anchors, given the images with a prior (``finite``)."""
        ...

    def intrinsics_radius(self, refiner: CameraRefiner, radius: Tensor, observations: Tensor | None) -> Tensor:
        """The track prior's radius of the intrinsics latent."""
        ...

    def prior_blocks(self, refiner: CameraRefiner) -> list[PriorBlock]:
        """The latents under the track prior, each with its anchor and radius."""
        ...


class PerImageIntrinsics:
    """Every image refines all K columns itself: the latent ``whitened_delta`` [n, K], P the symmetric root of
    each image's damped Gram (paper eq. 20)."""

    def pose_columns(self, k: int) -> int:
        return k

    def latent(self, refiner: CameraRefiner, images: Tensor | None) -> Float[Tensor, "m k"]:
        latent = refiner.whitened_delta if images is None else refiner.whitened_delta[images]
        return latent.to(torch.float64)

    def base(self, refiner: CameraRefiner, base: Float[Tensor, "n 13"]) -> Float[Tensor, "n 13"]:
        return base

    def recompute(self, refiner: CameraRefiner, optimizer: torch.optim.Optimizer | None) -> None:
        """P per image at its refined intrinsics, the latent and Adam's moments re-expressed (``reexpress_latent``)."""
        device = refiner.precond.device
        intrinsics = refiner.refined_intrinsics().detach()
        result = compute_preconditioner(
            intrinsics, refiner.layout, refiner.sampling, refiner.damping, ranges=refiner.sampling_ranges()
        )
        old = Preconditioner(matrix=refiner.precond, inverse=refiner.precond_inv, gram=refiner.gram, num_valid=None)
        new = Preconditioner(
            matrix=result.matrix.to(device), inverse=result.inverse.to(device), gram=result.gram, num_valid=None
        )
        latent = refiner.whitened_delta
        state = optimizer.state.get(latent) if optimizer is not None else None
        reexpress_latent(latent, old, new, state)
        refiner.precond.copy_(new.matrix)
        refiner.precond_inv.copy_(new.inverse)
        refiner.gram.copy_(result.gram.to(device))

    def anchor_mask(self, refiner: CameraRefiner, finite: Tensor) -> Tensor:
        return finite[:, None].expand(refiner.num_images, refiner.layout.num_params).clone()

    def intrinsics_radius(self, refiner: CameraRefiner, radius: Tensor, observations: Tensor | None) -> Tensor:
        return refiner.prior_radius_intrinsics  # no intrinsics latent of their own: nothing to scale

    def prior_blocks(self, refiner: CameraRefiner) -> list[PriorBlock]:
        anchor = whitened_anchor(refiner.precond, refiner.prior_anchor)
        return [PriorBlock(refiner.whitened_delta, anchor, refiner.prior_radius)]


def mean_per_camera(
    values: Float[Tensor, "n d"], camera_of_image: Int[Tensor, " n"], num_cameras: int
) -> Float[Tensor, "n d"]:
    """Each image's row replaced by the mean over the images of its physical camera (``camera_of_image``, one index
    below ``num_cameras`` per image): the base intrinsics a shared layout starts from, in ``values``' dtype."""
    count = torch.bincount(camera_of_image, minlength=num_cameras).to(values)  # [C]
    sums = torch.zeros(num_cameras, values.shape[1], dtype=values.dtype, device=values.device)
    sums = sums.index_add_(0, camera_of_image, values)  # [C, d]
    return (sums / count.clamp(min=1.0)[:, None])[camera_of_image]


class PerCameraIntrinsics:
    """The images of a physical camera share its intrinsics (``core.shared_intrinsics``): the pose latent
    ``whitened_delta`` [n, 6] per image and the intrinsics latent ``whitened_intrinsics`` [C, K - 6] per camera;
    P is the block upper-triangular T of the camera, stored per image (its images share it)."""

    def pose_columns(self, k: int) -> int:
        return NUM_POSE_PARAMS

    def latent(self, refiner: CameraRefiner, images: Tensor | None) -> Float[Tensor, "m k"]:
        """[z_i; w_c]: the pose latent of each image and the intrinsics latent of its camera."""
        pose, camera_of_image = refiner.whitened_delta, refiner.camera_of_image
        if images is not None:
            pose, camera_of_image = pose[images], camera_of_image[images]
        shared = refiner.whitened_intrinsics.to(torch.float64)[camera_of_image]
        return torch.cat([pose.to(torch.float64), shared], dim=-1)

    def base(self, refiner: CameraRefiner, base: Float[Tensor, "n 13"]) -> Float[Tensor, "n 13"]:
        """One set of base intrinsics per physical camera: the mean over its images (they agree for SfM cameras;
        a per-image perturbation averages out). Images of one camera must have the same size."""
        index = refiner.camera_of_image
        first = refiner.first_image_of_each_camera()
        size_mismatch = (base[first][index, 7:9] != base[:, 7:9]).any(dim=-1)
        if bool(size_mismatch.any()):
            i = int(torch.nonzero(size_mismatch)[0])
            j = int(first[index[i]])
            raise ValueError(
                f"training image {i} is {int(base[i, 7])}x{int(base[i, 8])} but image {j} of the same physical camera "
                f"{int(index[i])} is {int(base[j, 7])}x{int(base[j, 8])}: shared intrinsics need one "
                "image size per camera (or --pipeline.model.camera-optimizer.intrinsics per-image)"
            )
        return mean_per_camera(base, index, refiner.num_physical_cameras)

    def recompute(self, refiner: CameraRefiner, optimizer: torch.optim.Optimizer | None) -> None:
        """T per physical camera from its refined intrinsics, the latents and Adam's moments re-expressed without
        moving any camera (``reexpress_shared_latents``)."""
        device = refiner.precond.device
        first = refiner.first_image_of_each_camera()
        intrinsics = refiner.refined_intrinsics().detach()[first]
        result = compute_shared_preconditioner(
            intrinsics, refiner.layout, refiner.sampling, refiner.damping, ranges=refiner.sampling_ranges(first)
        )
        matrix, inverse = result.matrix.to(device), result.inverse.to(device)  # [C, K, K]
        states = [None, None]
        if optimizer is not None:
            states = [optimizer.state.get(refiner.whitened_delta), optimizer.state.get(refiner.whitened_intrinsics)]
        reexpress_shared_latents(
            refiner.whitened_delta, refiner.whitened_intrinsics, refiner.camera_of_image, refiner.precond[first],
            refiner.precond_inv[first], matrix, inverse, *states,
        )  # fmt: skip
        refiner.precond.copy_(matrix[refiner.camera_of_image])
        refiner.precond_inv.copy_(inverse[refiner.camera_of_image])
        refiner.gram.copy_(result.gram.to(device)[refiner.camera_of_image])

    def anchor_mask(self, refiner: CameraRefiner, finite: Tensor) -> Tensor:
        """The pose columns where the image has a prior; the intrinsics columns where any image of its camera has."""
        keep = finite[:, None].expand(refiner.num_images, refiner.layout.num_params).clone()
        tracked = torch.zeros(refiner.num_physical_cameras, dtype=torch.bool, device=finite.device)
        tracked[refiner.camera_of_image[finite]] = True
        keep[:, NUM_POSE_PARAMS:] = tracked[refiner.camera_of_image][:, None]
        return keep

    def intrinsics_radius(self, refiner: CameraRefiner, radius: Tensor, observations: Tensor | None) -> Tensor:
        return pooled_intrinsics_radius(radius, observations, refiner.camera_of_image, refiner.num_physical_cameras)

    def prior_blocks(self, refiner: CameraRefiner) -> list[PriorBlock]:
        """P is block-triangular, so the images of one camera give the same intrinsics anchor: their first image's."""
        anchor = whitened_anchor(refiner.precond, refiner.prior_anchor)
        first = refiner.first_image_of_each_camera()
        return [
            PriorBlock(refiner.whitened_delta, anchor[:, :NUM_POSE_PARAMS], refiner.prior_radius),
            PriorBlock(refiner.whitened_intrinsics, anchor[first, NUM_POSE_PARAMS:], refiner.prior_radius_intrinsics),
        ]


__all__ = ["LatentLayout", "PerCameraIntrinsics", "PerImageIntrinsics", "PriorBlock", "mean_per_camera"]
