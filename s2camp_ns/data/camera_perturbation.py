"""CamP's perturbation (``core.perturbation``) applied to nerfstudio's (OpenGL, normalized) training cameras."""

from __future__ import annotations

from collections.abc import Callable

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from s2camp_ns.core.camera import opengl_to_opencv
from s2camp_ns.core.perturbation import PerturbationConfig, PerturbedCameras, perturb_cameras
from s2camp_ns.data.camera_conversion import SUPPORTED_CAMERA_TYPES
from s2camp_ns.data.camera_fields import replace_cameras

Perturb = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, PerturbationConfig], PerturbedCameras]
"""A perturbation of OpenCV cameras: (c2w [N, 3, 4], fx [N], fy [N], config) -> ``PerturbedCameras`` (float64)."""


def perturb_nerfstudio_cameras(
    cameras: Cameras, config: PerturbationConfig, perturb: Perturb = perturb_cameras
) -> Cameras:
    """nerfstudio (OpenGL) cameras perturbed by CamP's protocol (or ``perturb``), their distortion zeroed;
    perspective and fisheye cameras only (poses and focal lengths mean the same in both), else ValueError."""
    unsupported = sorted({int(t) for t in cameras.camera_type.reshape(-1).tolist()} - set(SUPPORTED_CAMERA_TYPES))
    if unsupported:
        names = ", ".join(CameraType(t).name for t in unsupported)
        raise ValueError(f"the camera perturbation supports PERSPECTIVE and FISHEYE cameras, got {names}")
    c2w = opengl_to_opencv(cameras.camera_to_worlds.double())
    out = perturb(c2w, cameras.fx[:, 0].double(), cameras.fy[:, 0].double(), config)
    dtype = cameras.camera_to_worlds.dtype
    distortion = cameras.distortion_params
    return replace_cameras(
        cameras,
        camera_to_worlds=opengl_to_opencv(out.c2w).to(dtype),
        fx=out.fx[:, None].to(cameras.fx.dtype),
        fy=out.fy[:, None].to(cameras.fy.dtype),
        distortion_params=None if distortion is None else torch.zeros_like(distortion),
    )


__all__ = ["Perturb", "perturb_nerfstudio_cameras"]
