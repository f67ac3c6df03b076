"""Pixels to rays, the inverse of ``core.camera.project``, and the image's extent in ray space.

Pixels [N, L, 2] map to OpenCV camera-frame rays: ``unproject`` to undistorted tangents (x / z, y / z),
``pixel_to_ray_direction`` to unit directions (fisheye also beyond 90 degrees); both differentiable in the pixels and
the intrinsics (``core.distortion``'s inverses). ``tangent_bounds`` is the box of tangents landing in the image (the
paper's eq. 13 with an off-centre principal point and distortion), ``vertical_field_of_view`` the vertical angle.
"""

from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.distortion import distorted_coordinates, distortion_columns, undistort_scale, undistort_tangents


def _fisheye_directions(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 3"]:
    """Unit directions of fisheye pixels, theta from theta_d = |(a_d, b_d)| by ``undistort_scale``."""
    a_d, b_d = distorted_coordinates(pixels, intrinsics)
    theta_d2 = a_d * a_d + b_d * b_d
    k1, k2, k3, k4, _, _ = distortion_columns(intrinsics)
    if k1 is None:
        scale = torch.ones_like(theta_d2)
    else:  # theta / theta_d
        scale = undistort_scale(theta_d2, k1, k2, k3, k4, intrinsics.newton_iterations)
    theta = scale * torch.sqrt(torch.clamp(theta_d2, min=torch.finfo(theta_d2.dtype).tiny))
    # sin(theta) / theta_d = scale * sinc(theta), finite on the optical axis
    lateral = scale * torch.sinc(theta / math.pi)
    return torch.stack([a_d * lateral, b_d * lateral, torch.cos(theta)], dim=-1)


def unproject(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 2"]:
    """[n, l, 2] undistorted tangents (x/z, y/z) of the rays through pixels (fisheye: below 90 degrees only)."""
    if intrinsics.is_fisheye:
        directions = _fisheye_directions(pixels, intrinsics)
        return directions[..., :2] / directions[..., 2:]
    a_d, b_d = distorted_coordinates(pixels, intrinsics)
    a, b = undistort_tangents(a_d, b_d, intrinsics)
    return torch.stack([a, b], dim=-1)


def pixel_to_ray_direction(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 3"]:
    """[n, l, 3] unit camera-frame ray directions through pixels (fisheye: also beyond 90 degrees)."""
    if intrinsics.is_fisheye:
        return _fisheye_directions(pixels, intrinsics)
    tangents = unproject(pixels, intrinsics)
    directions = torch.cat([tangents, torch.ones_like(tangents[..., :1])], dim=-1)
    return directions / torch.linalg.norm(directions, dim=-1, keepdim=True)


def vertical_field_of_view(intrinsics: Intrinsics) -> Float[Tensor, " n"]:
    """[n] sum of the angles to the optical axis of the rays through the top and bottom edge at column cx."""
    zeros = torch.zeros_like(intrinsics.cx)
    edges = torch.stack([torch.stack([intrinsics.cx, zeros], -1), torch.stack([intrinsics.cx, intrinsics.height], -1)])
    directions = pixel_to_ray_direction(edges.transpose(0, 1), intrinsics)
    off_axis = torch.atan2(torch.linalg.norm(directions[..., :2], dim=-1), directions[..., 2])
    return off_axis.sum(dim=-1)


def tangent_bounds(intrinsics: Intrinsics, samples_per_edge: int = 129, inset: float = 1e-5) -> Float[Tensor, "n 4"]:
    """[n, 4] inner box (a_min, a_max, b_min, b_max) of tangents whose rays land in the image: the innermost
    unprojected border sample per edge, inset by ``inset`` of its size. ValueError for fisheye cameras."""
    if intrinsics.is_fisheye:
        raise ValueError(
            "tangent_bounds needs a perspective camera, got model 'fisheye': a fisheye's field of view has no "
            "tangent box; sample its image instead (preconditioner.sample_proxy_points does)"
        )
    n = intrinsics.num_cameras
    t = torch.linspace(0.0, 1.0, samples_per_edge, dtype=intrinsics.dtype, device=intrinsics.device)
    w, h = intrinsics.width[:, None], intrinsics.height[:, None]
    zeros = torch.zeros(n, samples_per_edge, dtype=intrinsics.dtype, device=intrinsics.device)
    edges = {
        "left": torch.stack([zeros, t * h], dim=-1),
        "right": torch.stack([zeros + w, t * h], dim=-1),
        "top": torch.stack([t * w, zeros], dim=-1),
        "bottom": torch.stack([t * w, zeros + h], dim=-1),
    }
    tangents = {name: unproject(pixels, intrinsics) for name, pixels in edges.items()}
    a_min, a_max = tangents["left"][..., 0].amax(dim=-1), tangents["right"][..., 0].amin(dim=-1)
    b_min, b_max = tangents["top"][..., 1].amax(dim=-1), tangents["bottom"][..., 1].amin(dim=-1)
    a_margin, b_margin = inset * (a_max - a_min), inset * (b_max - b_min)
    return torch.stack([a_min + a_margin, a_max - a_margin, b_min + b_margin, b_max - b_margin], dim=-1)
