"""Training rays cast through the refined cameras, once per step: pose and intrinsics really move the rays.

S2CamP's data manager (``PixelRayGenerator``) hands the model each ray's camera index and continuous pixel
coordinates (``ray_bundle.metadata[PIXEL_KEY]``) without casting it through the data parser's cameras; the camera
optimizer casts it here, through the refined cameras, differentiably (``cast_rays``). A step then costs one product
for every image's deltas, one for their refined intrinsics and pose, and the per-ray unprojection of the cameras'
declared form (``CameraRefiner.distortion_terms``: no Newton iteration without distortion), with no host read: the
whole function captures as one graph (tests/test_step_path.py). Rays without pixels (a stock data manager) can
only follow the pose (``apply_pose_only``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, pixel_to_ray_direction
from s2camp_ns.core.refiner import CameraRefiner

PIXEL_KEY = "s2camp_pixels"
"""RayBundle metadata key of the continuous pixel coordinates (u, v) = (x + 0.5, y + 0.5) of each training ray."""


@dataclass(frozen=True)
class CastRays:
    """Rays through pixels of refined cameras, world frame: origins and unit directions [r, 3]; ``directions_norm``
    [r, 1], nerfstudio's |(a, b, 1)| = 1 / d_z of the camera-frame direction (1 for fisheyes, whose directions are
    unit vectors already); ``pixel_area`` [r, 1], the solid angle of a pixel at the principal point, 1 / (fx fy) of
    the refined camera (nerfstudio's own rays take a per-ray finite difference; nerfacto and splatfacto read
    neither)."""

    origins: Float[Tensor, "r 3"]
    directions: Float[Tensor, "r 3"]
    directions_norm: Float[Tensor, "r 1"]
    pixel_area: Float[Tensor, "r 1"]


def cast_rays(
    refiner: CameraRefiner,
    camera_indices: Int[Tensor, " r"],
    pixels: Float[Tensor, "r 2"],
    dtype: torch.dtype = torch.float32,
) -> CastRays:
    """Rays through ``pixels`` of the refined cameras ``camera_indices`` (forward and backward, no host read).

    Every image's deltas, refined intrinsics and pose are computed once, in float64 (one batched product each, the
    cost of a few kernels whatever the number of images); each ray gathers its camera's and is unprojected in ``dtype``
    in the cameras' declared form. Autocast is disabled: undistortion and the pose product are not safe in half
    precision.
    """
    refiner.require_cameras()
    with torch.autocast(device_type=pixels.device.type, enabled=False):
        deltas = refiner.deltas()  # [n, 16]
        fields = refiner.refined_fields(deltas)  # [n, 13]
        c2w = refiner.refined_c2w(deltas)  # [n, 3, 4]
        indices = camera_indices.to(fields.device)
        per_ray = Intrinsics.from_tensors(fields[indices].to(dtype), refiner.projection, **refiner.intrinsics_form)
        directions_cam = pixel_to_ray_direction(pixels.to(dtype)[:, None, :], per_ray)[:, 0]  # [r, 3]
        c2w_rays = c2w[indices].to(dtype)  # [r, 3, 4]
        directions = (c2w_rays[:, :, :3] @ directions_cam[:, :, None])[..., 0]
        if per_ray.is_fisheye:
            directions_norm = torch.ones_like(directions_cam[:, 2:3])
        else:
            directions_norm = directions_cam[:, 2:3].reciprocal()
        pixel_area = (per_ray.fx * per_ray.fy).reciprocal()[:, None]
    return CastRays(c2w_rays[:, :, 3], directions, directions_norm, pixel_area)


def apply_pixel_rays(refiner: CameraRefiner, raybundle: RayBundle, pixels: Float[Tensor, "*batch 2"]) -> None:
    """Set the bundle's rays to those through its pixels of the refined cameras (pose AND intrinsics): origins,
    directions, pixel areas and ``directions_norm`` (``cast_rays``)."""
    shape = raybundle.camera_indices.shape[:-1]
    rays = cast_rays(refiner, raybundle.camera_indices.reshape(-1), pixels.reshape(-1, 2), raybundle.origins.dtype)
    raybundle.origins = rays.origins.reshape(*shape, 3)
    raybundle.directions = rays.directions.reshape(*shape, 3)
    raybundle.pixel_area = rays.pixel_area.reshape(*shape, 1)
    if raybundle.metadata is None:
        raybundle.metadata = {}
    raybundle.metadata["directions_norm"] = rays.directions_norm.reshape(*shape, 1)


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
        rays = cast_rays(refiner, camera_indices, pixels)
    return RayBundle(
        origins=rays.origins.reshape(height, width, 3),
        directions=rays.directions.reshape(height, width, 3),
        pixel_area=(rays.pixel_area * downscale**2).reshape(height, width, 1),
        camera_indices=camera_indices.reshape(height, width, 1),
        metadata={"directions_norm": rays.directions_norm.reshape(height, width, 1)},
    )


__all__ = ["PIXEL_KEY", "CastRays", "apply_pixel_rays", "apply_pose_only", "cast_rays", "train_camera_raybundle"]
