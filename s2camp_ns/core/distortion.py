"""Lens distortion of ``core.camera``: forward maps, their derivatives and inverses, and the one-to-one check.

Coefficients k1, k2, k3, k4, p1, p2 of N ``Intrinsics`` are read as [N, 1] columns broadcasting against per-point
[N, L] tensors (``per_camera_columns``). ``core.camera`` imports this module; what this one reads of its ``Intrinsics``
is the protocol ``Lens``.

- perspective (OpenCV) on tangents (a, b) = (x / z, y / z), r^2 = a^2 + b^2:
  a_d = a D + 2 p1 a b + p2 (r^2 + 2 a^2), b_d = b D + 2 p2 a b + p1 (r^2 + 2 b^2),
  D = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 (``distortion_factor``);
- fisheye (OpenCV equidistant): theta = atan2(sqrt(x^2 + y^2), z), theta_d = theta D(theta^2) (``fisheye_terms``).

Inverses (``undistort_scale``, ``undistort_tangents``) run Newton without autograd, then one Newton step with autograd
for the exact implicit-function gradient. ``check_distortion_monotonic`` rejects distortion that folds in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

import torch
from jaxtyping import Float
from torch import Tensor

UNDISTORT_ITERATIONS = 20


class Lens(Protocol):
    """What the functions here read of N cameras (``core.camera.Intrinsics``): [N] tensors, and the form."""

    fx: Tensor
    fy: Tensor
    cx: Tensor
    cy: Tensor
    skew: Tensor
    width: Tensor
    height: Tensor
    k1: Tensor
    k2: Tensor
    k3: Tensor
    k4: Tensor
    p1: Tensor
    p2: Tensor
    distortion_terms: tuple[str, ...] | None
    """The coefficients that may be nonzero (None: read from the values)."""
    newton_iterations: int

    @property
    def is_fisheye(self) -> bool: ...

    @property
    def num_cameras(self) -> int: ...

    @property
    def device(self) -> torch.device: ...

    @property
    def dtype(self) -> torch.dtype: ...

    def detach(self) -> Lens: ...


Coefficient = Tensor | float | None  # None: the form has no such term, left out of the arithmetic


def distortion_factor(r2: Tensor, k1: Tensor, k2: Tensor, k3: Coefficient = 0.0, k4: Coefficient = 0.0) -> Tensor:
    """1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 (fisheye: theta_d / theta for r^2 = theta^2); k1 None: 1."""
    if k1 is None:
        return 1.0
    if k3 is None and k4 is None:
        return 1.0 + r2 * (k1 + k2 * r2)
    k3, k4 = (0.0 if k is None else k for k in (k3, k4))
    return 1.0 + r2 * (k1 + k2 * r2 + r2 * r2 * (k3 + k4 * r2))


def distortion_slope(r2: Tensor, k1: Tensor, k2: Tensor, k3: Coefficient = 0.0, k4: Coefficient = 0.0) -> Tensor:
    """d(distortion_factor)/d(r^2) = k1 + 2 k2 r^2 + 3 k3 r^4 + 4 k4 r^6; k1 None: 0."""
    if k1 is None:
        return 0.0
    if k3 is None and k4 is None:
        return k1 + 2.0 * k2 * r2
    k3, k4 = (0.0 if k is None else k for k in (k3, k4))
    return k1 + 2.0 * k2 * r2 + r2 * r2 * (3.0 * k3 + 4.0 * k4 * r2)


def per_camera_columns(intrinsics: Lens, *names: str) -> tuple[Tensor, ...]:
    """Per-camera fields as [N, 1] columns that broadcast against per-point [N, L] tensors."""
    return tuple(getattr(intrinsics, name)[:, None] for name in names)


DISTORTION_NAMES: tuple[str, ...] = ("k1", "k2", "k3", "k4", "p1", "p2")


def distortion_columns(intrinsics: Lens) -> tuple[Tensor | None, ...]:
    """k1, k2, k3, k4, p1, p2 as [N, 1] columns, None for terms outside ``Lens.distortion_terms``."""
    terms = intrinsics.distortion_terms
    return tuple(
        getattr(intrinsics, name)[:, None] if terms is None or name in terms else None for name in DISTORTION_NAMES
    )


def _tangential_terms(a: Tensor, b: Tensor, r2: Tensor, p1: Coefficient, p2: Coefficient) -> tuple:
    """OpenCV tangential terms (2 p1 a b + p2 (r^2 + 2 a^2), 2 p2 a b + p1 (r^2 + 2 b^2)), (0, 0) without."""
    if p1 is None and p2 is None:
        return 0.0, 0.0
    p1, p2 = (0.0 if p is None else p for p in (p1, p2))
    return 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a), 2.0 * p2 * a * b + p1 * (r2 + 2.0 * b * b)


def distort_tangents(a: Tensor, b: Tensor, intrinsics: Lens) -> tuple[Tensor, Tensor]:
    """Perspective distortion (a, b) -> (a_d, b_d) (module doc)."""
    return _distort(a, b, distortion_columns(intrinsics))


def _distort(a: Tensor, b: Tensor, columns: tuple) -> tuple[Tensor, Tensor]:
    k1, k2, k3, k4, p1, p2 = columns
    if all(column is None for column in columns):
        return a, b
    r2 = a * a + b * b
    factor = distortion_factor(r2, k1, k2, k3, k4)
    tangential_a, tangential_b = _tangential_terms(a, b, r2, p1, p2)
    return a * factor + tangential_a, b * factor + tangential_b


def tangent_distortion_jacobian(a: Tensor, b: Tensor, intrinsics: Lens) -> Float[Tensor, "n l 2 2"]:
    """d(a_d, b_d)/d(a, b) of the perspective distortion."""
    return _distortion_jacobian(a, b, distortion_columns(intrinsics))


def _distortion_jacobian(a: Tensor, b: Tensor, columns: tuple) -> Float[Tensor, "n l 2 2"]:
    k1, k2, k3, k4, p1, p2 = columns
    p1, p2 = (0.0 if p is None else p for p in (p1, p2))
    r2 = a * a + b * b
    factor = distortion_factor(r2, k1, k2, k3, k4)
    slope = distortion_slope(r2, k1, k2, k3, k4)
    return torch.stack([
        torch.stack([factor + 2.0 * slope * a * a + (2.0 * p1 * b + 6.0 * p2 * a),
                     2.0 * slope * a * b + (2.0 * p1 * a + 2.0 * p2 * b)], dim=-1),
        torch.stack([2.0 * slope * a * b + (2.0 * p2 * b + 2.0 * p1 * a),
                     factor + 2.0 * slope * b * b + (2.0 * p2 * a + 6.0 * p1 * b)], dim=-1),
    ], dim=-2)  # fmt: skip


FISHEYE_SERIES_BELOW = 1e-4  # below this rho / z, theta / rho comes from its Taylor series


@dataclass(frozen=True)
class FisheyeTerms:
    """Per-point terms of the equidistant projection, safe on the optical axis and behind the camera: h = theta / rho,
    theta2, q = (z / R - h) / rho^2 (dh/dx = x q), norm2 = R = x^2 + y^2 + z^2, theta (no gradient)."""

    h: Tensor
    theta2: Tensor
    q: Tensor
    norm2: Tensor
    theta: Tensor


def fisheye_terms(points_cam: Float[Tensor, "n l 3"]) -> FisheyeTerms:
    """``FisheyeTerms`` of [n, l, 3] camera points: theta = atan2(rho, z), Taylor branches where rho << z."""
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


def fisheye_fold_angle(intrinsics: Lens) -> tuple[Float[Tensor, " n"], Float[Tensor, " n"]]:
    """([n] theta_fold in (0, pi] up to which theta_d increases, [n] theta_d there), scanned on a grid; no gradient."""
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


def _radial_residual(
    s: Tensor, r_d2: Tensor, k1: Tensor, k2: Tensor, k3: Coefficient, k4: Coefficient
) -> tuple[Tensor, Tensor]:
    """g(s) = s D(s^2 r_d^2) - 1 and g'(s) (``undistort_scale``)."""
    s2r = s * s * r_d2
    if k3 is None and k4 is None:  # Horner in u = s^2 r_d^2: g = s (1 + u (k1 + k2 u)) - 1, g' = 1 + u (3 k1 + 5 k2 u)
        u_poly = s2r * torch.addcmul(k1, k2, s2r)
        return torch.addcmul(s, s, u_poly) - 1.0, 1.0 + s2r * torch.addcmul(3.0 * k1, 5.0 * k2, s2r)
    k3, k4 = (0.0 if k is None else k for k in (k3, k4))
    cubic = s2r * s2r * s2r
    g = s * (1.0 + k1 * s2r + k2 * s2r * s2r + cubic * (k3 + k4 * s2r)) - 1.0
    dg = 1.0 + 3.0 * k1 * s2r + 5.0 * k2 * s2r * s2r + cubic * (7.0 * k3 + 9.0 * k4 * s2r)
    return g, dg


def undistort_scale(
    r_d2: Tensor,
    k1: Tensor,
    k2: Tensor,
    k3: Coefficient = 0.0,
    k4: Coefficient = 0.0,
    iterations: int = UNDISTORT_ITERATIONS,
) -> Tensor:
    """s = r / r_d (fisheye: theta / theta_d) solving s D(s^2 r_d^2) = 1: Newton from s = 1 without autograd, then
    one step with autograd, giving the implicit-function gradient ds/dtheta = -(dg/dtheta) / g'(s)."""
    with torch.no_grad():
        s = torch.ones_like(r_d2)
        for _ in range(iterations):
            g, dg = _radial_residual(s, r_d2, k1, k2, k3, k4)
            s = s - g / dg
    g, dg = _radial_residual(s, r_d2, k1, k2, k3, k4)
    return s - g / dg.detach()


def _tangential_newton_step(a: Tensor, b: Tensor, a_d: Tensor, b_d: Tensor, columns: tuple) -> tuple[Tensor, Tensor]:
    """One 2-D Newton step on distort(a, b) = (a_d, b_d); skipped where the Jacobian is (nearly) singular."""
    fa, fb = _distort(a, b, columns)
    jac = _distortion_jacobian(a, b, columns)
    ra, rb = fa - a_d, fb - b_d
    det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
    ok = det.abs() > 1e-12
    safe_det = torch.where(ok, det, torch.ones_like(det))
    step_a = (jac[..., 1, 1] * ra - jac[..., 0, 1] * rb) / safe_det
    step_b = (jac[..., 0, 0] * rb - jac[..., 1, 0] * ra) / safe_det
    return a - torch.where(ok, step_a, torch.zeros_like(step_a)), b - torch.where(ok, step_b, torch.zeros_like(step_b))


def _newton_tangential(
    a_d: Tensor, b_d: Tensor, columns: tuple, iterations: int = UNDISTORT_ITERATIONS
) -> tuple[Tensor, Tensor]:
    """(a, b) with distort(a, b) = (a_d, b_d) by 2-D Newton from (a_d, b_d), without autograd."""
    with torch.no_grad():
        a, b = a_d.detach().clone(), b_d.detach().clone()
        for _ in range(iterations):
            a, b = _tangential_newton_step(a, b, a_d, b_d, columns)
    return a, b


def _undistortion_form(intrinsics: Lens) -> tuple[tuple[str, ...], int]:
    """(terms, Newton iterations): the declared form, or, undeclared, read from the values (a host read)."""
    if intrinsics.distortion_terms is not None:
        return intrinsics.distortion_terms, intrinsics.newton_iterations
    tangential = not (bool((intrinsics.p1.detach() == 0).all()) and bool((intrinsics.p2.detach() == 0).all()))
    return DISTORTION_NAMES if tangential else DISTORTION_NAMES[:4], UNDISTORT_ITERATIONS


def undistort_tangents(a_d: Tensor, b_d: Tensor, intrinsics: Lens) -> tuple[Tensor, Tensor]:
    """Inverse of ``distort_tangents``: radial-only via ``undistort_scale``; tangential by 2-D Newton, then one step
    with the Jacobian detached, the implicit-function gradient d(a, b)/dtheta = -J^-1 dF/dtheta."""
    terms, iterations = _undistortion_form(intrinsics)
    if not terms:
        return a_d, b_d
    if intrinsics.distortion_terms is None:  # undeclared: every term read
        intrinsics = replace(intrinsics, distortion_terms=terms)
    columns = distortion_columns(intrinsics)
    k1, k2, k3, k4, p1, p2 = columns
    if p1 is None and p2 is None:
        scale = undistort_scale(a_d * a_d + b_d * b_d, k1, k2, k3, k4, iterations)
        return a_d * scale, b_d * scale
    a, b = _newton_tangential(a_d, b_d, columns, iterations)
    fa, fb = _distort(a, b, columns)
    jac = _distortion_jacobian(a, b, columns).detach()
    ra, rb = fa - a_d, fb - b_d
    det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
    return (
        a - (jac[..., 1, 1] * ra - jac[..., 0, 1] * rb) / det,
        b - (jac[..., 0, 0] * rb - jac[..., 1, 0] * ra) / det,
    )


MIN_NEWTON_ITERATIONS = 2  # fewest Newton steps for a camera with distortion
NEWTON_TOLERANCE = 1e-10  # largest relative error of the undistorted tangents
COEFFICIENT_MARGIN = 2.0  # counted with coefficients this many times as large: room to refine until the next refresh


def undistortion_iterations(intrinsics: Lens) -> int:
    """Newton steps (0 without distortion, else at least ``MIN_NEWTON_ITERATIONS``) inverting every ``image_grid``
    pixel to ``NEWTON_TOLERANCE``, the coefficients scaled by ``COEFFICIENT_MARGIN`` unless that folds."""
    terms = intrinsics.distortion_terms
    if terms is not None and not terms:
        return 0
    cameras = intrinsics.detach().to(dtype=torch.float64)
    if terms is None:
        cameras = replace(cameras, distortion_terms=DISTORTION_NAMES)
    scaled = replace(cameras, **{name: getattr(cameras, name) * COEFFICIENT_MARGIN for name in DISTORTION_NAMES})
    try:
        check_distortion_monotonic(scaled)
        cameras = scaled
    except ValueError:
        pass
    a_d, b_d = distorted_coordinates(image_grid(cameras), cameras)
    columns = distortion_columns(cameras)
    k1, k2, k3, k4, p1, p2 = columns
    iterates: list[tuple[Tensor, ...]] = []
    with torch.no_grad():
        if (p1 is None and p2 is None) or cameras.is_fisheye:
            r_d2, s = a_d * a_d + b_d * b_d, torch.ones_like(a_d)
            for _ in range(UNDISTORT_ITERATIONS):
                g, dg = _radial_residual(s, r_d2, k1, k2, k3, k4)
                s = s - g / dg
                iterates.append((s,))
        else:
            a, b = a_d.clone(), b_d.clone()
            for _ in range(UNDISTORT_ITERATIONS):
                a, b = _tangential_newton_step(a, b, a_d, b_d, columns)
                iterates.append((a, b))
    limit = iterates[-1]
    scale = 1.0 + torch.stack([value.abs() for value in limit]).amax()
    for count, values in enumerate(iterates, start=1):
        error = torch.stack([(value - reference).abs() for value, reference in zip(values, limit, strict=True)]).amax()
        if count >= MIN_NEWTON_ITERATIONS and bool(error <= NEWTON_TOLERANCE * scale):
            return count
    return UNDISTORT_ITERATIONS


def distorted_coordinates(pixels: Float[Tensor, "n l 2"], intrinsics: Lens) -> tuple[Tensor, Tensor]:
    """(a_d, b_d) of pixels: the inverse of the affine map u = fx a_d + s b_d + cx, v = fy b_d + cy."""
    fx, fy, cx, cy, skew = per_camera_columns(intrinsics, "fx", "fy", "cx", "cy", "skew")
    b_d = (pixels[..., 1] - cy) / fy
    a_d = (pixels[..., 0] - cx - skew * b_d) / fx
    return a_d, b_d


def _corner_distorted_radius(intrinsics: Lens) -> Tensor:
    """Largest distorted radius |(a_d, b_d)| over the four image corners, [N]."""
    us = torch.stack([torch.zeros_like(intrinsics.width), intrinsics.width], dim=-1)
    vs = torch.stack([torch.zeros_like(intrinsics.height), intrinsics.height], dim=-1)
    b_d = (vs - intrinsics.cy[:, None]) / intrinsics.fy[:, None]
    a_d = us[:, :, None] - intrinsics.cx[:, None, None] - intrinsics.skew[:, None, None] * b_d[:, None, :]
    a_d = a_d / intrinsics.fx[:, None, None]
    r_d = torch.sqrt(a_d**2 + b_d[:, None, :] ** 2)
    return r_d.reshape(intrinsics.num_cameras, -1).amax(dim=-1)


def _coefficients(intrinsics: Lens, index: int, names: tuple[str, ...]) -> str:
    return ", ".join(names) + " = (" + ", ".join(f"{getattr(intrinsics, n)[index].item():g}" for n in names) + ")"


def check_distortion_monotonic(intrinsics: Lens) -> None:
    """ValueError, naming the coefficients and the camera, unless the distortion is one-to-one over the image:
    analytic fold radius (k1, k2 only), a grid check (other perspective) or ``fisheye_fold_angle`` (fisheye)."""
    if intrinsics.is_fisheye:
        _check_fisheye(intrinsics)
        return
    extra = torch.stack([intrinsics.k3, intrinsics.k4, intrinsics.p1, intrinsics.p2]).detach()
    if bool((extra == 0).all()):
        _check_radial(intrinsics)
    else:
        _check_perspective_grid(intrinsics)


def _check_radial(intrinsics: Lens) -> None:
    """r (1 + k1 r^2 + k2 r^4) must increase up to the corners: its distorted radius at the fold, the smallest
    positive root of 1 + 3 k1 s + 5 k2 s^2 (s = r^2), must exceed the corner radius."""
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


def _check_fisheye(intrinsics: Lens) -> None:
    """theta_d(theta) must increase from the optical axis up to the image corners."""
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


def image_grid(intrinsics: Lens, edge: int = GRID_EDGE_SAMPLES, interior: int = GRID_INTERIOR_SAMPLES) -> Tensor:
    """Pixels [N, L, 2] on the image border (``edge`` per side) and on an ``interior`` x ``interior`` grid."""
    t = torch.linspace(0.0, 1.0, edge, dtype=intrinsics.dtype, device=intrinsics.device)
    s = torch.linspace(0.0, 1.0, interior, dtype=intrinsics.dtype, device=intrinsics.device)
    zeros, ones = torch.zeros_like(t), torch.ones_like(t)
    border = torch.cat([torch.stack(pair, dim=-1) for pair in ((t, zeros), (t, ones), (zeros, t), (ones, t))], dim=0)
    inner = torch.stack(torch.meshgrid(s, s, indexing="ij"), dim=-1).reshape(-1, 2)
    unit = torch.cat([border, inner], dim=0)
    size = torch.stack([intrinsics.width, intrinsics.height], dim=-1)
    return unit[None] * size[:, None, :]


def _check_perspective_grid(intrinsics: Lens) -> None:
    """Undistortion must converge with an invertible Jacobian on ``image_grid``."""
    intrinsics64 = intrinsics.detach().to(dtype=torch.float64)
    pixels = image_grid(intrinsics64)
    a_d, b_d = distorted_coordinates(pixels, intrinsics64)
    with torch.no_grad():
        a, b = _newton_tangential(a_d, b_d, distortion_columns(intrinsics64))
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
