"""The held-out camera of test-time alignment and its variables: an OpenGL c2w in the field's frame moved by a local
se(3) twist (c2w' = c2w exp(xi), OpenCV camera frame), its focal lengths scaled by exp(log_focal).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, opengl_to_opencv, se3_exp


@dataclass
class HeldOutView:
    """A held-out image and its camera in the field's frame (the start of the alignment)."""

    image: Float[Tensor, "h w c"]
    c2w_gl: Float[Tensor, "3 4"]
    intrinsics: Intrinsics
    index: int = 0


def scale_focal(intrinsics: Intrinsics, factor: float | Tensor) -> Intrinsics:
    """The same camera with fx and fy multiplied by ``factor`` (differentiable in a tensor factor)."""
    return replace(intrinsics, fx=intrinsics.fx * factor, fy=intrinsics.fy * factor)


def twisted_c2w(c2w_gl: Float[Tensor, "3 4"], twist: Float[Tensor, 6]) -> Float[Tensor, "3 4"]:
    """OpenCV c2w exp(twist) (float64) of an OpenGL ``c2w_gl``; differentiable in ``twist`` (rho, omega)."""
    c2w_cv = opengl_to_opencv(c2w_gl.double())
    delta = se3_exp(twist.double())
    rotation = c2w_cv[:, :3] @ delta[:, :3]
    centre = c2w_cv[:, 3] + c2w_cv[:, :3] @ delta[:, 3]
    return torch.cat([rotation, centre[:, None]], dim=-1)


__all__ = ["HeldOutView", "scale_focal", "twisted_c2w"]
