"""Between nerfstudio ``Cameras`` and the core's cameras (``Intrinsics``, OpenCV c2w), mapped explicitly.

nerfstudio's distortion_params are [k1, k2, k3, k4, p1, p2]. PERSPECTIVE cameras: k1, k2, k3, p1, p2 are OpenCV's
(the radial-tangential model of ``core.camera``) plus a polynomial r^8 term k4 that no COLMAP model has (nerfstudio
issue 3355) and that must be zero; FISHEYE cameras' [k1, k2, k3, k4, 0, 0] are OPENCV_FISHEYE's k1..k4. Cameras
S2CamP cannot represent are refused with a ValueError that names what is allowed.
"""

from __future__ import annotations

import warnings

import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras, CameraType
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, opengl_to_opencv, se3_exp
from s2camp_ns.core.colmap_camera_models import SUPPORTED_COLMAP_MODELS
from s2camp_ns.core.refiner import CameraRefiner
from s2camp_ns.data.camera_fields import replace_cameras

SUPPORTED_CAMERA_TYPES = {
    CameraType.PERSPECTIVE.value: "perspective",
    CameraType.FISHEYE.value: "fisheye",
}
"""nerfstudio camera types S2CamP refines, and the core projection each one is."""


def group_identical_intrinsics(cameras: Cameras) -> Tensor:
    """Physical-camera id per camera: cameras with identical intrinsics, distortion, size and type share one."""
    n = cameras.shape[0]
    columns = [getattr(cameras, name).reshape(n, -1).to(torch.float64).cpu() for name in ("fx", "fy", "cx", "cy")]
    columns += [cameras.width.reshape(n, -1).double().cpu(), cameras.height.reshape(n, -1).double().cpu()]
    columns.append(cameras.camera_type.reshape(n, -1).double().cpu())
    if cameras.distortion_params is not None:
        columns.append(cameras.distortion_params.reshape(n, -1).to(torch.float64).cpu())
    _, ids = torch.unique(torch.cat(columns, dim=-1), dim=0, return_inverse=True)
    return ids


def _supported_types_message() -> str:
    return (
        "supported are PERSPECTIVE (COLMAP "
        + ", ".join(m for m in SUPPORTED_COLMAP_MODELS if "FISHEYE" not in m)
        + " with k4 = k5 = k6 = 0) and FISHEYE (COLMAP OPENCV_FISHEYE)"
    )


def projection_of(cameras: Cameras) -> str:
    """The core projection ("perspective" or "fisheye") of nerfstudio cameras; ValueError naming any camera type
    S2CamP cannot refine (equirectangular, omnidirectional, orthographic, ...) or a mix of types."""
    types = sorted({int(t) for t in cameras.camera_type.reshape(-1).tolist()})
    unsupported = [CameraType(t).name for t in types if t not in SUPPORTED_CAMERA_TYPES]
    if unsupported:
        raise ValueError(
            f"camera type {', '.join(unsupported)} is not supported by S2CamP's camera refinement; "
            + _supported_types_message()
        )
    if len(types) > 1:
        raise ValueError(
            f"cameras mix the types {[CameraType(t).name for t in types]}; S2CamP refines one camera type per scene"
        )
    return SUPPORTED_CAMERA_TYPES[types[0]]


def intrinsics_from_cameras(cameras: Cameras, dtype: torch.dtype = torch.float64) -> Intrinsics:
    """Base intrinsics of nerfstudio cameras, mapped explicitly; raises ValueError for cameras S2CamP cannot represent.

    nerfstudio's distortion_params are [k1, k2, k3, k4, p1, p2]. PERSPECTIVE: k1, k2, k3, p1, p2 are OpenCV's (the
    radial-tangential model of ``core.camera``); k4 multiplies r^8 in nerfstudio, which no COLMAP model can hold
    (FULL_OPENCV's k4 is a rational coefficient, nerfstudio issue 3355), so it must be zero. FISHEYE: k1..k4 are
    OPENCV_FISHEYE's (theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8), what nerfstudio renders) and p1, p2,
    which OpenCV's fisheye model lacks, must be zero.
    """
    projection = projection_of(cameras)
    n = cameras.shape[0]
    params = torch.zeros(n, 6, dtype=dtype)
    if cameras.distortion_params is not None:
        params = cameras.distortion_params.reshape(n, 6).to(dtype).cpu()
    if projection == "perspective":
        reason = "a polynomial r^8 term in nerfstudio; COLMAP FULL_OPENCV's k4 divides instead (nerfstudio issue 3355)"
        must_be_zero = [(3, "k4", reason)]
    else:
        reason = "OPENCV_FISHEYE has no tangential terms"
        must_be_zero = [(4, "p1", reason), (5, "p2", reason)]
    for column, name, reason in must_be_zero:
        if bool((params[:, column] != 0).any()):
            i = int(torch.nonzero(params[:, column] != 0)[0])
            raise ValueError(
                f"distortion parameter {name} = {params[i, column].item():g} of {projection} camera {i} is not "
                f"supported ({reason}); allowed is {name} = 0"
            )
    k1, k2, k3, k4, p1, p2 = params.unbind(dim=-1)
    return Intrinsics.create(
        fx=cameras.fx.reshape(n).cpu(),
        fy=cameras.fy.reshape(n).cpu(),
        cx=cameras.cx.reshape(n).cpu(),
        cy=cameras.cy.reshape(n).cpu(),
        width=cameras.width.reshape(n).cpu(),
        height=cameras.height.reshape(n).cpu(),
        k1=k1,
        k2=k2,
        k3=k3,
        k4=k4 if projection == "fisheye" else 0.0,
        p1=p1 if projection == "perspective" else 0.0,
        p2=p2 if projection == "perspective" else 0.0,
        model=projection,
        dtype=dtype,
    )


def nerfstudio_distortion(intrinsics: Intrinsics) -> Float[Tensor, "n 6"]:
    """nerfstudio's distortion_params [k1, k2, k3, k4, p1, p2] of ``intrinsics`` (the inverse of
    ``intrinsics_from_cameras``): the same slots for both projections, p1 = p2 = 0 for fisheye cameras."""
    zeros = torch.zeros_like(intrinsics.k1)
    tangential = (zeros, zeros) if intrinsics.is_fisheye else (intrinsics.p1, intrinsics.p2)
    return torch.stack([intrinsics.k1, intrinsics.k2, intrinsics.k3, intrinsics.k4, *tangential], dim=-1)


def opengl_pose_correction(deltas: Float[Tensor, "m 16"]) -> Float[Tensor, "m 3 4"]:
    """Pose corrections D with c2w_gl' = c2w_gl D in nerfstudio's OpenGL camera frame, of the local twists
    deltas[:, :6] (c2w_cv' = c2w_cv E, E = exp(xi)): c2w_gl' = c2w_cv E F = c2w_gl (F E F), F = diag(1, -1, -1), so
    E's rows and columns 1, 2 flip."""
    correction = opengl_to_opencv(se3_exp(deltas[:, :6]))  # [m, 3, 4]
    correction[:, 1:3, :] = -correction[:, 1:3, :]
    return correction


def compose_poses(c2w: Float[Tensor, "m 3 4"], correction: Float[Tensor, "m 3 4"]) -> Float[Tensor, "m 3 4"]:
    """c2w D for rigid transforms [R | t] stored as [m, 3, 4]: rotation R R_D, translation t + R t_D."""
    rotation = c2w[:, :, :3] @ correction[:, :, :3]
    translation = c2w[:, :, 3:] + c2w[:, :, :3] @ correction[:, :, 3:]
    return torch.cat([rotation, translation], dim=-1)


@torch.no_grad()
def refined_nerfstudio_cameras(refiner: CameraRefiner, cameras: Cameras, indices: Tensor | None = None) -> Cameras:
    """nerfstudio Cameras of the training cameras ``indices`` (of ``cameras``, the refiner's images) with refined
    pose, fx, fy, cx, cy and distortion (``nerfstudio_distortion``: nerfstudio's [k1, k2, k3, k4, p1, p2] meaning).

    Skew is not representable in nerfstudio's Cameras and is dropped here (a warning says so when nonzero).
    """
    refiner.require_cameras()
    indices = torch.arange(refiner.num_images) if indices is None else indices.reshape(-1).cpu()
    deltas = refiner.deltas()
    intrinsics = refiner.refined_intrinsics(deltas)[indices.to(refiner.precond.device)]
    if bool((intrinsics.skew.abs() > 1e-6).any()):
        warnings.warn("refined skew is dropped: nerfstudio Cameras cannot represent skew", stacklevel=3)
    c2w = refiner.refined_c2w(deltas, opengl=True)[indices.to(refiner.precond.device)]
    selected = cameras[indices]
    distortion = nerfstudio_distortion(intrinsics).cpu()
    device = selected.device
    return replace_cameras(
        selected,
        camera_to_worlds=c2w.to(device=device, dtype=torch.float32),
        fx=intrinsics.fx[:, None].to(device=device, dtype=torch.float32),
        fy=intrinsics.fy[:, None].to(device=device, dtype=torch.float32),
        cx=intrinsics.cx[:, None].to(device=device, dtype=torch.float32),
        cy=intrinsics.cy[:, None].to(device=device, dtype=torch.float32),
        distortion_params=distortion.to(device=device, dtype=torch.float32),
    )


__all__ = [
    "SUPPORTED_CAMERA_TYPES",
    "compose_poses",
    "group_identical_intrinsics",
    "intrinsics_from_cameras",
    "nerfstudio_distortion",
    "opengl_pose_correction",
    "projection_of",
    "refined_nerfstudio_cameras",
]
