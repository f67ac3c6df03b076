"""How well L proxy points estimate the Gram matrix: relative error against a dense reference (paper eq. 5).

Sigma is a mean over the frustum of J(p)^T J(p), so a point set is an integration rule for it. What makes 10% of
the samples enough is integration accuracy (docs/DESIGN-NOTES.md sec. 2): a low-discrepancy rule integrates a smooth
integrand with error close to O(1/L) where random points give O(1/sqrt(L)). The reference uses at least 2^20
scrambled Sobol points mapped through the same transform and is evaluated in chunks to bound memory.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, ParameterLayout, tangent_bounds
from s2camp_ns.core.camp_sampling import camp_frustum_points
from s2camp_ns.core.frustum import sample_frustum
from s2camp_ns.core.jacobian import projection_jacobian, relative_gram_error
from s2camp_ns.core.lattice import unit_cube_points
from s2camp_ns.core.preconditioner import SamplingConfig, gram_from_points, sample_proxy_points
from s2camp_ns.core.validation import check_range

REFERENCE_POINTS = 2**20


def reference_gram(
    intrinsics: Intrinsics, sampling: SamplingConfig, layout: ParameterLayout | None = None,
    num_points: int = REFERENCE_POINTS, seed: int = 12345, chunk: int = 2**16,
) -> Float[Tensor, "n k k"]:
    """Sigma from ``num_points`` (at least 10^6) points of the distribution ``sampling`` describes, in chunks of
    ``chunk``: volume-uniform samplers (lattice, Sobol, random) share one reference, scrambled Sobol points through
    ``sampling.transform``; CamP's random sampler, of another density, gets ``num_points`` of its own random draws."""
    check_range("num_points", num_points, low=10**6)
    sampling.validate()
    intrinsics = intrinsics.detach().to(dtype=torch.float64)
    bounds = tangent_bounds(intrinsics)
    if sampling.sampler == "camp-random":
        generator = torch.Generator().manual_seed(seed)
        draw = None
    else:
        draw = unit_cube_points("sobol", num_points, seed=seed)
    t_near, t_far = sampling.fixed_range()  # the reference is for one range: the sampling's own (no scene here)
    total = None
    valid = torch.zeros(intrinsics.num_cameras, dtype=torch.float64, device=bounds.device)
    for start in range(0, num_points, chunk):
        size = min(chunk, num_points - start)
        if draw is None:
            points = camp_frustum_points(intrinsics, size, t_near, t_far, sampling.ladder_p, generator=generator)
        else:
            unit = draw[start : start + size].to(bounds.device)
            points = sample_frustum(unit, bounds, t_near, t_far, sampling.transform, sampling.radial).camera
        _, jacobian, mask = projection_jacobian(points, intrinsics, layout)
        jacobian = jacobian / intrinsics.image_scale()[:, None, None, None]
        jacobian = jacobian * mask[..., None, None].to(jacobian.dtype)
        partial = torch.einsum("nlik,nlij->nkj", jacobian, jacobian)
        total = partial if total is None else total + partial
        valid += mask.sum(dim=-1)
    sigma = total / valid.clamp(min=1)[:, None, None]
    return 0.5 * (sigma + sigma.transpose(-1, -2))


def gram_estimation_error(
    intrinsics: Intrinsics, sampling: SamplingConfig, reference: Float[Tensor, "n k k"],
    layout: ParameterLayout | None = None, seeds: tuple[int, ...] = (0,),
) -> Float[Tensor, "s n"]:
    """Relative Frobenius error ||Sigma_L - Sigma_ref||_F / ||Sigma_ref||_F for each seed and camera."""
    errors = []
    for seed in seeds:
        config = replace(sampling, seed=seed)
        sigma, _ = gram_from_points(sample_proxy_points(intrinsics, config), intrinsics, layout)
        errors.append(relative_gram_error(sigma, reference))
    return torch.stack(errors)
