"""The camera-parameter preconditioner P = (Sigma + damping)^(1/2) (paper eqs. 15-20).

Whitening requires P^T P = Sigma (eq. 17); the solutions are Q Sigma^(1/2), Q orthogonal (eqs. 18-19), and the paper
picks the symmetric root Q = I (eq. 20). The optimizer works on phi_hat = P phi, the camera uses phi = P^-1 phi_hat
(eq. 15). Sigma is often nearly singular (focal against forward translation, principal point against rotation), so
the diagonal damping diag(max(damping_abs, damping_rel * diag(Sigma))) is added first, as in CamP; it also keeps P
finite and invertible for parameters the proxy points cannot observe.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.compat import DefaultsOnLoad
from s2camp_ns.core.camera import Intrinsics, ParameterLayout, pixel_to_ray_direction, tangent_bounds
from s2camp_ns.core.camp_sampling import CAMP_LADDER_P, CAMP_T_FAR, CAMP_T_NEAR, camp_frustum_points, validate_ladder
from s2camp_ns.core.contraction import uncontract_radius
from s2camp_ns.core.frustum import RADIALS, Radial, radius_from_unit, radius_per_camera, sample_frustum
from s2camp_ns.core.jacobian import gram_matrix, projection_jacobian
from s2camp_ns.core.lattice import unit_cube_points
from s2camp_ns.core.proxy_range import DEFAULT_T_FAR, DEFAULT_T_NEAR, ProxyRangeConfig, fixed_range, validate_overrides
from s2camp_ns.core.validation import check_choice, check_finite, check_positive_int, check_range

SamplerName = Literal["frolov", "sobol", "halton", "random", "camp-random"]
TransformName = Literal["pyramid", "spherical", "pixel"]
SAMPLERS: tuple[str, ...] = ("frolov", "sobol", "halton", "random", "camp-random")
TRANSFORMS: tuple[str, ...] = ("pyramid", "spherical", "pixel")
DEFAULT_CHUNK_SIZE = 1024  # cameras per chunk of ``compute_preconditioner``: bounds its float64 intermediates


@dataclass(frozen=True)
class SamplingConfig(DefaultsOnLoad):
    """Where and how the proxy points are placed (paper sec. 4, "Deterministic View-Frustum Sampling")."""

    num_points: int = 500
    """L, proxy points per camera."""
    sampler: SamplerName = "frolov"
    """Unit-cube point set: the Frolov lattice, a quasi-random or random baseline, or CamP's "camp-random" (random
    pixel and power-ladder ray distance, ``core.camp_sampling``; ``t_near`` / ``t_far`` then ray distances)."""
    transform: TransformName = "pyramid"
    """Unit cube to directions: the pinhole pyramid, the paper's spherical transform, or uniform image-plane tangents
    ("pixel"). Perspective only: fisheye cameras are sampled uniformly in the image."""
    radial: Radial = "volume"
    """Radial map: uniform in contracted volume ("volume", paper eq. 12) or in contracted distance along the ray."""
    t_near: float | None = None
    """Near contracted radius (scene units). None: chosen per camera from the scene's points (``auto_range``), 0.4
    without points; a number applies to every camera."""
    t_far: float | None = None
    """Far contracted radius, below 2 (distance 1 / (2 - t_far) beyond 1, paper eq. 10). None: chosen per camera
    from the scene's points (``auto_range``), 1.5 without points; a number applies to every camera."""
    auto_range: ProxyRangeConfig = field(default_factory=ProxyRangeConfig)
    """How an unset ``t_near`` / ``t_far`` is chosen from the points each camera sees (``core.proxy_range``)."""
    seed: int = 0
    """Seed of the random and scrambled samplers."""
    ladder_p: float = CAMP_LADDER_P
    """Negative exponent of "camp-random"'s power-ladder ray warp."""

    def validate(self) -> None:
        check_positive_int("num_points", self.num_points)
        check_choice("sampler", self.sampler, SAMPLERS)
        check_choice("transform", self.transform, TRANSFORMS)
        check_choice("radial", self.radial, RADIALS)
        if self.sampler == "camp-random":
            validate_ladder(*self.fixed_range(), self.ladder_p)
            return
        self.auto_range.validate()
        validate_overrides(self.t_near, self.t_far, self.auto_range)

    @property
    def auto(self) -> bool:
        """Whether some end of the range is chosen from the scene."""
        return self.sampler != "camp-random" and (self.t_near is None or self.t_far is None)

    def fixed_range(self) -> tuple[float, float]:
        """(t_near, t_far) without scene points: given ends, else the defaults (``proxy_range.fixed_range``)."""
        if self.sampler == "camp-random":  # ray distances, never from the scene
            near = DEFAULT_T_NEAR if self.t_near is None else self.t_near
            return near, DEFAULT_T_FAR if self.t_far is None else self.t_far
        return fixed_range(self.auto_range, self.t_near, self.t_far)


CAMP_SAMPLING = SamplingConfig(num_points=5000, sampler="camp-random", t_near=CAMP_T_NEAR, t_far=CAMP_T_FAR)
"""CamP's published proxy points (configs/camp/camera_optim.gin): 5000 points, ray distances 0.4 to 1000."""


@dataclass(frozen=True)
class DampingConfig:
    """Diagonal damping added to Sigma before the square root; defaults are CamP's (configs/camp/camera_optim.gin)."""

    damping_abs: float = 1e-8
    """Absolute floor of the damping, > 0: keeps P finite for unobservable parameters."""
    damping_rel: float = 0.1
    """Damping relative to Sigma's diagonal."""
    diagonal_only: bool = False
    """Use only Sigma's diagonal (per-parameter scaling, no decorrelation)."""

    def validate(self) -> None:
        check_range("damping_abs", self.damping_abs, low=0.0, low_inclusive=False)
        check_range("damping_rel", self.damping_rel, low=0.0)


@dataclass(frozen=True)
class Preconditioner:
    """P, P^-1, the undamped Gram matrix, and the proxy points projecting inside each image."""

    matrix: Float[Tensor, "n k k"]
    inverse: Float[Tensor, "n k k"]
    gram: Float[Tensor, "n k k"]
    num_valid: Tensor


def damped_gram(sigma: Float[Tensor, "n k k"], damping: DampingConfig) -> Float[Tensor, "n k k"]:
    """Sigma + diag(max(damping_abs, damping_rel * diag(Sigma)))."""
    damping.validate()
    diagonal = torch.diagonal(sigma, dim1=-2, dim2=-1)
    extra = torch.clamp(damping.damping_rel * diagonal, min=damping.damping_abs)
    return sigma + torch.diag_embed(extra)


def symmetric_sqrt_and_inverse(
    sigma: Float[Tensor, "n k k"], diagonal_only: bool = False
) -> tuple[Float[Tensor, "n k k"], Float[Tensor, "n k k"]]:
    """Float64 Sigma^(1/2) and Sigma^(-1/2) by eigendecomposition (paper eq. 20); ValueError unless SPD."""
    sigma = sigma.to(torch.float64)
    check_finite("sigma", sigma)
    if diagonal_only:
        diagonal = torch.diagonal(sigma, dim1=-2, dim2=-1)
        check_range("diagonal of sigma", diagonal, low=0.0, low_inclusive=False)
        return torch.diag_embed(diagonal.sqrt()), torch.diag_embed(diagonal.rsqrt())
    eigenvalues, eigenvectors = torch.linalg.eigh(0.5 * (sigma + sigma.transpose(-1, -2)))
    check_range("eigenvalues of sigma", eigenvalues, low=0.0, low_inclusive=False)
    root = (eigenvectors * eigenvalues.sqrt()[..., None, :]) @ eigenvectors.transpose(-1, -2)
    inverse_root = (eigenvectors * eigenvalues.rsqrt()[..., None, :]) @ eigenvectors.transpose(-1, -2)
    return 0.5 * (root + root.transpose(-1, -2)), 0.5 * (inverse_root + inverse_root.transpose(-1, -2))


def sample_fisheye_points(
    intrinsics: Intrinsics, sampling: SamplingConfig, ranges: Float[Tensor, "n 2"] | None = None
) -> Float[Tensor, "n l 3"]:
    """Fisheye proxy points: pixel (u3 W, u2 H) unprojected, at contracted radius Q_r(u1) (paper eqs. 10, 12).
    ``ranges``: [t_near, t_far] per camera (None: the fixed range)."""
    intrinsics = intrinsics.detach().to(dtype=torch.float64)
    shared = unit_cube_points(sampling.sampler, sampling.num_points, seed=sampling.seed).to(torch.float64)
    shared = shared.to(intrinsics.device)
    unit = shared.expand(intrinsics.num_cameras, -1, -1)
    size = torch.stack([intrinsics.width, intrinsics.height], dim=-1)[:, None, :]
    pixels = torch.stack([unit[..., 2], unit[..., 1]], dim=-1) * size
    with torch.no_grad():
        directions = pixel_to_ray_direction(pixels, intrinsics)
    if ranges is not None:  # per camera: independent of the batch
        radius = radius_per_camera(shared[:, 0], ranges[:, 0], ranges[:, 1], sampling.radial).to(directions.device)
        return uncontract_radius(radius)[..., None] * directions
    # one radius for all cameras, so a camera's points do not depend on its batch
    t_near, t_far = sampling.fixed_range()
    radius = radius_from_unit(shared[:, 0], t_near, t_far, sampling.radial)
    return uncontract_radius(radius)[:, None] * directions


def sample_proxy_points(
    intrinsics: Intrinsics,
    sampling: SamplingConfig,
    generator: torch.Generator | None = None,
    ranges: Float[Tensor, "n 2"] | None = None,
) -> Float[Tensor, "n l 3"]:
    """[n, l, 3] camera-frame proxy points filling each contracted frustum (paper eqs. 6-14). ``generator``:
    "camp-random"'s stream, continued across chunks. ``ranges``: [n, 2] contracted [t_near, t_far] (None: fixed)."""
    sampling.validate()
    if ranges is not None:
        ranges = _check_ranges(ranges, intrinsics.num_cameras, sampling)
    if sampling.sampler == "camp-random":  # random pixels, unprojected: any camera model
        t_near, t_far = sampling.fixed_range()
        return camp_frustum_points(
            intrinsics, sampling.num_points, t_near, t_far, sampling.ladder_p, generator=generator, seed=sampling.seed
        )
    if intrinsics.is_fisheye:
        return sample_fisheye_points(intrinsics, sampling, ranges)
    bounds = tangent_bounds(intrinsics.to(dtype=torch.float64))
    unit = unit_cube_points(sampling.sampler, sampling.num_points, seed=sampling.seed)
    if ranges is None:
        t_near, t_far = sampling.fixed_range()
    else:
        t_near, t_far = ranges[:, 0].to(bounds.device), ranges[:, 1].to(bounds.device)
    return sample_frustum(unit.to(bounds.device), bounds, t_near, t_far, sampling.transform, sampling.radial).camera


def _check_ranges(ranges: Tensor, num_cameras: int, sampling: SamplingConfig) -> Tensor:
    """[N, 2] float64 ranges with 0 <= t_near < t_far < 2, else ValueError."""
    if sampling.sampler == "camp-random":
        raise ValueError('ranges must be None for sampler "camp-random" (its t_near / t_far are ray distances)')
    if not isinstance(ranges, Tensor) or ranges.ndim != 2 or tuple(ranges.shape) != (num_cameras, 2):
        shape = tuple(ranges.shape) if isinstance(ranges, Tensor) else type(ranges).__name__
        raise ValueError(f"ranges must have shape [{num_cameras}, 2] ([t_near, t_far] per camera), got {shape}")
    ranges = ranges.detach().to(torch.float64)
    check_range("ranges t_near", ranges[:, 0], low=0.0)
    check_range("ranges t_far", ranges[:, 1], high=2.0, high_inclusive=False)
    check_range("ranges t_far - t_near", ranges[:, 1] - ranges[:, 0], low=0.0, low_inclusive=False)
    return ranges


def gram_from_points(
    points_cam: Float[Tensor, "n l 3"], intrinsics: Intrinsics, layout: ParameterLayout | None = None
) -> tuple[Float[Tensor, "n k k"], Tensor]:
    """Float64 Sigma (paper eq. 5) and the valid count from camera-frame proxy points."""
    intrinsics64 = intrinsics.detach().to(dtype=torch.float64)
    _, jacobian, mask = projection_jacobian(points_cam.detach().to(torch.float64), intrinsics64, layout)
    return gram_matrix(jacobian, mask, intrinsics64.image_scale())


def compute_preconditioner(
    intrinsics: Intrinsics,
    layout: ParameterLayout | None = None,
    sampling: SamplingConfig | None = None,
    damping: DampingConfig | None = None,
    chunk_size: int | None = DEFAULT_CHUNK_SIZE,
    share_intrinsics: bool = True,
    ranges: Float[Tensor, "n 2"] | None = None,
) -> Preconditioner:
    """P and P^-1 per camera from proxy points in its frustum (paper eqs. 4, 5, 20), ``chunk_size`` cameras at a time.
    ``ranges``: [n, 2] contracted [t_near, t_far] (None: fixed). With ``share_intrinsics``, cameras with bitwise-equal
    intrinsics and range share one computation. Bit-identical for any chunk size, except the last bits of
    "camp-random" (per-point ``pow`` and undistortion round differently in vectorised and scalar loops)."""
    sampling = sampling or SamplingConfig()
    damping = damping or DampingConfig()
    sampling.validate()
    damping.validate()
    if chunk_size is not None:
        check_positive_int("chunk_size", chunk_size)
    intrinsics = intrinsics.detach().to(dtype=torch.float64).general()  # P depends on the values alone
    intrinsics.validate()
    if ranges is not None:
        ranges = _check_ranges(ranges, intrinsics.num_cameras, sampling)
    if share_intrinsics and sampling.sampler != "camp-random":
        unique, index, unique_ranges = unique_intrinsics(intrinsics, ranges)
        if unique.num_cameras < intrinsics.num_cameras:
            shared = compute_preconditioner(
                unique, layout, sampling, damping, chunk_size, share_intrinsics=False, ranges=unique_ranges
            )
            return Preconditioner(
                matrix=shared.matrix[index],
                inverse=shared.inverse[index],
                gram=shared.gram[index],
                num_valid=shared.num_valid[index],
            )
    generator = torch.Generator().manual_seed(int(sampling.seed)) if sampling.sampler == "camp-random" else None
    n = intrinsics.num_cameras
    step = chunk_size or max(n, 1)
    result: Preconditioner | None = None
    for start in range(0, max(n, 1), step):
        part = intrinsics[start : start + step]
        part_ranges = None if ranges is None else ranges[start : start + step]
        points = sample_proxy_points(part, sampling, generator, part_ranges)
        sigma, count = gram_from_points(points, part, layout)
        del points
        matrix, inverse = symmetric_sqrt_and_inverse(damped_gram(sigma, damping), damping.diagonal_only)
        if step >= n:
            return Preconditioner(matrix=matrix, inverse=inverse, gram=sigma, num_valid=count)
        if result is None:  # filled in place, no second copy
            result = Preconditioner(
                matrix=matrix.new_empty((n, *matrix.shape[1:])),
                inverse=inverse.new_empty((n, *inverse.shape[1:])),
                gram=sigma.new_empty((n, *sigma.shape[1:])),
                num_valid=count.new_empty((n, *count.shape[1:])),
            )
        stop = start + part.num_cameras
        result.matrix[start:stop] = matrix
        result.inverse[start:stop] = inverse
        result.gram[start:stop] = sigma
        result.num_valid[start:stop] = count
    assert result is not None
    return result


def unique_intrinsics(
    intrinsics: Intrinsics, ranges: Float[Tensor, "n 2"] | None = None
) -> tuple[Intrinsics, Tensor, Tensor | None]:
    """(Distinct cameras by bitwise intrinsics and range, [n] index into them, their ranges or None)."""
    stacked = intrinsics.tensors()
    width = stacked.shape[-1]
    if ranges is not None:
        stacked = torch.cat([stacked, ranges.to(stacked)], dim=-1)
    unique, index = torch.unique(stacked, dim=0, return_inverse=True)
    unique_ranges = None if ranges is None else unique[:, width:]
    return Intrinsics.from_tensors(unique[:, :width], intrinsics.model, **intrinsics.form), index, unique_ranges


def whitening_error(inverse: Float[Tensor, "n k k"], sigma: Float[Tensor, "n k k"]) -> Float[Tensor, " n"]:
    """max |eigenvalue - 1| of P^-T Sigma P^-1 (paper eq. 16): zero for perfect whitening."""
    whitened = inverse.transpose(-1, -2).to(torch.float64) @ sigma.to(torch.float64) @ inverse.to(torch.float64)
    eigenvalues = torch.linalg.eigvalsh(0.5 * (whitened + whitened.transpose(-1, -2)))
    return (eigenvalues - 1.0).abs().amax(dim=-1)


def condition_number(sigma: Float[Tensor, "n k k"]) -> Float[Tensor, " n"]:
    """Largest over smallest eigenvalue of symmetric PSD matrices."""
    eigenvalues = torch.linalg.eigvalsh(sigma.to(torch.float64))
    return eigenvalues[..., -1] / eigenvalues[..., 0].clamp(min=torch.finfo(torch.float64).tiny)
