"""Camera models: perspective (OpenCV radial-tangential) and fisheye (OpenCV equidistant), with se(3) pose delta.

Conventions (COLMAP's, so refined cameras export without conversion): camera frame x right, y down, z forward;
continuous pixels, the image covering [0, W] x [0, H]; u = fx a_d + s b_d + cx, v = fy b_d + cy (paper eq. 2 with
skew s and distortion) with (a_d, b_d) from the projection (``Intrinsics.model``):

- ``"perspective"`` (COLMAP SIMPLE_PINHOLE ... FULL_OPENCV with k4 = k5 = k6 = 0): a = x / z, b = y / z,
  D = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8, a_d = a D + 2 p1 a b + p2 (r^2 + 2 a^2), b_d likewise; k4 is
  nerfstudio's polynomial r^8 term (FULL_OPENCV's k4 divides);
- ``"fisheye"`` (COLMAP OPENCV_FISHEYE): theta = atan2(sqrt(x^2 + y^2), z), theta_d = theta D(theta^2),
  (a_d, b_d) = theta_d (x, y) / sqrt(x^2 + y^2).

Deltas (paper sec. 4) are ordered as ``PARAMETER_NAMES``: a local se(3) twist (rho, omega) applied on the right of
c2w, focal (pixels, added to fx and fy), principal point, skew, then k1, k2, k3, k4, p1, p2; the paper's K = 12 are
the first twelve. Distortion maps and inverses live in ``core.distortion``.

Pixels [N, L, 2] map back to OpenCV camera-frame rays: ``unproject`` to undistorted tangents (x / z, y / z),
``pixel_to_ray_direction`` to unit directions (fisheye also beyond 90 degrees), both differentiable in the pixels and
the intrinsics; ``tangent_bounds`` is the box of tangents landing in the image (the paper's eq. 13 with an off-centre
principal point and distortion), ``vertical_field_of_view`` the vertical angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.distortion import (
    DISTORTION_NAMES,
    UNDISTORT_ITERATIONS,
    check_distortion_monotonic,
    distort_tangents,
    distorted_coordinates,
    distortion_columns,
    distortion_factor,
    fisheye_fold_angle,
    fisheye_terms,
    per_camera_columns,
    undistort_scale,
    undistort_tangents,
)
from s2camp_ns.core.validation import check_choice, check_finite, check_range

PARAMETER_NAMES: tuple[str, ...] = (
    "rho_x", "rho_y", "rho_z", "omega_x", "omega_y", "omega_z", "focal", "cx", "cy", "skew",
    "k1", "k2", "k3", "k4", "p1", "p2",
)  # fmt: skip
NUM_CAMERA_PARAMS = len(PARAMETER_NAMES)
PAPER_NUM_PARAMS = 12  # the paper's K: pose, focal, principal point, skew, k1, k2

PARAMETER_GROUPS: dict[str, tuple[int, ...]] = {
    "pose": (0, 1, 2, 3, 4, 5), "focal": (6,), "principal_point": (7, 8), "skew": (9,), "radial": (10, 11),
    "radial_k3": (12,), "radial_k4": (13,), "tangential": (14, 15),
}  # fmt: skip

PROJECTIONS: tuple[str, ...] = ("perspective", "fisheye")

CAMERA_MODEL_DISTORTION: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("radial",),
    "PINHOLE": ("radial",),
    "SIMPLE_RADIAL": ("radial",),
    "RADIAL": ("radial",),
    "OPENCV": ("radial", "tangential"),
    "FULL_OPENCV": ("radial", "radial_k3", "tangential"),
    "OPENCV_FISHEYE": ("radial", "radial_k3", "radial_k4"),
}
"""Distortion groups the ``"all"`` preset refines per COLMAP model; pinhole models get k1, k2 (the paper's K = 12)."""

CAMERA_MODEL_PROJECTION: dict[str, str] = {
    name: ("fisheye" if name == "OPENCV_FISHEYE" else "perspective") for name in CAMERA_MODEL_DISTORTION
}

PRESETS: tuple[str, ...] = ("pose", "pose+focal", "pose+intrinsics", "all")


@dataclass(frozen=True)
class ParameterLayout:
    """Refined parameter groups, in ``PARAMETER_NAMES`` order; ``distortion``: ``camera_model``'s groups."""

    pose: bool = True
    focal: bool = True
    principal_point: bool = True
    skew: bool = True
    distortion: bool = True
    camera_model: str = "RADIAL"

    def __post_init__(self) -> None:
        check_choice("camera_model", self.camera_model, tuple(CAMERA_MODEL_DISTORTION))

    @classmethod
    def from_preset(cls, preset: str, camera_model: str = "RADIAL") -> ParameterLayout:
        """One of ``PRESETS``; only ``"all"`` refines distortion (that of ``camera_model``)."""
        presets = {
            "pose": dict(focal=False, principal_point=False, skew=False, distortion=False),
            "pose+focal": dict(principal_point=False, skew=False, distortion=False),
            "pose+intrinsics": dict(distortion=False),
            "all": dict(),
        }
        if preset not in presets:
            raise ValueError(f"parameter preset must be one of {', '.join(map(repr, presets))}, got {preset!r}")
        return cls(camera_model=camera_model, **presets[preset])

    @property
    def groups(self) -> tuple[str, ...]:
        enabled = [name for name in ("pose", "focal", "principal_point", "skew") if getattr(self, name)]
        if self.distortion:
            enabled += list(CAMERA_MODEL_DISTORTION[self.camera_model])
        return tuple(enabled)

    @property
    def indices(self) -> tuple[int, ...]:
        return tuple(sorted(i for group in self.groups for i in PARAMETER_GROUPS[group]))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(PARAMETER_NAMES[i] for i in self.indices)

    @property
    def num_params(self) -> int:
        return len(self.indices)

    def expand(self, delta: Float[Tensor, "*batch k"]) -> Float[Tensor, "*batch 16"]:
        """[..., K] -> [..., 16], zeros in disabled columns."""
        if delta.shape[-1] != self.num_params:
            raise ValueError(f"delta must have {self.num_params} columns for this layout, got {delta.shape[-1]}")
        full = delta.new_zeros(*delta.shape[:-1], NUM_CAMERA_PARAMS)
        full[..., list(self.indices)] = delta
        return full


TENSOR_FIELDS: tuple[str, ...] = ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "width", "height", "k3", "k4", "p1", "p2")
"""Per-camera tensor fields of ``Intrinsics`` in declaration order."""

DELTA_FIELDS: dict[str, tuple[str, ...]] = {
    "focal": ("fx", "fy"), "cx": ("cx",), "cy": ("cy",), "skew": ("skew",),
    "k1": ("k1",), "k2": ("k2",), "k3": ("k3",), "k4": ("k4",), "p1": ("p1",), "p2": ("p2",),
}  # fmt: skip
"""The ``TENSOR_FIELDS`` each intrinsics delta adds to."""


def full_delta(delta: Float[Tensor, "n k"]) -> Float[Tensor, "n 16"]:
    """[n, 16] deltas: as given, or the paper's 12 padded with zeros; ValueError otherwise."""
    if delta.shape[-1] == PAPER_NUM_PARAMS:
        delta = torch.cat([delta, delta.new_zeros(*delta.shape[:-1], NUM_CAMERA_PARAMS - PAPER_NUM_PARAMS)], dim=-1)
    if delta.shape[-1] != NUM_CAMERA_PARAMS:
        raise ValueError(
            f"delta must have {NUM_CAMERA_PARAMS} columns (PARAMETER_NAMES) or the paper's {PAPER_NUM_PARAMS}, "
            f"got {delta.shape[-1]}"
        )
    return delta


def delta_field_map(dtype: torch.dtype, device: torch.device | str | None = None) -> Float[Tensor, "16 13"]:
    """[16, 13] 0/1 matrix M with Phi' = Phi + dPhi M on ``Intrinsics.tensors`` columns (``DELTA_FIELDS``)."""
    field_map = torch.zeros(NUM_CAMERA_PARAMS, len(TENSOR_FIELDS), dtype=dtype, device=device)
    for name, fields in DELTA_FIELDS.items():
        for field_name in fields:
            field_map[PARAMETER_NAMES.index(name), TENSOR_FIELDS.index(field_name)] = 1.0
    return field_map


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics of N cameras: tensor fields [N] on one device and dtype (k3, k4, p1, p2 default to zero);
    ``model`` in ``PROJECTIONS``; ``distortion_terms`` (None: read from the values on the host) the coefficients
    that may be nonzero, inverted in ``newton_iterations`` Newton steps."""

    fx: Float[Tensor, " n"]
    fy: Float[Tensor, " n"]
    cx: Float[Tensor, " n"]
    cy: Float[Tensor, " n"]
    skew: Float[Tensor, " n"]
    k1: Float[Tensor, " n"]
    k2: Float[Tensor, " n"]
    width: Float[Tensor, " n"]
    height: Float[Tensor, " n"]
    k3: Float[Tensor, " n"] | None = None
    k4: Float[Tensor, " n"] | None = None
    p1: Float[Tensor, " n"] | None = None
    p2: Float[Tensor, " n"] | None = None
    model: str = "perspective"
    distortion_terms: tuple[str, ...] | None = None
    newton_iterations: int = UNDISTORT_ITERATIONS

    def __post_init__(self) -> None:
        if self.model not in PROJECTIONS:  # checked here, not by core.validation: it runs at every step
            raise ValueError(f"model must be one of {', '.join(map(repr, PROJECTIONS))}, got {self.model!r}")
        if self.distortion_terms is not None and not set(self.distortion_terms) <= set(DISTORTION_NAMES):
            raise ValueError(f"distortion_terms must be among {DISTORTION_NAMES}, got {self.distortion_terms}")
        for name in ("k3", "k4", "p1", "p2"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, torch.zeros_like(self.k1))

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
        k3: float | Tensor = 0.0,
        k4: float | Tensor = 0.0,
        p1: float | Tensor = 0.0,
        p2: float | Tensor = 0.0,
        model: str = "perspective",
    ) -> Intrinsics:
        """From scalars or tensors broadcast to [N]; validated unless ``validate`` is False."""
        given = (fx, fy, cx, cy, skew, k1, k2, width, height, k3, k4, p1, p2)
        values = [torch.as_tensor(v, dtype=dtype, device=device) for v in given]
        values = [v.reshape(-1) for v in torch.broadcast_tensors(*[v.reshape(-1) for v in values])]
        intrinsics = cls(*values, model=model)
        if validate:
            intrinsics.validate()
        return intrinsics

    def _map(self, function) -> Intrinsics:
        return replace(self, **{name: function(getattr(self, name)) for name in TENSOR_FIELDS})

    def tensors(self) -> Float[Tensor, "n 13"]:
        """[n, 13] fields in ``TENSOR_FIELDS`` order."""
        return torch.stack([getattr(self, name) for name in TENSOR_FIELDS], dim=-1)

    @classmethod
    def from_tensors(cls, values: Float[Tensor, "n 13"], model: str = "perspective", **form) -> Intrinsics:
        """Inverse of ``tensors``; ``form``: ``distortion_terms`` and ``newton_iterations``."""
        return cls(*values.unbind(dim=-1), model=model, **form)

    @property
    def form(self) -> dict:
        """``distortion_terms`` and ``newton_iterations`` as keywords of ``from_tensors``."""
        return {"distortion_terms": self.distortion_terms, "newton_iterations": self.newton_iterations}

    @property
    def is_fisheye(self) -> bool:
        return self.model == "fisheye"

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
        return self._map(lambda v: v.to(device=device, dtype=dtype))

    def __getitem__(self, index) -> Intrinsics:
        return self._map(lambda v: v[index].reshape(-1))

    def detach(self) -> Intrinsics:
        return self._map(lambda v: v.detach())

    def image_scale(self) -> Float[Tensor, " n"]:
        """max(W, H), the pixel scale that makes the Gram matrix resolution-independent."""
        return torch.maximum(self.width, self.height)

    def with_delta(self, delta: Float[Tensor, "n 16"]) -> Intrinsics:
        """Phi' = Phi + dPhi (paper sec. 4) for [n, 16] or the paper's [n, 12] deltas (``full_delta``)."""
        delta = full_delta(delta)
        fields = torch.addmm(self.tensors(), delta, delta_field_map(delta.dtype, delta.device))
        return Intrinsics.from_tensors(fields, model=self.model, **self.form)

    def general(self) -> Intrinsics:
        """The same cameras without a declared form, so what is computed from them depends on their values only."""
        return replace(self, distortion_terms=None, newton_iterations=UNDISTORT_ITERATIONS)

    def validate(self) -> None:
        """ValueError unless finite, fx, fy, W, H > 0 and the distortion one-to-one in the image."""
        for name in TENSOR_FIELDS:
            check_finite(name, getattr(self, name))
        check_range("fx", self.fx, low=0.0, low_inclusive=False)
        check_range("fy", self.fy, low=0.0, low_inclusive=False)
        check_range("width", self.width, low=0.0, low_inclusive=False)
        check_range("height", self.height, low=0.0, low_inclusive=False)
        check_distortion_monotonic(self)


def distortion_form(base: Intrinsics, layout: ParameterLayout | None) -> tuple[str, ...]:
    """``Intrinsics.distortion_terms`` of ``base`` refined with ``layout`` (None: not refined): the refined and the
    nonzero terms (a host read), k1 and k2 with any radial term."""
    live = {name for name in (layout.names if layout is not None else ()) if name in DISTORTION_NAMES}
    live |= {name for name in DISTORTION_NAMES if bool((getattr(base, name) != 0).any())}
    if live & {"k1", "k2", "k3", "k4"}:
        live |= {"k1", "k2"}
    return tuple(name for name in DISTORTION_NAMES if name in live)


def camera_model_of(intrinsics: Intrinsics) -> str:
    """COLMAP model from the values: OPENCV_FISHEYE (fisheye), FULL_OPENCV (some k3), OPENCV (some p1, p2), RADIAL."""
    if intrinsics.is_fisheye:
        return "OPENCV_FISHEYE"
    if bool((intrinsics.k3 != 0).any()):
        return "FULL_OPENCV"
    if bool((intrinsics.p1 != 0).any() | (intrinsics.p2 != 0).any()):
        return "OPENCV"
    return "RADIAL"


def project(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics
) -> tuple[Float[Tensor, "n l 2"], Float[Tensor, "n l"]]:
    """Pixels [n, l, 2] of camera-frame points (paper eq. 2) and a margin [n, l], positive where the projection is
    valid: z (perspective) or theta_fold - theta in radians (fisheye). Invalid points get finite, meaningless pixels."""
    if intrinsics.is_fisheye:
        terms = fisheye_terms(points_cam)
        k1, k2, k3, k4 = per_camera_columns(intrinsics, "k1", "k2", "k3", "k4")
        scale = terms.h * distortion_factor(terms.theta2, k1, k2, k3, k4)
        a_d, b_d = points_cam[..., 0] * scale, points_cam[..., 1] * scale
        theta_fold, _ = fisheye_fold_angle(intrinsics)
        at_centre = (points_cam.detach() == 0).all(dim=-1)
        margin = torch.where(at_centre, torch.full_like(terms.theta, -1.0), theta_fold[:, None] - terms.theta)
    else:
        z = points_cam[..., 2]
        safe_z = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
        a = points_cam[..., 0] / safe_z
        b = points_cam[..., 1] / safe_z
        a_d, b_d = distort_tangents(a, b, intrinsics)
        margin = z
    fx, fy, cx, cy, skew = per_camera_columns(intrinsics, "fx", "fy", "cx", "cy", "skew")
    u = fx * a_d + skew * b_d + cx
    v = fy * b_d + cy
    return torch.stack([u, v], dim=-1), margin


def opengl_to_opencv(c2w: Float[Tensor, "*batch 3 4"]) -> Float[Tensor, "*batch 3 4"]:
    """c2w F with F = diag(1, -1, -1): OpenGL (y up, z back) <-> OpenCV (y down, z forward), either way."""
    if c2w.shape[-2:] not in ((3, 4), (4, 4)):
        raise ValueError(f"c2w must have shape [..., 3, 4] or [..., 4, 4], got {tuple(c2w.shape)}")
    flip = c2w.new_ones(c2w.shape[-1])
    flip[1:3] = -1.0
    return c2w * flip


def skew_matrix(v: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3 3"]:
    """[v]_x, the matrix with [v]_x w = v x w."""
    zero = torch.zeros_like(v[..., 0])
    return torch.stack([
        torch.stack([zero, -v[..., 2], v[..., 1]], dim=-1),
        torch.stack([v[..., 2], zero, -v[..., 0]], dim=-1),
        torch.stack([-v[..., 1], v[..., 0], zero], dim=-1),
    ], dim=-2)  # fmt: skip


def se3_exp(xi: Float[Tensor, "*batch 6"]) -> Float[Tensor, "*batch 3 4"]:
    """[..., 3, 4] [R | t] = exp(xi), xi = (rho, omega): R = (1 - B th^2) I + A [w]x + B w w^T,
    t = rho + B (w x rho) + C (w x (w x rho)), A = sin(th)/th, B = (1 - cos th)/th^2, C = (th - sin th)/th^3."""
    rho, omega = xi[..., :3], xi[..., 3:]
    theta2 = (omega * omega).sum(dim=-1, keepdim=True)  # [*, 1]
    small = theta2 < 1e-6
    safe_theta2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe_theta2)
    sinc = torch.sin(theta) / theta
    coef_a = torch.where(small, 1.0 - theta2 / 6.0, sinc)
    coef_b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe_theta2)
    coef_c = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (1.0 - sinc) / safe_theta2)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(*omega.shape[:-1], 3, 3)
    w = torch.linalg.cross(eye, omega[..., None, :].expand_as(eye))  # rows e_i x w: [w]x
    outer = omega[..., :, None] * omega[..., None, :]
    rotation = (1.0 - coef_b * theta2)[..., None] * eye + coef_a[..., None] * w + coef_b[..., None] * outer
    cross = torch.linalg.cross(omega, rho)
    translation = rho + coef_b * cross + coef_c * torch.linalg.cross(omega, cross)
    return torch.cat([rotation, translation[..., None]], dim=-1)


def apply_local_transform(
    points_cam: Float[Tensor, "n l 3"], transform: Float[Tensor, "n 3 4"]
) -> Float[Tensor, "n l 3"]:
    """Camera-frame points after c2w' = c2w [R_d | t_d]: x' = R_d^T (x - t_d)."""
    rotation, translation = transform[:, :, :3], transform[:, :, 3]
    return torch.einsum("nji,nlj->nli", rotation, points_cam - translation[:, None, :])


def apply_pose_delta(points_cam: Float[Tensor, "n l 3"], pose_delta: Float[Tensor, "n 6"]) -> Float[Tensor, "n l 3"]:
    """Camera-frame points after c2w' = c2w exp(xi)."""
    return apply_local_transform(points_cam, se3_exp(pose_delta))


def project_with_delta(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics, delta: Float[Tensor, "n 16"]
) -> Float[Tensor, "n l 2"]:
    """Pixels of Pi_P(Phi + dPhi) (paper eq. 4) for [n, 16] (or [n, 12]) deltas: the analytic Jacobian's reference."""
    moved = apply_pose_delta(points_cam, delta[:, :6])
    pixels, _ = project(moved, intrinsics.with_delta(delta))
    return pixels


def in_image(pixels: Float[Tensor, "n l 2"], depth: Float[Tensor, "n l"], intrinsics: Intrinsics) -> Tensor:
    """Mask of points with positive ``depth`` (``project``'s margin) and finite pixels inside [0, W] x [0, H]."""
    u, v = pixels[..., 0], pixels[..., 1]
    return (
        (depth > 0) & (u >= 0) & (v >= 0) & (u <= intrinsics.width[:, None]) & (v <= intrinsics.height[:, None])
        & torch.isfinite(pixels).all(dim=-1)
    )  # fmt: skip


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
