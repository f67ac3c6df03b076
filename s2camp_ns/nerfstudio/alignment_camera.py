"""The held-out camera of test-time alignment and its two variables (``test_time_alignment``'s module docstring).

A held-out view starts from an OpenGL camera-to-world matrix (nerfstudio's convention) in the model's frame and
its intrinsics; the alignment moves it by a local se(3) twist, c2w' = c2w exp(xi) in the OpenCV camera frame (the
S2CamP camera model, ``core.camera``), and scales its focal lengths by exp(log_focal). Shared by the ray renderer
(nerfacto models, ``ray_alignment``) and the splat renderer (``splat_alignment``).
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
    """OpenCV camera-to-world c2w exp(twist) of an OpenGL ``c2w_gl``, in float64, differentiable in ``twist``
    (rho, omega: ``core.camera.se3_exp``)."""
    c2w_cv = opengl_to_opencv(c2w_gl.double())
    delta = se3_exp(twist.double())
    rotation = c2w_cv[:, :3] @ delta[:, :3]
    centre = c2w_cv[:, 3] + c2w_cv[:, :3] @ delta[:, 3]
    return torch.cat([rotation, centre[:, None]], dim=-1)


__all__ = ["HeldOutView", "scale_focal", "twisted_c2w"]
