"""Copies of nerfstudio ``Cameras`` with some fields replaced (nerfstudio's Cameras has no such method)."""

from __future__ import annotations

import torch
from jaxtyping import Int
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from s2camp_ns.core.shared_intrinsics import mean_per_camera


def replace_cameras(cameras: Cameras, **fields) -> Cameras:
    """A copy of ``cameras`` with the given fields replaced (nerfstudio's Cameras has no such method)."""
    values = dict(
        camera_to_worlds=cameras.camera_to_worlds,
        fx=cameras.fx,
        fy=cameras.fy,
        cx=cameras.cx,
        cy=cameras.cy,
        width=cameras.width,
        height=cameras.height,
        distortion_params=cameras.distortion_params,
        camera_type=cameras.camera_type,
        times=cameras.times,
        metadata=cameras.metadata,
    )
    values.update(fields)
    return Cameras(**values)


def has_distortion(cameras: Cameras) -> bool:
    """Whether any of ``cameras`` has a non-zero distortion coefficient (what a full-image data manager undistorts)."""
    return cameras.distortion_params is not None and bool((cameras.distortion_params != 0).any())


def physical_camera_means(cameras: Cameras, camera_ids: Int[Tensor, " n"]) -> Cameras:
    """A copy of ``cameras`` in which every image of a physical camera (``camera_ids``, one per image) holds the mean
    over those images of fx, fy, cx, cy and the distortion: the intrinsics a refiner that shares them starts from
    (``core.refiner``). Images that agree already (SfM's cameras) are unchanged up to rounding; a per-image
    perturbation of the focal length (CamP's) averages out. Poses, sizes and types are kept."""
    n = cameras.shape[0]
    ids = torch.as_tensor(camera_ids, dtype=torch.long).reshape(-1).cpu()
    if ids.shape[0] != n:
        raise ValueError(f"camera_ids must hold {n} entries (one per image), got {ids.shape[0]}")
    num_cameras = int(ids.max()) + 1 if n else 0

    def mean(values: Tensor | None) -> Tensor | None:
        if values is None:
            return None
        flat = values.reshape(n, -1).to("cpu", torch.float64)  # [n, d]
        return mean_per_camera(flat, ids, num_cameras).reshape(values.shape).to(values)

    fields = {name: mean(getattr(cameras, name)) for name in ("fx", "fy", "cx", "cy", "distortion_params")}
    return replace_cameras(cameras, **fields)


__all__ = ["has_distortion", "physical_camera_means", "replace_cameras"]
