"""Contraction (paper eq. 10) and the unit-cube -> frustum inverse transforms (paper eqs. 6-14)."""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_ns.core.contraction import contract, contract_radius, uncontract, uncontract_radius
from s2camp_ns.core.frustum import frustum_to_unit, sample_frustum

ROOM = torch.tensor([[-389.25 / 793.13, 388.75 / 793.13, -259.375 / 793.49, 258.625 / 793.49]], dtype=torch.float64)
OFF_CENTRE = torch.tensor([[-0.3, 0.9, 0.1, 0.6]], dtype=torch.float64)  # principal point far off centre
WIDE = torch.tensor([[-1.0, 1.0, -2.0 / 3.0, 2.0 / 3.0]], dtype=torch.float64)
BOUNDS = torch.cat([ROOM, OFF_CENTRE, WIDE])


def uniform_cube(n: int, seed: int = 0) -> torch.Tensor:
    return torch.rand((n, 3), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_contraction_round_trip() -> None:
    x = torch.randn(1000, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 5
    y = contract(x)
    assert float(y.norm(dim=-1).max()) < 2.0
    assert torch.allclose(uncontract(y), x, rtol=1e-12, atol=1e-12)
    inner = x[x.norm(dim=-1) <= 1.0]
    assert torch.equal(contract(inner), inner)
    r = torch.linspace(0.0, 50.0, 501, dtype=torch.float64)
    assert torch.allclose(uncontract_radius(contract_radius(r)), r, rtol=1e-12)
    t = torch.tensor([0.0, 0.5, 1.0, 1.5, 1.9, 1.99], dtype=torch.float64)
    expected = torch.tensor([0.0, 0.5, 1.0, 2.0, 10.0, 100.0], dtype=torch.float64)
    assert torch.allclose(uncontract_radius(t), expected, rtol=1e-12)


def test_contraction_errors() -> None:
    with pytest.raises(ValueError, match="t must lie in"):
        uncontract_radius(torch.tensor([2.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="contracted radius"):
        uncontract(torch.tensor([[0.0, 0.0, 2.5]], dtype=torch.float64))
    with pytest.raises(ValueError, match="points"):
        contract(torch.tensor([[math.nan, 0.0, 1.0]], dtype=torch.float64))


@pytest.mark.parametrize(
    ("transform", "radial"), [("pyramid", "volume"), ("spherical", "volume"), ("pixel", "ray"), ("pyramid", "ray")]
)
def test_round_trip_and_radius(transform: str, radial: str) -> None:
    u = uniform_cube(5000)
    samples = sample_frustum(u, BOUNDS, 0.1, 1.99, transform, radial)
    assert samples.contracted.shape == (3, 5000, 3) and samples.camera.shape == (3, 5000, 3)
    radius = samples.contracted.norm(dim=-1)
    assert float(radius.min()) >= 0.1 - 1e-12 and float(radius.max()) <= 1.99 + 1e-12
    assert torch.allclose(
        frustum_to_unit(samples.contracted, BOUNDS, 0.1, 1.99, transform, radial), u.expand(3, -1, -1), atol=1e-12
    )
    # Euclidean points: same direction, radius through the inverse contraction.
    assert torch.allclose(samples.camera.norm(dim=-1), uncontract_radius(radius), rtol=1e-12)
    assert torch.allclose(
        torch.nn.functional.normalize(samples.camera, dim=-1),
        torch.nn.functional.normalize(samples.contracted, dim=-1),
        atol=1e-12,
    )


def test_inverse_of_forward_cdf() -> None:
    # Q(F(x)) = x for points inside the pyramid (paper eq. 7).
    x = torch.rand((20000, 3), generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 4 - 2
    a, b = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
    box = OFF_CENTRE[0]
    inside = (x[:, 2] > 0) & (x.norm(dim=-1) < 1.99) & (a > box[0]) & (a < box[1]) & (b > box[2]) & (b < box[3])
    pts = x[inside][None]
    u = frustum_to_unit(pts, OFF_CENTRE, 0.0, 1.99, "pyramid")
    assert bool(((u >= 0) & (u <= 1)).all())
    assert torch.allclose(sample_frustum(u, OFF_CENTRE, 0.0, 1.99, "pyramid").contracted, pts, atol=1e-12)


def _rejection_uniform(box: torch.Tensor, n: int, transform: str) -> torch.Tensor:
    x = torch.rand((n, 3), generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 4 - 2
    x[:, 2] = x[:, 2].abs()
    r = x.norm(dim=-1)
    if transform == "pyramid":
        a, b = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
        ok = (a > box[0]) & (a < box[1]) & (b > box[2]) & (b < box[3])
    else:
        az, el = torch.atan2(x[:, 0], x[:, 2]), torch.asin(x[:, 1] / r)
        ok = (az > math.atan(box[0])) & (az < math.atan(box[1])) & (el > math.atan(box[2])) & (el < math.atan(box[3]))
    return x[ok & (r < 1.99)]


@pytest.mark.parametrize("transform", ["pyramid", "spherical"])
@pytest.mark.parametrize("camera", [0, 1])
def test_uniform_in_volume(transform: str, camera: int) -> None:
    # Transformed uniform points and rejection-sampled uniform points have the same marginals (two-sample KS).
    box = BOUNDS[camera]
    reference = _rejection_uniform(box, 600_000, transform)
    samples = sample_frustum(uniform_cube(len(reference), seed=9), box[None], 0.0, 1.99, transform).contracted[0]
    for ref, got in [(reference[:, i], samples[:, i]) for i in range(3)] + [
        (reference.norm(dim=-1), samples.norm(dim=-1))
    ]:
        grid = torch.cat([ref, got]).sort().values
        cdf_ref = torch.searchsorted(ref.sort().values, grid, right=True) / len(ref)
        cdf_got = torch.searchsorted(got.sort().values, grid, right=True) / len(got)
        n_eff = len(ref) / 2
        assert float((cdf_ref - cdf_got).abs().max()) < 2.0 / math.sqrt(n_eff)  # ~ KS at alpha 1e-3


def test_pyramid_inside_box_spherical_not() -> None:
    u = uniform_cube(20000)
    for transform, expect_all in [("pyramid", True), ("spherical", False)]:
        p = sample_frustum(u, BOUNDS, 0.0, 1.99, transform).contracted
        a, b = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
        inside = (a >= BOUNDS[:, 0:1]) & (a <= BOUNDS[:, 1:2]) & (b >= BOUNDS[:, 2:3]) & (b <= BOUNDS[:, 3:4])
        assert bool(inside.all()) == expect_all
    # The far corners of the cube (u2 -> b, u3 -> a) stay inside for the pyramid, exactly.
    corners = torch.tensor([[1, i, j] for i in (0, 1) for j in (0, 1)], dtype=torch.float64)
    p = sample_frustum(corners, BOUNDS, 0.0, 1.99, "pyramid").contracted
    assert torch.allclose(p[..., 0] / p[..., 2], BOUNDS[:, [0, 1, 0, 1]], atol=1e-14)
    assert torch.allclose(p[..., 1] / p[..., 2], BOUNDS[:, [2, 2, 3, 3]], atol=1e-14)


def test_ray_radial_map_is_uniform_in_contracted_distance() -> None:
    u = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    points = torch.stack([u, torch.full_like(u, 0.5), torch.full_like(u, 0.5)], dim=-1)
    radius = sample_frustum(points, ROOM, 0.4, 1.9, "pyramid", "ray").contracted.norm(dim=-1)[0]
    torch.testing.assert_close(radius, 0.4 + 1.5 * u, atol=1e-14, rtol=0)
    volume = sample_frustum(points, ROOM, 0.4, 1.9, "pyramid", "volume").contracted.norm(dim=-1)[0]
    assert float(volume[5]) > float(radius[5]) + 0.2  # the paper's map puts the median far out (cube root)


def test_frustum_errors_name_the_parameter() -> None:
    u = uniform_cube(10)
    with pytest.raises(ValueError, match="t_near"):
        sample_frustum(u, ROOM, -0.1, 1.5)
    with pytest.raises(ValueError, match="t_far"):
        sample_frustum(u, ROOM, 0.0, 2.0)
    with pytest.raises(ValueError, match="t_near"):
        sample_frustum(u, ROOM, 1.5, 1.5)
    with pytest.raises(ValueError, match="a_max - a_min"):
        sample_frustum(u, torch.tensor([[0.5, -0.5, -0.3, 0.3]], dtype=torch.float64), 0.0, 1.5)
    with pytest.raises(ValueError, match="b_max - b_min"):
        sample_frustum(u, torch.tensor([[-0.5, 0.5, 0.3, 0.3]], dtype=torch.float64), 0.0, 1.5)
    with pytest.raises(ValueError, match="tangent_bounds"):
        sample_frustum(u, torch.tensor([[-math.inf, 0.5, -0.3, 0.3]], dtype=torch.float64), 0.0, 1.5)
    with pytest.raises(ValueError, match="tangent_bounds"):
        sample_frustum(u, torch.zeros(4, dtype=torch.float64), 0.0, 1.5)
    with pytest.raises(ValueError, match="unit_points"):
        sample_frustum(u + 1.0, ROOM, 0.0, 1.5)
    with pytest.raises(ValueError, match="transform"):
        sample_frustum(u, ROOM, 0.0, 1.5, "cone")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="radial"):
        sample_frustum(u, ROOM, 0.0, 1.5, "pyramid", "log")  # type: ignore[arg-type]
