"""Visual-inertial drift of the training cameras, the benchmarks' "phone" start.

The errors of visual-inertial odometry (VIO) poses, such as the ARKit / ARCore poses that phone capture apps (Polycam,
Record3D) export. VIO observes roll and pitch through gravity, and leaves global position and yaw (rotation about
gravity) unobservable: the four unobservable directions of vision-aided inertial navigation (Hesch, Kottas, Bowman and
Roumeliotis, "Consistency analysis and improvement of vision-aided inertial navigation", IEEE T-RO 2014). So position
and yaw errors accumulate along the capture while roll and pitch stay small. The model, for cameras k = 0 .. N-1 in
capture order (the order given; the generated ring scenes are captured in image order), with OpenCV camera-to-world
poses [R_k | c_k] and the world's unit up vector u (``DriftConfig.up``):

- position: a random walk from the first camera, e_0 = 0, e_k = e_{k-1} + sigma_p w_k with w_k ~ N(0, I_3), so
  E|e_k|^2 = 3 k sigma_p^2. sigma_p = position_drift L / sqrt(3 (N - 1)), L = sum_k |c_k - c_{k-1}| the distance the
  given cameras travel, makes the RMS error position_drift L sqrt(k / (N - 1)): zero at the first camera,
  position_drift L at the last. The walk is the integral of a stationary velocity error (VIO observes velocity, not
  position); isotropic (an assumption: no separate vertical size);
- yaw: a random walk psi_0 = 0, psi_k = psi_{k-1} + sigma_psi n_k, n_k ~ N(0, 1), sigma_psi = yaw_drift / sqrt(N - 1):
  RMS yaw_drift sqrt(k / (N - 1)), a rotation about u through the camera centre;
- roll and pitch: independent per camera, uniform in [-tilt, tilt] each (bounded; RMS tilt / sqrt(3)): pitch about the
  camera's horizontal right axis h1 = h2 x u, roll about its horizontal forward axis h2 (the optical axis z projected
  on the plane normal to u, normalized; a camera looking along u uses h1 = its x projected, h2 = u x h1). Positive
  pitch raises the optical axis; positive roll lowers the image's right side. Both axes lie in the plane normal to
  u, so the tilt moves the camera's gravity direction by sqrt(pitch^2 + roll^2) and nothing else does;
- R_k' = Exp(psi_k u) Exp(pitch_k h1_k + roll_k h2_k) R_k and c_k' = c_k + e_k (Exp: the rotation of a rotation
  vector; the yaw leaves the centre in place);
- focal length: one factor exp(n_f log1p(focal_error)), n_f ~ N(0, 1), for every image (one phone camera, one
  factory calibration), none per image.

The drift is applied after CamP's steps (``s2camp_ns.core.perturbation``, to their output) and draws from the same
seeded stream after all of CamP's draws, in this order: w (N - 1 rows of 3), n (N - 1), the tilts (N rows of pitch,
roll), n_f. CamP's draws, and so its result, are the same whether the drift is on or off; with the drift off its code
does not run. For the drift alone, set CamP's four sigmas to zero (its steps then return the cameras to rounding).
The benchmarks' data parser (``data_parser``) applies it to the training cameras of the "phone" start.

The default sizes (``DriftConfig``) and what each rests on: docs/benchmarks/phone-drift.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.compat import DefaultsOnLoad
from s2camp_ns.core.camera import se3_exp
from s2camp_ns.core.perturbation import PerturbationConfig, PerturbedCameras, perturb_cameras
from s2camp_ns.core.validation import check_range


@dataclass
class DriftConfig(DefaultsOnLoad):
    """Visual-inertial odometry drift (module docstring); off by default. Sizes are RMS values at the last camera,
    except ``tilt_deg`` (a bound) and ``focal_error`` (a log-normal sigma); the defaults stand for a phone's ARKit /
    ARCore poses (docs/benchmarks/phone-drift.md)."""

    enabled: bool = False
    """Add the drift to the perturbed cameras (needs ``perturbation.enabled``; after CamP's steps)."""
    position_drift: float = 0.01
    """RMS position error at the last camera as a fraction of the distance the cameras travel (the sum of the
    distances between consecutive centres, in capture order)."""
    yaw_drift_deg: float = 1.5
    """RMS yaw error (degrees, about ``up``) at the last camera."""
    tilt_deg: float = 0.3
    """Bound (degrees) of each camera's roll and pitch errors, each uniform in [-tilt_deg, tilt_deg]."""
    focal_error: float = 0.015
    """Relative size of the one focal error shared by all images: focal scales by exp(N(0,1) log1p(focal_error))."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """World up (gravity opposite), normalized before use; +z in the frame the S2CamP data parser perturbs in."""

    def validate(self) -> None:
        check_range("drift.position_drift", self.position_drift, low=0.0, high=1.0)
        check_range("drift.yaw_drift_deg", self.yaw_drift_deg, low=0.0, high=180.0)
        check_range("drift.tilt_deg", self.tilt_deg, low=0.0, high=10.0)
        check_range("drift.focal_error", self.focal_error, low=0.0, high=0.5)
        up = tuple(self.up)
        if len(up) != 3 or not all(math.isfinite(float(v)) for v in up) or math.hypot(*map(float, up)) < 1e-9:
            raise ValueError(f"drift.up must be 3 finite numbers of norm > 0, got {self.up!r}")


def _rotation_exp(omega: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3 3"]:
    """Rotation matrices of rotation vectors (exactly the identity for a zero vector)."""
    return se3_exp(torch.cat([torch.zeros_like(omega), omega], dim=-1))[:, :, :3]


def _horizontal_axes(rotation: Float[Tensor, "n 3 3"], up: Float[Tensor, " 3"]) -> tuple[Tensor, Tensor]:
    """Each camera's horizontal right h1 and horizontal forward h2 axes, unit vectors normal to ``up`` with
    h1 = h2 x up: h2 is the optical axis projected on the horizontal plane; a camera looking along ``up`` takes h1
    from its x axis instead (module docstring). Shapes [N, 3]."""
    forward, right = rotation[:, :, 2], rotation[:, :, 0]
    forward_h = forward - (forward @ up)[:, None] * up  # [n, 3]
    right_h = right - (right @ up)[:, None] * up  # [n, 3]
    forward_norm = torch.linalg.norm(forward_h, dim=-1, keepdim=True)
    along_up = forward_norm < 1e-9  # [n, 1]
    h2_forward = forward_h / forward_norm.clamp_min(1e-300)
    h1_right = right_h / torch.linalg.norm(right_h, dim=-1, keepdim=True).clamp_min(1e-300)
    up_n = up.expand_as(forward)
    h1 = torch.where(along_up, h1_right, torch.linalg.cross(h2_forward, up_n, dim=-1))
    h2 = torch.where(along_up, torch.linalg.cross(up_n, h1_right, dim=-1), h2_forward)
    return h1, h2


def vio_drift(
    rotation: Float[Tensor, "n 3 3"], centre: Float[Tensor, "n 3"], given_centre: Float[Tensor, "n 3"],
    config: DriftConfig, generator: torch.Generator,
) -> tuple[Float[Tensor, "n 3 3"], Float[Tensor, "n 3"], Float[Tensor, " n"]]:
    """The visual-inertial drift of the module docstring applied to float64 CPU cameras [rotation | centre], in
    capture order; ``given_centre`` (the cameras before any perturbation) sets the distance travelled L. Returns the
    new rotations, centres and the shared focal factor (repeated per camera). Draws in the documented order."""
    n = rotation.shape[0]
    steps = max(n - 1, 1)  # no step for a single camera: its drift is zero
    up = torch.tensor(config.up, dtype=torch.float64)
    up = up / torch.linalg.norm(up)
    travelled = torch.linalg.norm(given_centre[1:] - given_centre[:-1], dim=-1).sum()  # L, scalar

    sigma_position = config.position_drift * travelled / math.sqrt(3 * steps)
    position_steps = torch.randn(n - 1, 3, dtype=torch.float64, generator=generator)  # w_k, [n - 1, 3]
    position_error = torch.cat([centre.new_zeros(1, 3), torch.cumsum(sigma_position * position_steps, dim=0)])

    sigma_yaw = math.radians(config.yaw_drift_deg) / math.sqrt(steps)
    yaw_steps = torch.randn(n - 1, dtype=torch.float64, generator=generator)  # n_k, [n - 1]
    yaw = torch.cat([centre.new_zeros(1), torch.cumsum(sigma_yaw * yaw_steps, dim=0)])  # psi_k, [n]

    tilt_draw = torch.rand(n, 2, dtype=torch.float64, generator=generator)  # [n, 2]: pitch, roll in [0, 1)
    tilt = math.radians(config.tilt_deg) * (2.0 * tilt_draw - 1.0)  # [n, 2] in [-tilt, tilt)
    h1, h2 = _horizontal_axes(rotation, up)
    tilt_vector = tilt[:, :1] * h1 + tilt[:, 1:] * h2  # [n, 3], normal to up

    focal_draw = torch.randn(1, dtype=torch.float64, generator=generator)
    focal = torch.exp(focal_draw * math.log1p(config.focal_error)).expand(n).clone()  # [n], one value

    new_rotation = _rotation_exp(yaw[:, None] * up) @ _rotation_exp(tilt_vector) @ rotation
    return new_rotation, centre + position_error, focal


def perturb_with_drift(
    c2w: Float[Tensor, "n 3 4"], fx: Float[Tensor, " n"], fy: Float[Tensor, " n"], config: PerturbationConfig,
    drift: DriftConfig,
) -> PerturbedCameras:
    """CamP's perturbation of OpenCV cameras (``perturb_cameras``, seeded with ``config.seed``), then the drift drawn
    from the same stream (module docstring). The result is on the CPU."""
    drift.validate()
    generator = torch.Generator(device="cpu").manual_seed(int(config.seed))
    camp = perturb_cameras(c2w, fx, fy, config, generator=generator)
    given = c2w.detach().to(device="cpu", dtype=torch.float64)
    c2w_camp = camp.c2w.cpu()
    rotation, centre, focal = vio_drift(c2w_camp[:, :, :3], c2w_camp[:, :, 3], given[:, :, 3], drift, generator)
    focal_scale = camp.focal_scale.cpu() * focal
    return PerturbedCameras(
        c2w=torch.cat([rotation, centre[:, :, None]], dim=-1),
        fx=fx.detach().to(device="cpu", dtype=torch.float64) * focal_scale,
        fy=fy.detach().to(device="cpu", dtype=torch.float64) * focal_scale,
        focal_scale=focal_scale, dolly_scale=camp.dolly_scale.cpu(),
    )


__all__ = ["DriftConfig", "perturb_with_drift", "vio_drift"]
