"""Contraction (paper eq. 10) and the unit-cube -> frustum inverse transforms (paper eqs. 6-14)."""

from __future__ import annotations

import math
import re

import pytest
import torch
from frustum_cdf import contract, frustum_to_unit, uncontract

from s2camp_ns.core.contraction import contract_radius, uncontract_radius
from s2camp_ns.core.frustum import radius_per_camera, sample_frustum

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


# ----------------------------------------------------------------------------------------------------------------
# Tests added from the mutation-testing run (docs/mutation-testing.md).


def test_contraction_closed_form_on_any_batch_shape() -> None:
    # |(3, 4, 0)| = 5 contracts to radius 2 - 1/5 = 1.8: (1.08, 1.44, 0); |(0, 0.6, 0.8)| = 1 stays.
    far = torch.tensor([3.0, 4.0, 0.0], dtype=torch.float64)
    near = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    far_contracted = torch.tensor([1.08, 1.44, 0.0], dtype=torch.float64)
    torch.testing.assert_close(contract(far), far_contracted, atol=1e-15, rtol=0)
    batch = torch.stack([torch.stack([far, near]), torch.stack([near, 2.0 * far])])  # [2, 2, 3]
    # |(6, 8, 0)| = 10 contracts to 1.9: (1.14, 1.52, 0).
    expected = torch.stack(
        [torch.stack([far_contracted, near]), torch.stack([near, torch.tensor([1.14, 1.52, 0.0], dtype=torch.float64)])]
    )
    torch.testing.assert_close(contract(batch), expected, atol=1e-15, rtol=0)
    torch.testing.assert_close(uncontract(expected), batch, atol=1e-14, rtol=0)
    torch.testing.assert_close(uncontract(expected[0]), batch[0], atol=1e-14, rtol=0)


def test_contraction_errors_name_the_parameter() -> None:
    with pytest.raises(ValueError, match=r"^radius must lie in \[0, inf\), got -0.5"):
        contract_radius(torch.tensor([0.5, -0.5], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"^t must lie in \[0, 2\), got -0.5"):
        uncontract_radius(torch.tensor([-0.5], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"^t must lie in \[0, 2\), got 2"):
        uncontract_radius(torch.tensor([1.0, 2.0], dtype=torch.float64))  # radius exactly 2: infinitely far
    with pytest.raises(ValueError, match="^points must be finite"):
        contract(torch.tensor([[0.0, math.inf, 1.0]], dtype=torch.float64))


def test_default_maps_invert_each_other() -> None:
    """frustum_to_unit and sample_frustum default to the same maps (pyramid, volume)."""
    u = uniform_cube(200, seed=3)
    samples = sample_frustum(u, BOUNDS, 0.2, 1.8)
    torch.testing.assert_close(frustum_to_unit(samples.contracted, BOUNDS, 0.2, 1.8), u.expand(3, -1, -1))


def test_float32_inputs_are_computed_in_float64() -> None:
    u32 = uniform_cube(100, seed=6).float()
    samples = sample_frustum(u32, ROOM.float(), 0.2, 1.8)
    reference = sample_frustum(u32.double(), ROOM.float().double(), 0.2, 1.8)
    assert samples.contracted.dtype == torch.float64 and samples.camera.dtype == torch.float64
    torch.testing.assert_close(samples.contracted, reference.contracted, atol=1e-15, rtol=0)
    back = frustum_to_unit(samples.contracted.float(), ROOM, 0.2, 1.8)
    torch.testing.assert_close(
        back, frustum_to_unit(samples.contracted.float().double(), ROOM, 0.2, 1.8), atol=1e-15, rtol=0
    )


def test_portrait_and_small_frusta_are_valid() -> None:
    # A portrait box (b range wider than the a range, b_min < a_min) and a far radius below 1.
    portrait = torch.tensor([[-0.3, 0.3, -0.5, 0.5]], dtype=torch.float64)
    corners = torch.tensor([[1.0, i, j] for i in (0.0, 1.0) for j in (0.0, 1.0)], dtype=torch.float64)
    p = sample_frustum(corners, portrait, 0.1, 0.5).contracted[0]
    torch.testing.assert_close(p.norm(dim=-1), torch.full((4,), 0.5, dtype=torch.float64))
    torch.testing.assert_close(p[:, 0] / p[:, 2], torch.tensor([-0.3, 0.3, -0.3, 0.3], dtype=torch.float64))
    torch.testing.assert_close(p[:, 1] / p[:, 2], torch.tensor([-0.5, -0.5, 0.5, 0.5], dtype=torch.float64))


def test_nearly_hemispherical_frusta_give_finite_samples_inside_the_box() -> None:
    """Tangent bounds up to 1e8 (fields of view just below 180 degrees): rounding must not produce NaN."""
    box = torch.tensor([[-1e6, 1e6, -1e8, 1e8], [-1e8, 1e8, -1e6, 1e6]], dtype=torch.float64)
    u = uniform_cube(2000, seed=8)
    u[:4, 1:] = torch.tensor([[i, j] for i in (0.0, 1.0) for j in (0.0, 1.0)], dtype=torch.float64)
    p = sample_frustum(u, box, 0.1, 1.9, "pyramid").contracted
    assert bool(torch.isfinite(p).all()) and bool((p[..., 2] >= 0).all())


def test_unit_points_are_checked() -> None:
    with pytest.raises(ValueError, match=re.escape("unit_points must have shape [L, 3] or [N, L, 3], got (10, 4)")):
        sample_frustum(torch.zeros(10, 4, dtype=torch.float64), ROOM, 0.0, 1.5)
    with pytest.raises(
        ValueError, match=re.escape("unit_points must have shape [L, 3] or [N, L, 3], got (1, 1, 5, 3)")
    ):
        sample_frustum(torch.zeros(1, 1, 5, 3, dtype=torch.float64), ROOM, 0.0, 1.5)
    with pytest.raises(ValueError, match=re.escape("unit_points must have shape [L, 3] or [N, L, 3], got list")):
        sample_frustum([[0.5, 0.5, 0.5]], ROOM, 0.0, 1.5)  # type: ignore[arg-type]
    message = "unit_points must have N = 3 cameras to match tangent_bounds, got 2"
    with pytest.raises(ValueError, match=re.escape(message)):
        sample_frustum(torch.zeros(2, 5, 3, dtype=torch.float64), BOUNDS, 0.0, 1.5)
    with pytest.raises(ValueError, match=r"^unit_points must lie in \[0, 1\]"):
        sample_frustum(uniform_cube(10) - 1.0, ROOM, 0.0, 1.5)


def test_frustum_errors_state_parameter_and_range() -> None:
    u = uniform_cube(10)
    with pytest.raises(ValueError, match=r"^t_far must lie in \(0, 2\), got 0.0"):
        sample_frustum(u, ROOM, 0.0, 0.0)
    with pytest.raises(ValueError, match=r"^t_far must lie in \(0, 2\), got 2.0"):
        sample_frustum(u, ROOM, 0.0, 2.0)
    with pytest.raises(ValueError, match=r"^t_near must lie in \[0, 1.5\), got 1.5"):
        sample_frustum(u, ROOM, 1.5, 1.5)
    with pytest.raises(ValueError, match="^transform must be one of"):
        sample_frustum(u, ROOM, 0.0, 1.5, "cone")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="^radial must be one of"):
        sample_frustum(u, ROOM, 0.0, 1.5, "pyramid", "log")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="^tangent_bounds must be finite"):
        sample_frustum(u, torch.tensor([[-math.inf, 0.5, -0.3, 0.3]], dtype=torch.float64), 0.0, 1.5)
    with pytest.raises(ValueError, match=r"^tangent_bounds a_max - a_min must lie in \(0, inf\), got 0"):
        sample_frustum(u, torch.tensor([[0.5, 0.5, -0.3, 0.3]], dtype=torch.float64), 0.0, 1.5)
    with pytest.raises(ValueError, match=r"^tangent_bounds b_max - b_min must lie in \(0, inf\), got 0"):
        sample_frustum(u, torch.tensor([[-0.5, 0.5, 0.3, 0.3]], dtype=torch.float64), 0.0, 1.5)
    prefix = "tangent_bounds must have shape [N, 4] (a_min, a_max, b_min, b_max), got "
    with pytest.raises(ValueError, match=re.escape(prefix + "(4,)")):
        sample_frustum(u, torch.zeros(4, dtype=torch.float64), 0.0, 1.5)
    with pytest.raises(ValueError, match=re.escape(prefix + "list")):
        sample_frustum(u, [[-0.5, 0.5, -0.3, 0.3]], 0.0, 1.5)  # type: ignore[arg-type]


@pytest.mark.parametrize("radial", ["ray", "volume"])
def test_radius_per_camera_maps_each_cameras_own_range(radial: str) -> None:
    """Q_r(u1) on each camera's [t_near, t_far] (paper eq. 12; "ray": uniform in contracted distance)."""
    u1 = torch.tensor([0.0, 0.25, 0.5, 1.0], dtype=torch.float64)
    near = torch.tensor([0.2, 0.5, 0.2])
    far = torch.tensor([1.0, 1.9, 1.0])
    radius = radius_per_camera(u1, near, far, radial)
    n, f = near.double()[:, None], far.double()[:, None]
    expected = n + u1 * (f - n) if radial == "ray" else (n**3 + u1 * (f**3 - n**3)) ** (1.0 / 3.0)
    assert radius.dtype == torch.float64
    torch.testing.assert_close(radius, expected, atol=1e-15, rtol=0)


@pytest.mark.parametrize("per_camera_points", [False, True], ids=["shared-points", "per-camera-points"])
@pytest.mark.parametrize("radial", ["volume", "ray"])
def test_per_camera_ranges_set_only_each_cameras_radii(per_camera_points: bool, radial: str) -> None:
    """Tensor ranges [N]: camera n's contracted radii are Q_r(u1) on its own [t_near, t_far] (paper eq. 12), its
    directions those of any range (the range moves points along their rays only); a float end is shared by all."""
    u = uniform_cube(50, seed=8)
    if per_camera_points:
        u = torch.stack([u, uniform_cube(50, seed=9), uniform_cube(50, seed=10)])
    near = torch.tensor([0.2, 0.5, 0.0], dtype=torch.float64)
    far = torch.tensor([1.0, 1.9, 1.5], dtype=torch.float64)
    u1 = u[..., 0].expand(3, -1)
    for t_near, t_far in ((near, far), (0.2, far), (near, 1.9)):
        n = torch.as_tensor(t_near, dtype=torch.float64).expand(3)[:, None]
        f = torch.as_tensor(t_far, dtype=torch.float64).expand(3)[:, None]
        contracted = sample_frustum(u, BOUNDS, t_near, t_far, "pyramid", radial).contracted
        expected = n + u1 * (f - n) if radial == "ray" else (n**3 + u1 * (f**3 - n**3)) ** (1.0 / 3.0)
        radius = contracted.norm(dim=-1)
        torch.testing.assert_close(radius, expected, atol=1e-12, rtol=0)
        reference = sample_frustum(u, BOUNDS, 0.3, 1.2, "pyramid", radial).contracted
        directions = contracted / radius[..., None].clamp_min(1e-300)
        moved = radius > 0  # t_near = 0 with u1 = 0 sits on the camera centre
        expected_directions = (reference / reference.norm(dim=-1, keepdim=True))[moved]
        torch.testing.assert_close(directions[moved], expected_directions, atol=1e-12, rtol=0)


def _f64(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


@pytest.mark.parametrize(
    ("t_near", "t_far", "message"),
    [
        (_f64(0.2, -0.1, 0.2), 1.5, "t_near must lie in [0, inf), got -0.1 (element 1)"),
        (0.4, _f64(1.5, 0.4, 1.5), "t_far - t_near must lie in (0, inf), got 0 (element 1)"),
        (_f64(0.2, 1.9, 0.2), 1.9, "t_far - t_near must lie in (0, inf), got 0 (element 1)"),
        (0.2, _f64(1.5, 2.0, 1.5), "t_far must lie in (0, 2), got 2 (element 1)"),
        (_f64(0.2, 0.3), 1.5, "t_near must be a float or hold one value per camera (N = 3), got shape (2,)"),
        (0.2, _f64(1.5, 1.6, 1.7, 1.8), "t_far must be a float or hold one value per camera (N = 3), got shape (4,)"),
        (
            _f64(0.2, 0.3, 0.25)[None],
            1.5,
            "t_near must be a float or hold one value per camera (N = 3), got shape (1, 3)",
        ),
    ],
)
def test_bad_per_camera_ranges_are_named_in_full(t_near, t_far, message: str) -> None:
    with pytest.raises(ValueError) as error:
        sample_frustum(uniform_cube(10), BOUNDS, t_near, t_far)
    assert str(error.value) == message


def test_validate_frustum_defaults_to_the_pyramid_and_volume_maps() -> None:
    from s2camp_ns.core.frustum import validate_frustum

    bounds = validate_frustum(BOUNDS.float(), 0.2, 1.5)
    assert bounds.dtype == torch.float64 and torch.equal(bounds, BOUNDS.float().double())
