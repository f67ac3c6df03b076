"""Camera model: pinhole with focal length, principal point, skew and radial k1, k2, plus a local se(3) pose delta.

Conventions (the same as COLMAP and pycolmap, so refined cameras export without conversion):

- camera frame: x right, y down, z forward;
- continuous pixel coordinates, the image covering [0, W] x [0, H] (the centre of pixel (i, j) is (i + .5, j + .5));
- undistorted image-plane tangents a = x / z, b = y / z; radial distortion scales them by
  1 + k1 r^2 + k2 r^4 with r^2 = a^2 + b^2 (COLMAP's RADIAL / OPENCV k1, k2);
- pixels u = fx a_d + s b_d + cx, v = fy b_d + cy (paper eq. 2 with the skew s and distortion added).

The K = 12 camera-parameter deltas of the paper (sec. 4, "Camera Parameterization") are ordered as
``PARAMETER_NAMES``: a local se(3) pose delta (rho, omega) applied on the right of the camera-to-world pose, then
focal length (pixels, added to fx and fy), principal point (pixels), skew (pixels) and k1, k2.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.validation import check_finite, check_range

PARAMETER_NAMES: tuple[str, ...] = (
    "rho_x",
    "rho_y",
    "rho_z",
    "omega_x",
    "omega_y",
    "omega_z",
    "focal",
    "cx",
    "cy",
    "skew",
    "k1",
    "k2",
)
NUM_CAMERA_PARAMS = len(PARAMETER_NAMES)

PARAMETER_GROUPS: dict[str, tuple[int, ...]] = {
    "pose": (0, 1, 2, 3, 4, 5),
    "focal": (6,),
    "principal_point": (7, 8),
    "skew": (9,),
    "distortion": (10, 11),
}

UNDISTORT_ITERATIONS = 20


@dataclass(frozen=True)
class ParameterLayout:
    """Which parameter groups are refined; the enabled columns keep the order of ``PARAMETER_NAMES``."""

    pose: bool = True
    focal: bool = True
    principal_point: bool = True
    skew: bool = True
    distortion: bool = True

    @classmethod
    def from_preset(cls, preset: str) -> ParameterLayout:
        """``"pose"``, ``"pose+focal"``, ``"pose+intrinsics"`` (no distortion) or ``"all"``."""
        presets = {
            "pose": cls(focal=False, principal_point=False, skew=False, distortion=False),
            "pose+focal": cls(principal_point=False, skew=False, distortion=False),
            "pose+intrinsics": cls(distortion=False),
            "all": cls(),
        }
        if preset not in presets:
            raise ValueError(f"parameter preset must be one of {', '.join(map(repr, presets))}, got {preset!r}")
        return presets[preset]

    @property
    def indices(self) -> tuple[int, ...]:
        enabled = [group for group in PARAMETER_GROUPS if getattr(self, group)]
        return tuple(sorted(i for group in enabled for i in PARAMETER_GROUPS[group]))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(PARAMETER_NAMES[i] for i in self.indices)

    @property
    def num_params(self) -> int:
        return len(self.indices)

    def expand(self, delta: Float[Tensor, "*batch k"]) -> Float[Tensor, "*batch 12"]:
        """Scatter enabled-parameter deltas into the full 12-vector (disabled entries are zero)."""
        if delta.shape[-1] != self.num_params:
            raise ValueError(f"delta must have {self.num_params} columns for this layout, got {delta.shape[-1]}")
        full = delta.new_zeros(*delta.shape[:-1], NUM_CAMERA_PARAMS)
        full[..., list(self.indices)] = delta
        return full


@dataclass(frozen=True)
class Intrinsics:
    """Batched intrinsics of N cameras; every field is a tensor of shape [N] on one device and dtype."""

    fx: Float[Tensor, " n"]
    fy: Float[Tensor, " n"]
    cx: Float[Tensor, " n"]
    cy: Float[Tensor, " n"]
    skew: Float[Tensor, " n"]
    k1: Float[Tensor, " n"]
    k2: Float[Tensor, " n"]
    width: Float[Tensor, " n"]
    height: Float[Tensor, " n"]

    @classmethod
    def create(
        cls,
        fx: float | Tensor,
        fy: float | Tensor,
        cx: float | Tensor,
        cy: float | Tensor,
        width: float | Tensor,
        height: float | Tensor,
        skew: float | Tensor = 0.0,
        k1: float | Tensor = 0.0,
        k2: float | Tensor = 0.0,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
        validate: bool = True,
    ) -> Intrinsics:
        """Build from scalars or tensors (broadcast to a common [N]) and validate unless told not to."""
        values = [torch.as_tensor(v, dtype=dtype, device=device) for v in (fx, fy, cx, cy, skew, k1, k2, width, height)]
        values = [v.reshape(-1) for v in torch.broadcast_tensors(*[v.reshape(-1) for v in values])]
        intrinsics = cls(*values)
        if validate:
            intrinsics.validate()
        return intrinsics

    @property
    def num_cameras(self) -> int:
        return self.fx.shape[0]

    @property
    def device(self) -> torch.device:
        return self.fx.device

    @property
    def dtype(self) -> torch.dtype:
        return self.fx.dtype

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Intrinsics:
        return Intrinsics(*[getattr(self, f.name).to(device=device, dtype=dtype) for f in fields(self)])

    def __getitem__(self, index) -> Intrinsics:
        return Intrinsics(*[getattr(self, f.name)[index].reshape(-1) for f in fields(self)])

    def detach(self) -> Intrinsics:
        return Intrinsics(*[getattr(self, f.name).detach() for f in fields(self)])

    def image_scale(self) -> Float[Tensor, " n"]:
        """max(W, H): pixels are divided by it so that the Gram matrix does not depend on resolution."""
        return torch.maximum(self.width, self.height)

    def with_delta(self, delta: Float[Tensor, "n 12"]) -> Intrinsics:
        """Intrinsics after the additive residual update Phi' = Phi + dPhi (paper sec. 4) of the last six deltas."""
        return replace(
            self,
            fx=self.fx + delta[:, 6],
            fy=self.fy + delta[:, 6],
            cx=self.cx + delta[:, 7],
            cy=self.cy + delta[:, 8],
            skew=self.skew + delta[:, 9],
            k1=self.k1 + delta[:, 10],
            k2=self.k2 + delta[:, 11],
        )

    def validate(self) -> None:
        """Positive focal lengths and image sizes, finite values, and distortion monotonic inside the image."""
        for f in fields(self):
            check_finite(f.name, getattr(self, f.name))
        check_range("fx", self.fx, low=0.0, low_inclusive=False)
        check_range("fy", self.fy, low=0.0, low_inclusive=False)
        check_range("width", self.width, low=0.0, low_inclusive=False)
        check_range("height", self.height, low=0.0, low_inclusive=False)
        check_distortion_monotonic(self)


def distortion_factor(r2: Tensor, k1: Tensor, k2: Tensor) -> Tensor:
    """Radial distortion factor 1 + k1 r^2 + k2 r^4 (COLMAP RADIAL model)."""
    return 1.0 + r2 * (k1 + k2 * r2)


def _corner_distorted_radius(intrinsics: Intrinsics) -> Tensor:
    """Largest distorted tangent radius over the four image corners, [N]."""
    us = torch.stack([torch.zeros_like(intrinsics.width), intrinsics.width], dim=-1)
    vs = torch.stack([torch.zeros_like(intrinsics.height), intrinsics.height], dim=-1)
    b_d = (vs - intrinsics.cy[:, None]) / intrinsics.fy[:, None]
    a_d = us[:, :, None] - intrinsics.cx[:, None, None] - intrinsics.skew[:, None, None] * b_d[:, None, :]
    a_d = a_d / intrinsics.fx[:, None, None]
    r_d = torch.sqrt(a_d**2 + b_d[:, None, :] ** 2)
    return r_d.reshape(intrinsics.num_cameras, -1).amax(dim=-1)


def check_distortion_monotonic(intrinsics: Intrinsics) -> None:
    """Raise unless the distorted radius r (1 + k1 r^2 + k2 r^4) increases up to the image corners.

    Its derivative 1 + 3 k1 r^2 + 5 k2 r^4 first vanishes at the smallest positive root s* of the quadratic in
    s = r^2; beyond it the projection folds back and undistortion has two solutions. Require that the distorted
    radius at that fold exceeds the corner radius of every image.
    """
    k1 = intrinsics.k1.detach().double()
    k2 = intrinsics.k2.detach().double()
    a, b = 5.0 * k2, 3.0 * k1
    disc = b * b - 4.0 * a
    sqrt_disc = torch.sqrt(torch.clamp(disc, min=0.0))
    safe_a = torch.where(a == 0, torch.ones_like(a), a)
    roots = torch.stack([(-b - sqrt_disc) / (2 * safe_a), (-b + sqrt_disc) / (2 * safe_a)], dim=-1)
    linear_root = torch.where(b < 0, -1.0 / torch.where(b == 0, torch.ones_like(b), b), torch.full_like(b, torch.inf))
    roots = torch.where(roots > 0, roots, torch.full_like(roots, torch.inf)).amin(dim=-1)
    roots = torch.where(disc < 0, torch.full_like(roots, torch.inf), roots)
    s_fold = torch.where(a == 0, linear_root, roots)
    r_fold = torch.sqrt(s_fold)
    rd_fold = r_fold * distortion_factor(s_fold, k1, k2)
    rd_fold = torch.where(torch.isfinite(s_fold), rd_fold, torch.full_like(rd_fold, torch.inf))
    corner = _corner_distorted_radius(intrinsics.detach().to(dtype=torch.float64))
    bad = rd_fold <= corner
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0])
        raise ValueError(
            f"k1, k2 = ({k1[i].item():g}, {k2[i].item():g}) of camera {i} make the radial distortion non-monotonic "
            f"inside the image: the distorted radius peaks at {rd_fold[i].item():.4g} but the image corners reach "
            f"{corner[i].item():.4g}; allowed are k1, k2 whose fold radius exceeds the corner radius"
        )


def project(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics
) -> tuple[Float[Tensor, "n l 2"], Float[Tensor, "n l"]]:
    """Project camera-frame points to pixels (paper eq. 2, with skew and radial distortion); also return depth z.

    Points at z <= 0 get non-finite-free but meaningless pixels; callers mask them with the depth.
    """
    z = points_cam[..., 2]
    safe_z = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    a = points_cam[..., 0] / safe_z
    b = points_cam[..., 1] / safe_z
    factor = distortion_factor(a * a + b * b, intrinsics.k1[:, None], intrinsics.k2[:, None])
    a_d, b_d = a * factor, b * factor
    u = intrinsics.fx[:, None] * a_d + intrinsics.skew[:, None] * b_d + intrinsics.cx[:, None]
    v = intrinsics.fy[:, None] * b_d + intrinsics.cy[:, None]
    return torch.stack([u, v], dim=-1), z


def undistort_scale(r_d2: Tensor, k1: Tensor, k2: Tensor, iterations: int = UNDISTORT_ITERATIONS) -> Tensor:
    """Scale s = r / r_d solving s (1 + k1 r_d^2 s^2 + k2 r_d^4 s^4) = 1 (inverse of the radial distortion).

    Newton's method runs without autograd to convergence; one more Newton step with autograd on then gives the
    exact implicit-function gradient ds/dtheta = -(dg/dtheta) / g'(s), so undistortion stays differentiable
    without back-propagating through the iterations.
    """

    def residual(s: Tensor, r_d2: Tensor, k1: Tensor, k2: Tensor) -> tuple[Tensor, Tensor]:
        s2r = s * s * r_d2
        g = s * (1.0 + k1 * s2r + k2 * s2r * s2r) - 1.0
        dg = 1.0 + 3.0 * k1 * s2r + 5.0 * k2 * s2r * s2r
        return g, dg

    with torch.no_grad():
        s = torch.ones_like(r_d2)
        for _ in range(iterations):
            g, dg = residual(s, r_d2, k1, k2)
            s = s - g / dg
    g, dg = residual(s, r_d2, k1, k2)
    return s - g / dg.detach()


def unproject(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 2"]:
    """Undistorted tangents (a, b) = (x/z, y/z) of the rays through the given pixels (inverse of ``project``)."""
    b_d = (pixels[..., 1] - intrinsics.cy[:, None]) / intrinsics.fy[:, None]
    a_d = (pixels[..., 0] - intrinsics.cx[:, None] - intrinsics.skew[:, None] * b_d) / intrinsics.fx[:, None]
    scale = undistort_scale(a_d * a_d + b_d * b_d, intrinsics.k1[:, None], intrinsics.k2[:, None])
    return torch.stack([a_d * scale, b_d * scale], dim=-1)


def pixel_to_ray_direction(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 3"]:
    """Unit ray directions in the camera frame through the given pixels."""
    tangents = unproject(pixels, intrinsics)
    directions = torch.cat([tangents, torch.ones_like(tangents[..., :1])], dim=-1)
    return directions / torch.linalg.norm(directions, dim=-1, keepdim=True)


def tangent_bounds(intrinsics: Intrinsics, samples_per_edge: int = 129, inset: float = 1e-5) -> Float[Tensor, "n 4"]:
    """Inner box (a_min, a_max, b_min, b_max) of undistorted tangents whose rays land inside the image.

    The image border is unprojected at ``samples_per_edge`` points per edge. With barrel distortion the border
    bends inwards in tangent space, so the box takes the innermost tangent of each edge; with pincushion
    distortion it bends outwards and the box corners are the undistorted image corners. Between the border
    samples the extreme tangent can lie slightly further in, so the box is inset by ``inset`` of its size.
    """
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


def opengl_to_opencv(c2w: Float[Tensor, "*batch 3 4"]) -> Float[Tensor, "*batch 3 4"]:
    """Switch a camera-to-world matrix between the OpenGL (nerfstudio, viser: y up, z backwards) and the OpenCV
    (COLMAP, this module: y down, z forward) camera frames: c2w F with F = diag(1, -1, -1), its own inverse, so the
    same function also maps OpenCV to OpenGL. Works on [..., 3, 4] and [..., 4, 4] matrices and keeps dtype/device.
    """
    if c2w.shape[-2:] not in ((3, 4), (4, 4)):
        raise ValueError(f"c2w must have shape [..., 3, 4] or [..., 4, 4], got {tuple(c2w.shape)}")
    flip = c2w.new_ones(c2w.shape[-1])
    flip[1:3] = -1.0
    return c2w * flip


def skew_matrix(v: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3 3"]:
    """[v]_x, the matrix with [v]_x w = v x w."""
    zero = torch.zeros_like(v[..., 0])
    return torch.stack(
        [
            torch.stack([zero, -v[..., 2], v[..., 1]], dim=-1),
            torch.stack([v[..., 2], zero, -v[..., 0]], dim=-1),
            torch.stack([-v[..., 1], v[..., 0], zero], dim=-1),
        ],
        dim=-2,
    )


def se3_exp(xi: Float[Tensor, "*batch 6"]) -> Float[Tensor, "*batch 3 4"]:
    """Exponential map of a twist xi = (rho, omega) in se(3) to a rigid transform [R | t] (screw-axis form).

    R = I + A [w]x + B [w]x^2 and t = V rho with V = I + B [w]x + C [w]x^2, A = sin(th)/th,
    B = (1 - cos th)/th^2, C = (th - sin th)/th^3; Taylor series below th = 1e-3 keep it smooth at zero.
    """
    rho, omega = xi[..., :3], xi[..., 3:]
    theta2 = (omega * omega).sum(dim=-1)
    small = theta2 < 1e-6
    safe_theta2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe_theta2)
    coef_a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    coef_b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe_theta2)
    coef_c = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - torch.sin(theta)) / (safe_theta2 * theta))
    w = skew_matrix(omega)
    w2 = w @ w
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(w)
    rotation = eye + coef_a[..., None, None] * w + coef_b[..., None, None] * w2
    v = eye + coef_b[..., None, None] * w + coef_c[..., None, None] * w2
    translation = (v @ rho[..., None])[..., 0]
    return torch.cat([rotation, translation[..., None]], dim=-1)


def apply_local_transform(
    points_cam: Float[Tensor, "n l 3"], transform: Float[Tensor, "n 3 4"]
) -> Float[Tensor, "n l 3"]:
    """Camera-frame coordinates after the local update c2w' = c2w T with T = [R_d | t_d]: x' = R_d^T (x - t_d)."""
    rotation, translation = transform[:, :, :3], transform[:, :, 3]
    return torch.einsum("nji,nlj->nli", rotation, points_cam - translation[:, None, :])


def apply_pose_delta(points_cam: Float[Tensor, "n l 3"], pose_delta: Float[Tensor, "n 6"]) -> Float[Tensor, "n l 3"]:
    """Camera-frame coordinates after the local pose update c2w' = c2w exp(xi): x' = R_d^T (x - t_d)."""
    return apply_local_transform(points_cam, se3_exp(pose_delta))


def project_with_delta(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics, delta: Float[Tensor, "n 12"]
) -> Float[Tensor, "n l 2"]:
    """Pixels of the stacked projection Pi_P(Phi + dPhi) (paper eq. 4's function) for full 12-parameter deltas.

    This is the reference that the analytic Jacobian is tested against with autodiff and finite differences.
    """
    moved = apply_pose_delta(points_cam, delta[:, :6])
    pixels, _ = project(moved, intrinsics.with_delta(delta))
    return pixels


def in_image(pixels: Float[Tensor, "n l 2"], depth: Float[Tensor, "n l"], intrinsics: Intrinsics) -> Tensor:
    """Mask of points in front of the camera that project inside [0, W] x [0, H]."""
    u, v = pixels[..., 0], pixels[..., 1]
    return (
        (depth > 0)
        & (u >= 0)
        & (v >= 0)
        & (u <= intrinsics.width[:, None])
        & (v <= intrinsics.height[:, None])
        & torch.isfinite(pixels).all(dim=-1)
    )
