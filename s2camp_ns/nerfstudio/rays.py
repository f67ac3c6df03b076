"""Training rays through refined cameras: regenerated from each ray's pixel, so intrinsics really move the rays.

nerfstudio's rays are cast from the dataparser's cameras; S2CamP's data manager (``PixelRayGenerator``) carries each
ray's continuous pixel coordinates in ``ray_bundle.metadata[PIXEL_KEY]``, and the rays are cast again through the same
pixels of the refined cameras (pose and intrinsics, differentiably). Rays without pixels can only follow the pose.
"""

from __future__ import annotations

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor

from s2camp_ns.core.refiner import CameraRefiner
from s2camp_ns.core.unprojection import pixel_to_ray_direction

PIXEL_KEY = "s2camp_pixels"
"""RayBundle metadata key of the continuous pixel coordinates (u, v) = (x + 0.5, y + 0.5) of each training ray."""


def regenerate_rays(
    refiner: CameraRefiner,
    camera_indices: Int[Tensor, " num_rays"],
    pixels: Float[Tensor, "num_rays 2"],
    dtype: torch.dtype = torch.float32,
) -> tuple[Float[Tensor, "num_rays 3"], Float[Tensor, "num_rays 3"], Float[Tensor, "num_rays 1"]]:
    """World origins, unit directions and directions_norm of rays through pixels of refined cameras.

    The per-camera algebra runs in float64 for the cameras the rays come from only (at most one per ray, so a
    step costs O(rays), not O(cameras): docs/SCALING.md); the per-ray part in ``dtype``. Autocast is disabled:
    undistortion and the pose product are not safe in half precision.
    """
    refiner.require_cameras()
    with torch.autocast(device_type=pixels.device.type, enabled=False):
        cameras, ray_camera = torch.unique(camera_indices.to(refiner.precond.device), return_inverse=True)
        deltas = refiner.deltas(cameras)  # [c, 16]
        intrinsics = refiner.refined_intrinsics(deltas, cameras).to(dtype=dtype)
        c2w = refiner.refined_c2w(deltas, images=cameras).to(dtype=dtype)  # [c, 3, 4]
        per_ray = intrinsics[ray_camera]
        directions_cam = pixel_to_ray_direction(pixels.to(dtype)[:, None, :], per_ray)[:, 0]  # [num_rays, 3]
        c2w_rays = c2w[ray_camera]
        directions = (c2w_rays[:, :, :3] @ directions_cam[:, :, None])[..., 0]
        origins = c2w_rays[:, :, 3]
        # nerfstudio's directions_norm is |(a, b, 1)| of the unnormalized camera direction = 1 / d_z; its fisheye
        # directions are unit vectors already (norm 1).
        if intrinsics.is_fisheye:
            directions_norm = torch.ones_like(directions_cam[:, 2:3])
        else:
            directions_norm = 1.0 / directions_cam[:, 2:3]
    return origins, directions, directions_norm


def apply_pixel_rays(refiner: CameraRefiner, raybundle: RayBundle, pixels: Float[Tensor, "*batch 2"]) -> None:
    """Replace the bundle's rays by rays through the same pixels of the refined cameras (pose AND intrinsics)."""
    camera_indices = raybundle.camera_indices.reshape(-1)
    origins, directions, directions_norm = regenerate_rays(
        refiner, camera_indices, pixels.reshape(-1, 2), dtype=raybundle.origins.dtype
    )
    shape = raybundle.origins.shape
    with torch.no_grad():
        cameras, ray_camera = torch.unique(camera_indices.to(refiner.precond.device), return_inverse=True)
        refined = refiner.refined_intrinsics(images=cameras)
        base = refiner.base_intrinsics[cameras]
        focal_ratio = base[:, 0] * base[:, 1] / (refined.fx * refined.fy)
    raybundle.origins = origins.reshape(shape)
    raybundle.directions = directions.reshape(shape)
    # Cone footprints shrink with the focal length; nerfacto ignores them, other fields may not.
    raybundle.pixel_area = raybundle.pixel_area * focal_ratio[ray_camera].to(raybundle.pixel_area).reshape(
        raybundle.pixel_area.shape
    )
    if "directions_norm" in raybundle.metadata:
        raybundle.metadata["directions_norm"] = directions_norm.reshape(raybundle.metadata["directions_norm"].shape)


def apply_pose_only(refiner: CameraRefiner, raybundle: RayBundle) -> None:
    """Rays without pixel coordinates (a stock data manager): only the pose refinement can be applied, the rays
    moved rigidly with their camera (c2w' c2w^-1)."""
    camera_indices = raybundle.camera_indices.reshape(-1)
    dtype = raybundle.origins.dtype
    refined = refiner.refined_c2w()[camera_indices].to(dtype)  # [num_rays, 3, 4]
    base = refiner.base_c2w_cv[camera_indices].to(dtype)
    world_rotation = refined[:, :, :3] @ base[:, :, :3].transpose(-1, -2)
    shape = raybundle.origins.shape
    directions = (world_rotation @ raybundle.directions.reshape(-1, 3)[:, :, None])[..., 0]
    offset = (raybundle.origins.reshape(-1, 3) - base[:, :, 3])[:, :, None]
    raybundle.origins = (refined[:, :, 3] + (world_rotation @ offset)[..., 0]).reshape(shape)
    raybundle.directions = directions.reshape(shape)


def train_camera_raybundle(refiner: CameraRefiner, index: int, downscale: int = 1) -> RayBundle:
    """Full-image rays [H, W] of training camera ``index`` through its refined camera, skew included.

    nerfstudio's Cameras cannot represent skew, so rendering a refined training view goes through here.
    """
    refiner.require_cameras()
    width = int(refiner.base_intrinsics[index, 7]) // downscale
    height = int(refiner.base_intrinsics[index, 8]) // downscale
    device = refiner.precond.device
    ys, xs = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    pixels = torch.stack([xs + 0.5, ys + 0.5], dim=-1).reshape(-1, 2).to(torch.float32) * downscale  # [H W, 2]
    camera_indices = torch.full((pixels.shape[0],), index, dtype=torch.long, device=device)
    with torch.no_grad():
        origins, directions, directions_norm = regenerate_rays(refiner, camera_indices, pixels)
    refined = refiner.refined_intrinsics().detach()
    pixel_area = torch.full_like(directions_norm, float(downscale**2 / (refined.fx[index] * refined.fy[index])))
    return RayBundle(
        origins=origins.reshape(height, width, 3),
        directions=directions.reshape(height, width, 3),
        pixel_area=pixel_area.reshape(height, width, 1),
        camera_indices=camera_indices.reshape(height, width, 1),
        metadata={"directions_norm": directions_norm.reshape(height, width, 1)},
    )


__all__ = ["PIXEL_KEY", "apply_pixel_rays", "apply_pose_only", "regenerate_rays", "train_camera_raybundle"]
