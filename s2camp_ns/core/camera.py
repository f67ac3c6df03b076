"""Camera models: perspective (OpenCV radial-tangential) and fisheye (OpenCV equidistant), with se(3) pose delta.

Conventions (the same as COLMAP and pycolmap, so refined cameras export without conversion):

- camera frame: x right, y down, z forward;
- continuous pixel coordinates, the image covering [0, W] x [0, H] (the centre of pixel (i, j) is (i + .5, j + .5));
- pixels u = fx a_d + s b_d + cx, v = fy b_d + cy (paper eq. 2 with the skew s and distortion added), where the
  distorted image-plane coordinates (a_d, b_d) depend on the projection (``Intrinsics.model``):

  ``"perspective"`` (COLMAP SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV with k4 = k5 = k6 = 0):
      tangents a = x / z, b = y / z, r^2 = a^2 + b^2, D = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8,
      a_d = a D + 2 p1 a b + p2 (r^2 + 2 a^2),  b_d = b D + 2 p2 a b + p1 (r^2 + 2 b^2).
      k4 is nerfstudio's (a polynomial r^8 term); it has no COLMAP counterpart (FULL_OPENCV's k4 divides).
  ``"fisheye"`` (COLMAP OPENCV_FISHEYE, equidistant):
      theta = atan2(sqrt(x^2 + y^2), z) (defined beyond 90 degrees), theta_d = theta (1 + k1 theta^2 + k2 theta^4
      + k3 theta^6 + k4 theta^8), (a_d, b_d) = theta_d (x, y) / sqrt(x^2 + y^2).

The camera-parameter deltas of the paper (sec. 4, "Camera Parameterization") are ordered as ``PARAMETER_NAMES``: a
local se(3) pose delta (rho, omega) applied on the right of the camera-to-world pose, then focal length (pixels,
added to fx and fy), principal point (pixels), skew (pixels) and the distortion coefficients k1, k2, k3, k4, p1, p2.
The paper's K = 12 are the first twelve; which distortion columns a layout refines follows the COLMAP camera model
(``CAMERA_MODEL_DISTORTION``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.validation import check_choice, check_finite, check_range

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
    "k3",
    "k4",
    "p1",
    "p2",
)
NUM_CAMERA_PARAMS = len(PARAMETER_NAMES)
PAPER_NUM_PARAMS = 12
"""The paper's K: pose, focal, principal point, skew, k1, k2 (the first twelve ``PARAMETER_NAMES``)."""

PARAMETER_GROUPS: dict[str, tuple[int, ...]] = {
    "pose": (0, 1, 2, 3, 4, 5),
    "focal": (6,),
    "principal_point": (7, 8),
    "skew": (9,),
    "radial": (10, 11),
    "radial_k3": (12,),
    "radial_k4": (13,),
    "tangential": (14, 15),
}

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
"""Distortion groups the ``"all"`` preset refines per COLMAP camera model. Pinhole and one-coefficient models get
k1 and k2 as RADIAL does (the paper's K = 12: distortion is refined from zero)."""

CAMERA_MODEL_PROJECTION: dict[str, str] = {
    name: ("fisheye" if name == "OPENCV_FISHEYE" else "perspective") for name in CAMERA_MODEL_DISTORTION
}

PRESETS: tuple[str, ...] = ("pose", "pose+focal", "pose+intrinsics", "all")

UNDISTORT_ITERATIONS = 20


@dataclass(frozen=True)
class ParameterLayout:
    """Which parameter groups are refined; the enabled columns keep the order of ``PARAMETER_NAMES``.

    ``distortion`` enables the distortion groups of ``camera_model`` (``CAMERA_MODEL_DISTORTION``).
    """

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
        """``"pose"``, ``"pose+focal"``, ``"pose+intrinsics"`` (no distortion) or ``"all"`` (the distortion
        coefficients of ``camera_model``)."""
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
        """Scatter enabled-parameter deltas into the full 16-vector (disabled entries are zero)."""
        if delta.shape[-1] != self.num_params:
            raise ValueError(f"delta must have {self.num_params} columns for this layout, got {delta.shape[-1]}")
        full = delta.new_zeros(*delta.shape[:-1], NUM_CAMERA_PARAMS)
        full[..., list(self.indices)] = delta
        return full


TENSOR_FIELDS: tuple[str, ...] = ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "width", "height", "k3", "k4", "p1", "p2")
"""Per-camera tensor fields of ``Intrinsics`` in declaration order (the first nine are the historical layout)."""


@dataclass(frozen=True)
class Intrinsics:
    """Batched intrinsics of N cameras; every tensor field has shape [N], on one device and dtype.

    ``model`` is the projection of the whole batch (``"perspective"`` or ``"fisheye"``); k3, k4, p1, p2 default to
    zero, so the nine leading fields alone describe a RADIAL camera as before.
    """

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

    def __post_init__(self) -> None:
        check_choice("model", self.model, PROJECTIONS)
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
        """Build from scalars or tensors (broadcast to a common [N]) and validate unless told not to."""
        given = (fx, fy, cx, cy, skew, k1, k2, width, height, k3, k4, p1, p2)
        values = [torch.as_tensor(v, dtype=dtype, device=device) for v in given]
        values = [v.reshape(-1) for v in torch.broadcast_tensors(*[v.reshape(-1) for v in values])]
        intrinsics = cls(*values, model=model)
        if validate:
            intrinsics.validate()
        return intrinsics

    def _map(self, function) -> Intrinsics:
        return Intrinsics(**{name: function(getattr(self, name)) for name in TENSOR_FIELDS}, model=self.model)

    def tensors(self) -> Float[Tensor, "n 13"]:
        """The tensor fields stacked in ``TENSOR_FIELDS`` order (``from_tensors`` inverts it)."""
        return torch.stack([getattr(self, name) for name in TENSOR_FIELDS], dim=-1)

    @classmethod
    def from_tensors(cls, values: Float[Tensor, "n 13"], model: str = "perspective") -> Intrinsics:
        return cls(*values.unbind(dim=-1), model=model)

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
        """max(W, H): pixels are divided by it so that the Gram matrix does not depend on resolution."""
        return torch.maximum(self.width, self.height)

    def with_delta(self, delta: Float[Tensor, "n 16"]) -> Intrinsics:
        """Intrinsics after the additive residual update Phi' = Phi + dPhi (paper sec. 4) of the last ten deltas.

        ``delta`` holds all 16 ``PARAMETER_NAMES``, or only the paper's first 12 (k3, k4, p1, p2 then stay).
        """
        if delta.shape[-1] == PAPER_NUM_PARAMS:
            delta = torch.cat([delta, delta.new_zeros(*delta.shape[:-1], NUM_CAMERA_PARAMS - PAPER_NUM_PARAMS)], dim=-1)
        if delta.shape[-1] != NUM_CAMERA_PARAMS:
            raise ValueError(
                f"delta must have {NUM_CAMERA_PARAMS} columns (PARAMETER_NAMES) or the paper's {PAPER_NUM_PARAMS}, "
                f"got {delta.shape[-1]}"
            )
        return replace(
            self,
            fx=self.fx + delta[:, 6],
            fy=self.fy + delta[:, 6],
            cx=self.cx + delta[:, 7],
            cy=self.cy + delta[:, 8],
            skew=self.skew + delta[:, 9],
            k1=self.k1 + delta[:, 10],
            k2=self.k2 + delta[:, 11],
            k3=self.k3 + delta[:, 12],
            k4=self.k4 + delta[:, 13],
            p1=self.p1 + delta[:, 14],
            p2=self.p2 + delta[:, 15],
        )

    def validate(self) -> None:
        """Positive focal lengths and image sizes, finite values, and distortion one-to-one inside the image."""
        for name in TENSOR_FIELDS:
            check_finite(name, getattr(self, name))
        check_range("fx", self.fx, low=0.0, low_inclusive=False)
        check_range("fy", self.fy, low=0.0, low_inclusive=False)
        check_range("width", self.width, low=0.0, low_inclusive=False)
        check_range("height", self.height, low=0.0, low_inclusive=False)
        check_distortion_monotonic(self)


def camera_model_of(intrinsics: Intrinsics) -> str:
    """The COLMAP camera model whose distortion groups the "all" preset refines: OPENCV_FISHEYE for fisheye
    cameras; FULL_OPENCV when some camera has k3; OPENCV when some camera has p1 or p2; RADIAL otherwise.

    Decided by the values (nerfstudio's cameras do not keep the model's name): an OPENCV camera with
    p1 = p2 = 0 is a RADIAL camera, as COLMAP's models nest.
    """
    if intrinsics.is_fisheye:
        return "OPENCV_FISHEYE"
    if bool((intrinsics.k3 != 0).any()):
        return "FULL_OPENCV"
    if bool((intrinsics.p1 != 0).any() | (intrinsics.p2 != 0).any()):
        return "OPENCV"
    return "RADIAL"


def distortion_factor(r2: Tensor, k1: Tensor, k2: Tensor, k3: Tensor | float = 0.0, k4: Tensor | float = 0.0) -> Tensor:
    """Radial polynomial 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 (COLMAP RADIAL / OPENCV; with theta^2 for r^2 the
    fisheye's theta_d / theta). Written so that k3 = k4 = 0 adds an exact zero to the two-coefficient value."""
    return 1.0 + r2 * (k1 + k2 * r2 + r2 * r2 * (k3 + k4 * r2))


def distortion_slope(r2: Tensor, k1: Tensor, k2: Tensor, k3: Tensor | float = 0.0, k4: Tensor | float = 0.0) -> Tensor:
    """d(distortion_factor)/d(r^2) = k1 + 2 k2 r^2 + 3 k3 r^4 + 4 k4 r^6."""
    return k1 + 2.0 * k2 * r2 + r2 * r2 * (3.0 * k3 + 4.0 * k4 * r2)


def _columns(intrinsics: Intrinsics, *names: str) -> tuple[Tensor, ...]:
    """Per-camera fields as [N, 1] columns that broadcast against per-point [N, L] tensors."""
    return tuple(getattr(intrinsics, name)[:, None] for name in names)


def distort_tangents(a: Tensor, b: Tensor, intrinsics: Intrinsics) -> tuple[Tensor, Tensor]:
    """Perspective distortion (a, b) -> (a_d, b_d): radial polynomial and OpenCV tangential terms (module doc)."""
    k1, k2, k3, k4, p1, p2 = _columns(intrinsics, "k1", "k2", "k3", "k4", "p1", "p2")
    r2 = a * a + b * b
    factor = distortion_factor(r2, k1, k2, k3, k4)
    a_d = a * factor + (2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a))
    b_d = b * factor + (2.0 * p2 * a * b + p1 * (r2 + 2.0 * b * b))
    return a_d, b_d


FISHEYE_SERIES_BELOW = 1e-4
"""Below this ratio sqrt(x^2 + y^2) / z the fisheye's theta / rho is taken from its Taylor series (exact to 1e-24)."""


@dataclass(frozen=True)
class FisheyeTerms:
    """Per-point quantities of the equidistant projection, safe on the optical axis and behind the camera.

    h = theta / rho (-> 1 / z on the axis), theta2 = theta^2, q = (z / R - h) / rho^2 (the derivative factor
    dh/dx = x q, -> -2 / (3 z^3) on the axis), R = x^2 + y^2 + z^2, and the true angle theta (no gradient).
    """

    h: Tensor
    theta2: Tensor
    q: Tensor
    norm2: Tensor
    theta: Tensor


def fisheye_terms(points_cam: Float[Tensor, "n l 3"]) -> FisheyeTerms:
    """theta = atan2(rho, z), rho = sqrt(x^2 + y^2), with Taylor branches where rho << z (module doc)."""
    x, y, z = points_cam.unbind(dim=-1)
    rho2 = x * x + y * y
    norm2 = rho2 + z * z
    safe_norm2 = torch.where(norm2 > 0, norm2, torch.ones_like(norm2))
    small = (z > 0) & (rho2 < (FISHEYE_SERIES_BELOW * z) ** 2)
    # Series branch (t = rho / z): h = (1 - t^2/3 + t^4/5) / z, theta^2 = t^2 (1 - 2 t^2/3), q = (4 t^2/5 - 2/3) / z^3
    zs = torch.where(small, z, torch.ones_like(z))
    t2 = torch.where(small, rho2, torch.zeros_like(rho2)) / (zs * zs)
    h_series = (1.0 - t2 / 3.0 + t2 * t2 / 5.0) / zs
    theta2_series = t2 * (1.0 - 2.0 * t2 / 3.0)
    q_series = (-2.0 / 3.0 + 0.8 * t2) / (zs * zs * zs)
    # General branch; rho2 = 0 off the series branch (straight behind, or the centre) gets a finite stand-in.
    safe_rho2 = torch.where(small | (rho2 <= 0), torch.ones_like(rho2), rho2)
    rho = torch.sqrt(safe_rho2)
    theta_general = torch.atan2(rho, z)
    h_general = theta_general / rho
    q_general = (z / safe_norm2 - h_general) / safe_rho2
    with torch.no_grad():
        theta = torch.atan2(torch.sqrt(rho2.detach()), z.detach())
    return FisheyeTerms(
        h=torch.where(small, h_series, h_general),
        theta2=torch.where(small, theta2_series, theta_general * theta_general),
        q=torch.where(small, q_series, q_general),
        norm2=safe_norm2,
        theta=theta,
    )


FOLD_SCAN_SAMPLES = 4097


def fisheye_fold_angle(intrinsics: Intrinsics) -> tuple[Float[Tensor, " n"], Float[Tensor, " n"]]:
    """Angle theta_fold in (0, pi] up to which theta_d(theta) increases, and theta_d there (no gradient).

    theta_d' = 1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8 is scanned on a uniform grid of
    [0, pi]; the first sample where it is not positive ends the one-to-one range (pi if there is none).
    """
    k1, k2, k3, k4 = (
        getattr(intrinsics, name).detach().to(torch.float64)[:, None] for name in ("k1", "k2", "k3", "k4")
    )
    theta = torch.linspace(0.0, math.pi, FOLD_SCAN_SAMPLES, dtype=torch.float64, device=intrinsics.device)[None]
    theta2 = theta * theta
    slope = 1.0 + theta2 * (3.0 * k1 + theta2 * (5.0 * k2 + theta2 * (7.0 * k3 + 9.0 * k4 * theta2)))
    increasing = slope > 0
    folded = ~increasing.all(dim=-1)
    first_bad = torch.where(
        folded, (~increasing).to(torch.int64).argmax(dim=-1), torch.full_like(folded, 0, dtype=torch.int64)
    )
    last_good = torch.where(folded, (first_bad - 1).clamp(min=0), torch.full_like(first_bad, FOLD_SCAN_SAMPLES - 1))
    theta_fold = theta[0, last_good]
    theta_d = theta * distortion_factor(theta2, k1, k2, k3, k4)
    theta_d_fold = theta_d.gather(-1, last_good[:, None])[:, 0]
    return theta_fold.to(intrinsics.dtype), theta_d_fold.to(intrinsics.dtype)


def _corner_distorted_radius(intrinsics: Intrinsics) -> Tensor:
    """Largest distorted radius |(a_d, b_d)| over the four image corners, [N]."""
    us = torch.stack([torch.zeros_like(intrinsics.width), intrinsics.width], dim=-1)
    vs = torch.stack([torch.zeros_like(intrinsics.height), intrinsics.height], dim=-1)
    b_d = (vs - intrinsics.cy[:, None]) / intrinsics.fy[:, None]
    a_d = us[:, :, None] - intrinsics.cx[:, None, None] - intrinsics.skew[:, None, None] * b_d[:, None, :]
    a_d = a_d / intrinsics.fx[:, None, None]
    r_d = torch.sqrt(a_d**2 + b_d[:, None, :] ** 2)
    return r_d.reshape(intrinsics.num_cameras, -1).amax(dim=-1)


def _coefficients(intrinsics: Intrinsics, index: int, names: tuple[str, ...]) -> str:
    return ", ".join(names) + " = (" + ", ".join(f"{getattr(intrinsics, n)[index].item():g}" for n in names) + ")"


def check_distortion_monotonic(intrinsics: Intrinsics) -> None:
    """Raise unless the distortion is one-to-one over the image, naming the coefficients and the camera.

    - radial k1, k2 only: the analytic fold radius must exceed the image corners' radius (``_check_radial``);
    - other perspective cameras (k3, k4, p1, p2): the distortion map's Jacobian must stay invertible and
      undistortion must converge on a grid over the image (``_check_perspective_grid``);
    - fisheye: theta_d(theta) must increase up to the image corners (``fisheye_fold_angle``).
    """
    if intrinsics.is_fisheye:
        _check_fisheye(intrinsics)
        return
    extra = torch.stack([intrinsics.k3, intrinsics.k4, intrinsics.p1, intrinsics.p2]).detach()
    if bool((extra == 0).all()):
        _check_radial(intrinsics)
    else:
        _check_perspective_grid(intrinsics)


def _check_radial(intrinsics: Intrinsics) -> None:
    """The distorted radius r (1 + k1 r^2 + k2 r^4) must increase up to the image corners.

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


def _check_fisheye(intrinsics: Intrinsics) -> None:
    """theta_d(theta) must increase from the optical axis up to the image corners (no fold inside the image)."""
    intrinsics64 = intrinsics.detach().to(dtype=torch.float64)
    theta_fold, theta_d_fold = fisheye_fold_angle(intrinsics64)
    corner = _corner_distorted_radius(intrinsics64)
    bad = theta_d_fold <= corner
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0])
        raise ValueError(
            f"{_coefficients(intrinsics64, i, ('k1', 'k2', 'k3', 'k4'))} of fisheye camera {i} make theta_d(theta) "
            f"stop increasing at theta = {math.degrees(theta_fold[i].item()):.4g} degrees (theta_d = "
            f"{theta_d_fold[i].item():.4g}) but the image corners reach theta_d = {corner[i].item():.4g}; allowed "
            "are coefficients with theta_d increasing up to the image corners"
        )


GRID_EDGE_SAMPLES = 65
GRID_INTERIOR_SAMPLES = 17


def image_grid(intrinsics: Intrinsics, edge: int = GRID_EDGE_SAMPLES, interior: int = GRID_INTERIOR_SAMPLES) -> Tensor:
    """Pixels [N, L, 2] on the image border (``edge`` per side) and on an ``interior`` x ``interior`` grid."""
    t = torch.linspace(0.0, 1.0, edge, dtype=intrinsics.dtype, device=intrinsics.device)
    s = torch.linspace(0.0, 1.0, interior, dtype=intrinsics.dtype, device=intrinsics.device)
    zeros, ones = torch.zeros_like(t), torch.ones_like(t)
    border = torch.cat([torch.stack(pair, dim=-1) for pair in ((t, zeros), (t, ones), (zeros, t), (ones, t))], dim=0)
    inner = torch.stack(torch.meshgrid(s, s, indexing="ij"), dim=-1).reshape(-1, 2)
    unit = torch.cat([border, inner], dim=0)
    size = torch.stack([intrinsics.width, intrinsics.height], dim=-1)
    return unit[None] * size[:, None, :]


def _check_perspective_grid(intrinsics: Intrinsics) -> None:
    """Undistortion must converge with an invertible distortion Jacobian on a grid over the image (incl. border)."""
    intrinsics64 = intrinsics.detach().to(dtype=torch.float64)
    pixels = image_grid(intrinsics64)
    a_d, b_d = distorted_coordinates(pixels, intrinsics64)
    with torch.no_grad():
        a, b = _newton_tangential(a_d, b_d, intrinsics64)
        again_a, again_b = distort_tangents(a, b, intrinsics64)
        residual = torch.maximum((again_a - a_d).abs(), (again_b - b_d).abs())
        det = torch.linalg.det(tangent_distortion_jacobian(a, b, intrinsics64))
    tolerance = 1e-9 * (1.0 + torch.maximum(a_d.abs(), b_d.abs()))
    bad_point = ~(torch.isfinite(residual) & (residual <= tolerance) & (det > 0))
    if bool(bad_point.any()):
        i, j = (int(v) for v in torch.nonzero(bad_point)[0])
        names = ("k1", "k2", "k3", "k4", "p1", "p2")
        u, v = pixels[i, j].tolist()
        raise ValueError(
            f"{_coefficients(intrinsics64, i, names)} of camera {i} make the distortion fold inside the image: it "
            f"is not invertible at pixel ({u:.1f}, {v:.1f}); allowed are coefficients whose distortion stays "
            "one-to-one over the whole image"
        )


def tangent_distortion_jacobian(a: Tensor, b: Tensor, intrinsics: Intrinsics) -> Float[Tensor, "n l 2 2"]:
    """d(a_d, b_d)/d(a, b) of the perspective distortion."""
    k1, k2, k3, k4, p1, p2 = _columns(intrinsics, "k1", "k2", "k3", "k4", "p1", "p2")
    r2 = a * a + b * b
    factor = distortion_factor(r2, k1, k2, k3, k4)
    slope = distortion_slope(r2, k1, k2, k3, k4)
    return torch.stack(
        [
            torch.stack(
                [
                    factor + 2.0 * slope * a * a + (2.0 * p1 * b + 6.0 * p2 * a),
                    2.0 * slope * a * b + (2.0 * p1 * a + 2.0 * p2 * b),
                ],
                dim=-1,
            ),
            torch.stack(
                [
                    2.0 * slope * a * b + (2.0 * p2 * b + 2.0 * p1 * a),
                    factor + 2.0 * slope * b * b + (2.0 * p2 * a + 6.0 * p1 * b),
                ],
                dim=-1,
            ),
        ],
        dim=-2,
    )


def project(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics
) -> tuple[Float[Tensor, "n l 2"], Float[Tensor, "n l"]]:
    """Project camera-frame points to pixels (paper eq. 2, with skew and distortion); also return a validity margin.

    The margin is positive where the projection is valid and one-to-one: the depth z for perspective cameras; for
    fisheye cameras the angle theta_fold - theta (radians) to the first fold of theta_d(theta)
    (``fisheye_fold_angle``), so points beyond 90 degrees count and those past the fold or at the centre do not.
    Invalid points get finite but meaningless pixels; callers mask them with the margin (``in_image``).
    """
    if intrinsics.is_fisheye:
        terms = fisheye_terms(points_cam)
        k1, k2, k3, k4 = _columns(intrinsics, "k1", "k2", "k3", "k4")
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
    fx, fy, cx, cy, skew = _columns(intrinsics, "fx", "fy", "cx", "cy", "skew")
    u = fx * a_d + skew * b_d + cx
    v = fy * b_d + cy
    return torch.stack([u, v], dim=-1), margin


def undistort_scale(
    r_d2: Tensor,
    k1: Tensor,
    k2: Tensor,
    k3: Tensor | float = 0.0,
    k4: Tensor | float = 0.0,
    iterations: int = UNDISTORT_ITERATIONS,
) -> Tensor:
    """Scale s = r / r_d solving s (1 + k1 r_d^2 s^2 + k2 r_d^4 s^4 + k3 r_d^6 s^6 + k4 r_d^8 s^8) = 1.

    The inverse of the radial polynomial: r = s r_d for perspective cameras, theta = s theta_d for fisheye ones.
    Newton's method runs without autograd to convergence; one more Newton step with autograd on then gives the
    exact implicit-function gradient ds/dtheta = -(dg/dtheta) / g'(s), so undistortion stays differentiable
    without back-propagating through the iterations.
    """

    def residual(s: Tensor) -> tuple[Tensor, Tensor]:
        s2r = s * s * r_d2
        cubic = s2r * s2r * s2r
        g = s * (1.0 + k1 * s2r + k2 * s2r * s2r + cubic * (k3 + k4 * s2r)) - 1.0
        dg = 1.0 + 3.0 * k1 * s2r + 5.0 * k2 * s2r * s2r + cubic * (7.0 * k3 + 9.0 * k4 * s2r)
        return g, dg

    with torch.no_grad():
        s = torch.ones_like(r_d2)
        for _ in range(iterations):
            g, dg = residual(s)
            s = s - g / dg
    g, dg = residual(s)
    return s - g / dg.detach()


def _newton_tangential(
    a_d: Tensor, b_d: Tensor, intrinsics: Intrinsics, iterations: int = UNDISTORT_ITERATIONS
) -> tuple[Tensor, Tensor]:
    """Undistorted tangents (a, b) with distort_tangents(a, b) = (a_d, b_d) by 2-D Newton from (a_d, b_d).

    Runs without autograd; steps whose Jacobian is (nearly) singular are skipped, so a fold shows as a residual.
    """
    with torch.no_grad():
        a, b = a_d.detach().clone(), b_d.detach().clone()
        for _ in range(iterations):
            fa, fb = distort_tangents(a, b, intrinsics)
            jac = tangent_distortion_jacobian(a, b, intrinsics)
            ra, rb = fa - a_d, fb - b_d
            det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
            ok = det.abs() > 1e-12
            safe_det = torch.where(ok, det, torch.ones_like(det))
            step_a = (jac[..., 1, 1] * ra - jac[..., 0, 1] * rb) / safe_det
            step_b = (jac[..., 0, 0] * rb - jac[..., 1, 0] * ra) / safe_det
            a = a - torch.where(ok, step_a, torch.zeros_like(step_a))
            b = b - torch.where(ok, step_b, torch.zeros_like(step_b))
    return a, b


def undistort_tangents(a_d: Tensor, b_d: Tensor, intrinsics: Intrinsics) -> tuple[Tensor, Tensor]:
    """Inverse of ``distort_tangents``, differentiable through the implicit-function theorem.

    Radial-only cameras solve the scalar equation of ``undistort_scale``. With tangential terms, 2-D Newton converges
    without autograd, then one Newton step with autograd and the Jacobian detached gives
    d(a, b)/dtheta = -J^-1 dF/dtheta, the implicit-function gradient (F(a, b) = distortion - (a_d, b_d)).
    """
    if bool((intrinsics.p1.detach() == 0).all()) and bool((intrinsics.p2.detach() == 0).all()):
        k1, k2, k3, k4 = _columns(intrinsics, "k1", "k2", "k3", "k4")
        scale = undistort_scale(a_d * a_d + b_d * b_d, k1, k2, k3, k4)
        return a_d * scale, b_d * scale
    a, b = _newton_tangential(a_d, b_d, intrinsics)
    fa, fb = distort_tangents(a, b, intrinsics)
    jac = tangent_distortion_jacobian(a, b, intrinsics).detach()
    ra, rb = fa - a_d, fb - b_d
    det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
    return (
        a - (jac[..., 1, 1] * ra - jac[..., 0, 1] * rb) / det,
        b - (jac[..., 0, 0] * rb - jac[..., 1, 0] * ra) / det,
    )


def distorted_coordinates(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> tuple[Tensor, Tensor]:
    """(a_d, b_d) of pixels: the inverse of the affine map u = fx a_d + s b_d + cx, v = fy b_d + cy."""
    fx, fy, cx, cy, skew = _columns(intrinsics, "fx", "fy", "cx", "cy", "skew")
    b_d = (pixels[..., 1] - cy) / fy
    a_d = (pixels[..., 0] - cx - skew * b_d) / fx
    return a_d, b_d


def _fisheye_directions(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 3"]:
    """Unit directions of fisheye pixels: theta from theta_d = |(a_d, b_d)| by ``undistort_scale``."""
    a_d, b_d = distorted_coordinates(pixels, intrinsics)
    theta_d2 = a_d * a_d + b_d * b_d
    k1, k2, k3, k4 = _columns(intrinsics, "k1", "k2", "k3", "k4")
    scale = undistort_scale(theta_d2, k1, k2, k3, k4)  # theta / theta_d
    theta = scale * torch.sqrt(torch.clamp(theta_d2, min=torch.finfo(theta_d2.dtype).tiny))
    # sin(theta) / theta_d = scale * sinc(theta), finite on the optical axis.
    lateral = scale * torch.sinc(theta / math.pi)
    return torch.stack([a_d * lateral, b_d * lateral, torch.cos(theta)], dim=-1)


def unproject(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 2"]:
    """Undistorted tangents (a, b) = (x/z, y/z) of the rays through the given pixels (inverse of ``project``).

    For fisheye cameras these are tan(theta) times the ray's azimuth direction, defined only below 90 degrees; use
    ``pixel_to_ray_direction`` for rays at any angle.
    """
    if intrinsics.is_fisheye:
        directions = _fisheye_directions(pixels, intrinsics)
        return directions[..., :2] / directions[..., 2:]
    a_d, b_d = distorted_coordinates(pixels, intrinsics)
    a, b = undistort_tangents(a_d, b_d, intrinsics)
    return torch.stack([a, b], dim=-1)


def pixel_to_ray_direction(pixels: Float[Tensor, "n l 2"], intrinsics: Intrinsics) -> Float[Tensor, "n l 3"]:
    """Unit ray directions in the camera frame through the given pixels (fisheye: also beyond 90 degrees)."""
    if intrinsics.is_fisheye:
        return _fisheye_directions(pixels, intrinsics)
    tangents = unproject(pixels, intrinsics)
    directions = torch.cat([tangents, torch.ones_like(tangents[..., :1])], dim=-1)
    return directions / torch.linalg.norm(directions, dim=-1, keepdim=True)


def vertical_field_of_view(intrinsics: Intrinsics) -> Float[Tensor, " n"]:
    """Angle between the rays through the top and the bottom edge of the image at the principal point's column.

    The sum of the two rays' angles to the optical axis, so distortion and an off-centre principal point count, and
    a fisheye's field of view can exceed 180 degrees (pinhole with cy = h / 2: 2 atan(h / (2 fy))).
    """
    zeros = torch.zeros_like(intrinsics.cx)
    edges = torch.stack([torch.stack([intrinsics.cx, zeros], -1), torch.stack([intrinsics.cx, intrinsics.height], -1)])
    directions = pixel_to_ray_direction(edges.transpose(0, 1), intrinsics)
    off_axis = torch.atan2(torch.linalg.norm(directions[..., :2], dim=-1), directions[..., 2])
    return off_axis.sum(dim=-1)


def tangent_bounds(intrinsics: Intrinsics, samples_per_edge: int = 129, inset: float = 1e-5) -> Float[Tensor, "n 4"]:
    """Inner box (a_min, a_max, b_min, b_max) of undistorted tangents whose rays land inside the image.

    The image border is unprojected at ``samples_per_edge`` points per edge. With barrel distortion the border
    bends inwards in tangent space, so the box takes the innermost tangent of each edge; with pincushion
    distortion it bends outwards and the box corners are the undistorted image corners. Between the border
    samples the extreme tangent can lie slightly further in, so the box is inset by ``inset`` of its size.
    Perspective cameras only: a fisheye's field of view need not fit a tangent box (none exists past 90 degrees).
    """
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
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics, delta: Float[Tensor, "n 16"]
) -> Float[Tensor, "n l 2"]:
    """Pixels of the stacked projection Pi_P(Phi + dPhi) (paper eq. 4's function) for full 16-parameter deltas
    (or the paper's 12, see ``Intrinsics.with_delta``).

    This is the reference that the analytic Jacobian is tested against with autodiff and finite differences.
    """
    moved = apply_pose_delta(points_cam, delta[:, :6])
    pixels, _ = project(moved, intrinsics.with_delta(delta))
    return pixels


def in_image(pixels: Float[Tensor, "n l 2"], depth: Float[Tensor, "n l"], intrinsics: Intrinsics) -> Tensor:
    """Mask of valid points (``depth``: the margin ``project`` returns, positive in front of a perspective camera
    and inside a fisheye's one-to-one range) that project inside [0, W] x [0, H]."""
    u, v = pixels[..., 0], pixels[..., 1]
    return (
        (depth > 0)
        & (u >= 0)
        & (v >= 0)
        & (u <= intrinsics.width[:, None])
        & (v <= intrinsics.height[:, None])
        & torch.isfinite(pixels).all(dim=-1)
    )
