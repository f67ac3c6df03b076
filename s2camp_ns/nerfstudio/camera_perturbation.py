"""CamP's perturbation (``core.perturbation``) applied to nerfstudio's (OpenGL, normalized) training cameras."""

from __future__ import annotations

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from s2camp_ns.core.camera import opengl_to_opencv
from s2camp_ns.core.perturbation import PerturbationConfig, perturb_cameras
from s2camp_ns.nerfstudio.camera_conversion import SUPPORTED_CAMERA_TYPES
from s2camp_ns.nerfstudio.camera_fields import replace_cameras


def perturb_nerfstudio_cameras(cameras: Cameras, config: PerturbationConfig) -> Cameras:
    """Apply the CamP perturbation to nerfstudio (OpenGL) cameras; zero their distortion if configured.

    Perspective and fisheye cameras: the protocol draws poses and focal lengths only, which both projections share
    (a fisheye's focal scales its image-space angle as a pinhole's scales its tangent); zeroed distortion leaves a
    fisheye equidistant.
    """
    unsupported = sorted({int(t) for t in cameras.camera_type.reshape(-1).tolist()} - set(SUPPORTED_CAMERA_TYPES))
    if unsupported:
        names = ", ".join(CameraType(t).name for t in unsupported)
        raise ValueError(f"the camera perturbation supports PERSPECTIVE and FISHEYE cameras, got {names}")
    c2w = opengl_to_opencv(cameras.camera_to_worlds.double())
    out = perturb_cameras(c2w, cameras.fx[:, 0].double(), cameras.fy[:, 0].double(), config)
    dtype = cameras.camera_to_worlds.dtype
    distortion = cameras.distortion_params
    if config.zero_distortion and distortion is not None:
        distortion = torch.zeros_like(distortion)
    return replace_cameras(
        cameras,
        camera_to_worlds=opengl_to_opencv(out.c2w).to(dtype),
        fx=out.fx[:, None].to(cameras.fx.dtype),
        fy=out.fy[:, None].to(cameras.fy.dtype),
        distortion_params=distortion,
    )


__all__ = ["perturb_nerfstudio_cameras"]
