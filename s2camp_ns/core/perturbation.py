"""CamP's camera perturbation protocol (its configs/camp/camera_optim_perturbed.gin), to test recovery from bad
cameras.

The training images of a normalized scene are perturbed in this order, with one seeded random stream:

1. dolly zoom: the z of every world-to-camera translation t = -R^T c and the focal lengths scale by one shared
   s = exp(N(0, 1) log1p(sigma_dolly_z)), the centre recomputed: objects near the origin keep their image size;
2. focal length: each image's focal lengths scale by its own exp(N(0, 1) log1p(sigma_focal_length));
3. position: each centre moves by sigma_position times a random unit vector;
4. orientation: the look-at point (the optical axis' point closest to the origin, after step 1) moves by
   sigma_look_at times a random unit vector and the camera is re-aimed at it from its new centre, same up vector;
5. radial distortion is zeroed (by the caller, which owns the distortion parameters).

Sigmas are in normalized scene units; cameras are OpenCV (x right, y down, z forward). Configs of earlier versions:
``s2camp_ns.compat``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.compat import DefaultsOnLoad, old_names, refuse_removed_fields
from s2camp_ns.core.validation import check_finite, check_range


@dataclass
class PerturbationConfig(DefaultsOnLoad):
    """CamP's camera perturbation; the defaults are its ``camera_optim_perturbed`` setting."""

    enabled: bool = False
    """Perturb the training cameras (an evaluation protocol; off for normal training)."""
    sigma_look_at: float = 0.005
    """Distance (normalized scene units) the look-at point moves, along a random direction."""
    sigma_position: float = 0.005
    """Distance (normalized scene units) the camera centre moves, along a random direction."""
    sigma_dolly_z: float = 0.05
    """Shared dolly zoom: the z translation and the focal lengths scale by exp(N(0,1) log1p(sigma))."""
    sigma_focal_length: float = 0.02
    """Per-image focal length change: focal scales by exp(N(0,1) log1p(sigma))."""
    seed: int = 0
    """Seed of the random stream; the same seed and cameras give the same perturbation."""

    def validate(self) -> None:
        for name in ("sigma_look_at", "sigma_position", "sigma_dolly_z", "sigma_focal_length"):
            check_range(f"perturbation.{name}", getattr(self, name), low=0.0)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"perturbation.seed must be an integer in [0, inf), got {self.seed!r}")
        refuse_removed_fields("perturbation", self)


@dataclass
class PerturbedCameras:
    """Result of ``perturb_cameras``: float64, leading dimension N."""

    c2w: Float[Tensor, "n 3 4"]
    """Perturbed OpenCV camera-to-world poses."""
    fx: Float[Tensor, " n"]
    """Perturbed focal lengths (pixels)."""
    fy: Float[Tensor, " n"]
    focal_scale: Float[Tensor, " n"]
    """Total factor applied to both focal lengths (dolly times focal perturbation)."""
    dolly_scale: Float[Tensor, " n"]
    """Factor applied to the world-to-camera z translation (one value shared by all cameras)."""


def _unit_vectors(n: int, generator: torch.Generator) -> Tensor:
    directions = torch.randn(n, 3, dtype=torch.float64, generator=generator)
    return directions / torch.linalg.norm(directions, dim=-1, keepdim=True).clamp_min(1e-300)


def look_at_rotation(
    eye: Float[Tensor, "n 3"], target: Float[Tensor, "n 3"], up: Float[Tensor, "n 3"]
) -> Float[Tensor, "n 3 3"]:
    """Camera-to-world rotation of an OpenCV camera at ``eye`` looking at ``target``, ``up`` the world up: columns
    z = unit forward, x = z cross up (image right), y = z cross x (image down)."""
    forward = target - eye
    norm = torch.linalg.norm(forward, dim=-1, keepdim=True)
    if bool((norm < 1e-12).any()):
        raise ValueError("look-at target coincides with the camera centre; cannot aim the camera")
    z = forward / norm
    x = torch.linalg.cross(z, up, dim=-1)
    x_norm = torch.linalg.norm(x, dim=-1, keepdim=True)
    if bool((x_norm < 1e-12).any()):
        raise ValueError("camera up vector is parallel to its viewing direction; cannot aim the camera")
    x = x / x_norm
    y = torch.linalg.cross(z, x, dim=-1)
    return torch.stack([x, y, z], dim=-1)


def perturb_cameras(
    c2w: Float[Tensor, "n 3 4"],
    fx: Float[Tensor, " n"],
    fy: Float[Tensor, " n"] | None = None,
    config: PerturbationConfig | None = None,
    seed: int | None = None,
    generator: torch.Generator | None = None,
) -> PerturbedCameras:
    """Perturb OpenCV cameras with CamP's protocol (module docstring), ignoring ``config.enabled``. ``seed``
    overrides ``config.seed``; ``generator``: a CPU stream to draw from instead of a new seeded one. Computed in
    float64 on the CPU (the same on every machine), returned on the input device."""
    config = config or PerturbationConfig()
    config.validate()
    seed = config.seed if seed is None else seed
    if c2w.ndim != 3 or c2w.shape[1:] != (3, 4):
        raise ValueError(f"c2w must have shape [N, 3, 4], got {tuple(c2w.shape)}")
    n = c2w.shape[0]
    fy = fx if fy is None else fy
    if fx.shape != (n,) or fy.shape != (n,):
        raise ValueError(f"fx and fy must have shape [{n}], got {tuple(fx.shape)} and {tuple(fy.shape)}")
    check_finite("c2w", c2w)
    check_range("fx", fx, low=0.0, low_inclusive=False)
    check_range("fy", fy, low=0.0, low_inclusive=False)
    device = c2w.device
    c2w = c2w.detach().to(device="cpu", dtype=torch.float64)
    fx = fx.detach().to(device="cpu", dtype=torch.float64)
    fy = fy.detach().to(device="cpu", dtype=torch.float64)
    if generator is None:
        generator = torch.Generator(device="cpu").manual_seed(int(seed))
    rotation, centre = c2w[:, :, :3], c2w[:, :, 3]
    # World-to-camera translation t = -R^T c: its z is the depth of the world origin in front of the camera.
    translation = -torch.einsum("nji,nj->ni", rotation, centre)
    # 1. Dolly zoom (always draw, so the later draws do not depend on whether it is enabled).
    dolly_draw = torch.randn(1, dtype=torch.float64, generator=generator)
    dolly_scale = torch.exp(dolly_draw * math.log1p(config.sigma_dolly_z)).expand(n).clone()
    translation = translation.clone()
    translation[:, 2] = translation[:, 2] * dolly_scale
    centre = -torch.einsum("nij,nj->ni", rotation, translation)
    # 2. Focal length, per camera.
    focal_draw = torch.randn(n, dtype=torch.float64, generator=generator)
    focal_scale = dolly_scale * torch.exp(focal_draw * math.log1p(config.sigma_focal_length))
    # 3. Position.
    new_centre = centre + config.sigma_position * _unit_vectors(n, generator)
    # 4. Look-at point: the optical-axis point closest to the origin, from the dollied centre; unlike CamP, mirrored
    # in front of a camera that looks away from the origin (unit distance when it is the centre itself).
    axis = rotation[:, :, 2]
    depth = -(centre * axis).sum(dim=-1)
    depth = torch.where(depth.abs() > 1e-9, depth.abs(), torch.ones_like(depth))
    look_at = centre + depth[:, None] * axis
    look_at = look_at + config.sigma_look_at * _unit_vectors(n, generator)
    up = -rotation[:, :, 1]  # OpenCV y points down in the image
    new_rotation = look_at_rotation(new_centre, look_at, up)
    new_c2w = torch.cat([new_rotation, new_centre[:, :, None]], dim=-1)
    return PerturbedCameras(
        c2w=new_c2w.to(device),
        fx=(fx * focal_scale).to(device),
        fy=(fy * focal_scale).to(device),
        focal_scale=focal_scale.to(device),
        dolly_scale=dolly_scale.to(device),
    )


__getattr__ = old_names(__name__)  # names of earlier versions' configs (s2camp_ns.compat.RENAMED)
