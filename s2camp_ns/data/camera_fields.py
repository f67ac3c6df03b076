"""Copies of nerfstudio ``Cameras`` with some fields replaced (nerfstudio's Cameras has no such method)."""

from __future__ import annotations

import torch
from jaxtyping import Int
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from s2camp_ns.core.shared_intrinsics import mean_per_camera


def replace_cameras(cameras: Cameras, **fields) -> Cameras:
    """A copy of ``cameras`` with the given fields replaced."""
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
    """Whether any of ``cameras`` has a non-zero distortion coefficient."""
    return cameras.distortion_params is not None and bool((cameras.distortion_params != 0).any())


def physical_camera_means(cameras: Cameras, camera_ids: Int[Tensor, " n"]) -> Cameras:
    """A copy of ``cameras`` in which each image holds the mean fx, fy, cx, cy and distortion over its physical
    camera's images (``camera_ids`` [n]): where shared intrinsics start from."""
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
