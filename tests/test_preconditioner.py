"""Preconditioner P = (Sigma + damping)^(1/2) (paper eqs. 15-20): whitening, symmetry, damping, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from joint_latents import reexpress_adam_state

from s2camp_ns.core.camera import Intrinsics, ParameterLayout, in_image, project, project_with_delta
from s2camp_ns.core.lattice import unit_cube_points
from s2camp_ns.core.preconditioner import (
    DampingConfig,
    Preconditioner,
    SamplingConfig,
    compute_preconditioner,
    condition_number,
    damped_gram,
    gram_from_points,
    sample_proxy_points,
    symmetric_sqrt_and_inverse,
    whitening_error,
)

ROOM = Intrinsics.create(fx=793.13, fy=793.49, cx=389.25, cy=259.375, width=778, height=518)
DISTORTED = Intrinsics.create(fx=410.0, fy=405.0, cx=330.0, cy=210.0, width=640, height=420, k1=-0.03, k2=0.004)


def _spd(n: int, k: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 3 * k, k, generator=generator, dtype=torch.float64)
    return a.transpose(1, 2) @ a / (3 * k) + 0.05 * torch.eye(k, dtype=torch.float64)


def test_symmetric_sqrt_whitens_exactly_without_damping() -> None:
    sigma = _spd(4, 12, seed=0)
    root, inverse = symmetric_sqrt_and_inverse(sigma)
    eye = torch.eye(12, dtype=torch.float64).expand(4, 12, 12)
    torch.testing.assert_close(inverse.transpose(1, 2) @ sigma @ inverse, eye, atol=1e-8, rtol=0)  # eq. 16
    torch.testing.assert_close(root.transpose(1, 2) @ root, sigma, atol=1e-10, rtol=1e-10)  # eq. 17
    torch.testing.assert_close(root, root.transpose(1, 2))
    assert (torch.linalg.eigvalsh(root) > 0).all()
    torch.testing.assert_close(root @ inverse, eye, atol=1e-10, rtol=0)


def test_whitening_of_a_real_frustum_gram_is_exact_without_damping() -> None:
    points = sample_proxy_points(ROOM, SamplingConfig(num_points=500, t_near=0.4))
    sigma, count = gram_from_points(points, ROOM, ParameterLayout.from_preset("pose+focal"))
    assert count.item() == 500  # the pyramid transform puts every proxy point inside the image
    _, inverse = symmetric_sqrt_and_inverse(sigma)
    assert whitening_error(inverse, sigma).item() < 1e-6


def test_whitened_jacobian_is_orthonormal() -> None:
    """J P^-1 has orthonormal columns in the mean over points (eqs. 15-16) for an undamped P."""
    layout = ParameterLayout.from_preset("pose+focal")
    points = sample_proxy_points(ROOM, SamplingConfig(num_points=200))
    sigma, count = gram_from_points(points, ROOM, layout)
    _, inverse = symmetric_sqrt_and_inverse(sigma)
    delta = torch.zeros(1, layout.num_params, dtype=torch.float64)

    def whitened_projection(phi_hat: torch.Tensor) -> torch.Tensor:
        return project_with_delta(points, ROOM, layout.expand(phi_hat @ inverse[0].T)) / 778.0

    jacobian = torch.func.jacrev(whitened_projection)(delta)[0].reshape(-1, layout.num_params)
    torch.testing.assert_close(
        jacobian.T @ jacobian / count.item(), torch.eye(7, dtype=torch.float64), atol=1e-6, rtol=0
    )


def test_damping_keeps_unobservable_parameters_finite() -> None:
    sigma = torch.zeros(1, 12, 12, dtype=torch.float64)
    sigma[0, :6, :6] = _spd(1, 6, seed=1)[0]
    damped = damped_gram(sigma, DampingConfig(damping_abs=1e-6, damping_rel=0.1))
    root, inverse = symmetric_sqrt_and_inverse(damped)
    assert torch.isfinite(root).all() and torch.isfinite(inverse).all()
    torch.testing.assert_close(torch.diagonal(root[0])[6:], torch.full((6,), 1e-3, dtype=torch.float64))
    with pytest.raises(ValueError, match="eigenvalues of sigma"):
        symmetric_sqrt_and_inverse(sigma)


def test_diagonal_only_mode() -> None:
    sigma = _spd(2, 5, seed=2)
    root, inverse = symmetric_sqrt_and_inverse(sigma, diagonal_only=True)
    torch.testing.assert_close(root, torch.diag_embed(torch.diagonal(sigma, dim1=1, dim2=2).sqrt()))
    torch.testing.assert_close(root @ inverse, torch.eye(5, dtype=torch.float64).expand(2, 5, 5))


@pytest.mark.parametrize("intrinsics", [ROOM, DISTORTED], ids=["room", "distorted"])
def test_compute_preconditioner_is_spd_finite_and_bit_identical(intrinsics: Intrinsics) -> None:
    first = compute_preconditioner(intrinsics)
    second = compute_preconditioner(intrinsics)
    assert torch.equal(first.matrix, second.matrix) and torch.equal(first.inverse, second.inverse)
    assert first.matrix.dtype == torch.float64 and first.matrix.shape == (1, 12, 12)
    torch.testing.assert_close(first.matrix, first.matrix.transpose(1, 2))
    assert (torch.linalg.eigvalsh(first.matrix) > 0).all()
    torch.testing.assert_close(
        first.matrix @ first.inverse, torch.eye(12, dtype=torch.float64)[None], atol=1e-8, rtol=0
    )
    # Damping bounds the whitened spectrum: P^-1 Sigma P^-1 has eigenvalues in (0, 1].
    whitened = first.inverse @ first.gram @ first.inverse
    eigenvalues = torch.linalg.eigvalsh(whitened)
    assert eigenvalues.max() <= 1 + 1e-9 and eigenvalues.min() > 0
    assert condition_number(whitened).item() < condition_number(first.gram).item()


def test_random_samplers_are_seeded() -> None:
    config = SamplingConfig(sampler="camp-random", num_points=300, seed=7)
    torch.testing.assert_close(sample_proxy_points(ROOM, config), sample_proxy_points(ROOM, config))
    other = sample_proxy_points(ROOM, SamplingConfig(sampler="camp-random", num_points=300, seed=8))
    assert not torch.equal(sample_proxy_points(ROOM, config), other)


def test_batched_equals_per_camera() -> None:
    both = Intrinsics.create(
        fx=[793.13, 410.0],
        fy=[793.49, 405.0],
        cx=[389.25, 330.0],
        cy=[259.375, 210.0],
        width=[778, 640],
        height=[518, 420],
        k1=[0.0, -0.03],
        k2=[0.0, 0.004],
    )
    batched = compute_preconditioner(both)
    for i, single in enumerate([ROOM, DISTORTED]):
        torch.testing.assert_close(batched.matrix[i], compute_preconditioner(single).matrix[0], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    ("config", "name"),
    [
        (SamplingConfig(num_points=0), "num_points"),
        (SamplingConfig(t_near=-0.1), "t_near"),
        (SamplingConfig(t_near=1.0, t_far=0.5), "t_far"),
        (SamplingConfig(t_far=2.0), "t_far"),
        (SamplingConfig(sampler="magic"), "sampler"),  # type: ignore[arg-type]
        (SamplingConfig(radial="log"), "radial"),  # type: ignore[arg-type]
    ],
)
def test_bad_sampling_config_names_the_parameter(config: SamplingConfig, name: str) -> None:
    with pytest.raises(ValueError, match=rf"^{name} must"):
        compute_preconditioner(ROOM, sampling=config)


def test_bad_damping_names_the_parameter() -> None:
    with pytest.raises(ValueError, match="^damping_abs must"):
        compute_preconditioner(ROOM, damping=DampingConfig(damping_abs=0.0))
    with pytest.raises(ValueError, match="^damping_rel must"):
        compute_preconditioner(ROOM, damping=DampingConfig(damping_rel=-1.0))


def _adam_on_linear_losses(precond: torch.Tensor, directions: list[torch.Tensor]) -> tuple[torch.Tensor, dict]:
    """torch's Adam on the latent x = P phi, fed the gradients (by autograd) of the losses <a_t, phi>."""
    x = torch.zeros(1, 12, dtype=torch.float64, requires_grad=True)
    adam = torch.optim.Adam([x], lr=1e-3)
    p_inv = torch.linalg.inv(precond)
    for direction in directions:
        adam.zero_grad()
        ((p_inv @ x[..., None])[..., 0] * direction).sum().backward()
        adam.step()
    return x.detach(), adam.state[x]


@pytest.mark.parametrize("dense", [False, True], ids=["single-component-gradients", "dense-gradients"])
def test_reexpress_latent_keeps_the_camera_and_maps_adam_moments(dense: bool) -> None:
    """Re-expressed in P_new, the latent gives the same camera and Adam's state is that of an Adam that ran in the
    P_new basis from the start: m exactly; v exactly when every past gradient had one nonzero component (the
    documented assumption), within 1% for these dense gradients (measured: 0.1%; v left unmapped: 5%)."""
    from joint_latents import reexpress_latent

    old = compute_preconditioner(ROOM)
    changed = Intrinsics.create(fx=820.0, fy=820.0, cx=380.0, cy=262.0, width=778, height=518, k1=-0.02)
    new = compute_preconditioner(changed)
    generator = torch.Generator().manual_seed(3)
    if dense:
        directions = [torch.randn(1, 12, dtype=torch.float64, generator=generator) for _ in range(4)]
    else:  # a = P_old e_k: the gradient w.r.t. the old latent is e_k
        directions = [old.matrix[:, :, k] for k in (0, 6, 9, 3)]
    latent, state = _adam_on_linear_losses(old.matrix, directions)
    state = {key: value.clone() for key, value in state.items()}
    phi_before = (old.inverse @ latent[..., None])[..., 0]
    reexpress_latent(latent, old, new, state)
    torch.testing.assert_close((new.inverse @ latent[..., None])[..., 0], phi_before, rtol=1e-10, atol=1e-12)
    _, expected = _adam_on_linear_losses(new.matrix, directions)
    assert int(state["step"]) == int(expected["step"]) == 4
    torch.testing.assert_close(state["exp_avg"], expected["exp_avg"], rtol=1e-9, atol=1e-15)
    v_error = float((state["exp_avg_sq"] - expected["exp_avg_sq"]).norm() / expected["exp_avg_sq"].norm())
    assert v_error < (0.01 if dense else 1e-9)


FISHEYE = Intrinsics.create(
    fx=[170.0, 300.0],
    fy=[171.0, 298.0],
    cx=[320.0, 310.0],
    cy=[240.0, 245.0],
    width=[640, 640],
    height=[480, 480],
    k1=[0.03, -0.01],
    k2=[-0.002, 0.004],
    k3=[0.0005, 0.0],
    k4=[0.00005, 0.0],
    model="fisheye",
)


@pytest.mark.parametrize("sampler", ["frolov", "camp-random"])
def test_fisheye_proxy_points_fill_the_image_past_90_degrees(sampler: str) -> None:
    sampling = SamplingConfig(num_points=400, sampler=sampler)
    points = sample_proxy_points(FISHEYE, sampling)
    pixels, margin = project(points, FISHEYE)
    assert (margin > 0).all()
    assert in_image(pixels, margin, FISHEYE).all()
    assert (points[0, :, 2] < 0).any(), "the wide fisheye's samples must reach past 90 degrees"
    # The unit square maps onto the whole image: every quarter of it holds samples.
    u = (pixels[..., 0] / FISHEYE.width[:, None] > 0.5).to(torch.int64)
    v = (pixels[..., 1] / FISHEYE.height[:, None] > 0.5).to(torch.int64)
    counts = torch.stack([((2 * v + u) == q).sum(dim=-1) for q in range(4)], dim=-1)
    assert (counts > 0.15 * 400).all()
    radius = points.norm(dim=-1)
    assert radius.min() >= 0.4 - 1e-12 and radius.max() <= 1.0 / (2.0 - 1.5) + 1e-12


def test_fisheye_preconditioner_whitens_its_fourteen_parameters() -> None:
    layout = ParameterLayout.from_preset("all", "OPENCV_FISHEYE")
    result = compute_preconditioner(FISHEYE, layout)
    assert result.matrix.shape == (2, 14, 14) and (result.num_valid == 500).all()
    _, inverse = symmetric_sqrt_and_inverse(result.gram)
    assert whitening_error(inverse, result.gram).max() < 1e-6
    assert (torch.diagonal(result.gram, dim1=-2, dim2=-1)[:, 10:] > 0).all()  # k1..k4 are observed


def test_tangential_preconditioner_observes_p1_p2() -> None:
    camera = Intrinsics.create(
        fx=410.0, fy=405.0, cx=330.0, cy=210.0, width=640, height=420, k1=-0.03, k2=0.004, p1=0.001, p2=-0.002
    )
    layout = ParameterLayout.from_preset("all", "OPENCV")
    result = compute_preconditioner(camera, layout)
    assert layout.names[-2:] == ("p1", "p2") and result.matrix.shape == (1, 14, 14)
    assert (result.num_valid == 500).all()
    assert (torch.diagonal(result.gram, dim1=-2, dim2=-1)[0, 12:] > 0).all()
    _, inverse = symmetric_sqrt_and_inverse(result.gram)
    assert whitening_error(inverse, result.gram).item() < 1e-6


# ----------------------------------------------------------------------------------------------------------------
# Tests added from the mutation-testing run (docs/mutation-testing.md).


def _rotation(k: int, seed: int) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(k, k, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    return q


def test_condition_number_closed_form() -> None:
    assert condition_number(torch.diag(torch.tensor([1.0, 2.0, 4.0], dtype=torch.float64))[None]).tolist() == [4.0]
    q = _rotation(3, seed=0)
    sigma32 = (q @ torch.diag(torch.tensor([1.0, 10.0, 1e4], dtype=torch.float64)) @ q.T).float()[None]
    eigenvalues = np.linalg.eigvalsh(sigma32[0].double().numpy())  # of the float32 matrix, in float64
    np.testing.assert_allclose(condition_number(sigma32).numpy(), [eigenvalues[-1] / eigenvalues[0]], rtol=1e-10)


def test_symmetric_sqrt_uses_only_the_symmetric_part_and_returns_exactly_symmetric_matrices() -> None:
    sigma = _spd(2, 12, seed=4)
    antisymmetric = torch.randn(2, 12, 12, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    antisymmetric = 1e-3 * (antisymmetric - antisymmetric.transpose(1, 2))
    root, inverse = symmetric_sqrt_and_inverse(sigma)
    root_perturbed, inverse_perturbed = symmetric_sqrt_and_inverse(sigma + antisymmetric)
    torch.testing.assert_close(root_perturbed, root, atol=1e-13, rtol=0)
    torch.testing.assert_close(inverse_perturbed, inverse, atol=1e-12, rtol=0)
    assert torch.equal(root, root.transpose(1, 2)) and torch.equal(inverse, inverse.transpose(1, 2))


def test_symmetric_sqrt_of_float32_input_is_computed_in_float64() -> None:
    sigma32 = _spd(1, 12, seed=6).float()
    root, inverse = symmetric_sqrt_and_inverse(sigma32)
    assert root.dtype == torch.float64 and inverse.dtype == torch.float64
    reference = sigma32[0].double()
    torch.testing.assert_close(root[0] @ root[0], reference, atol=1e-13, rtol=0)
    torch.testing.assert_close(
        inverse[0] @ reference @ inverse[0], torch.eye(12, dtype=torch.float64), atol=1e-12, rtol=0
    )


def test_symmetric_sqrt_errors_name_the_offending_quantity() -> None:
    sigma = torch.diag(torch.tensor([1.0, 0.0, 2.0], dtype=torch.float64))[None]
    with pytest.raises(ValueError, match=r"^diagonal of sigma must lie in \(0, inf\), got 0"):
        symmetric_sqrt_and_inverse(sigma, diagonal_only=True)
    with pytest.raises(ValueError, match=r"^eigenvalues of sigma must lie in \(0, inf\), got 0"):
        symmetric_sqrt_and_inverse(sigma)
    with pytest.raises(ValueError, match="^sigma must be finite"):
        symmetric_sqrt_and_inverse(torch.full((1, 2, 2), math.nan, dtype=torch.float64))


def test_whitening_error_accepts_every_whitening_and_reports_per_camera() -> None:
    """Every P = Q Sigma^(1/2) with Q orthogonal whitens (eqs. 18-19), not only the symmetric one."""
    sigma = _spd(1, 6, seed=7)
    root, inverse = symmetric_sqrt_and_inverse(sigma)
    q = _rotation(6, seed=8)
    rotated_inverse = torch.linalg.inv(q @ root[0])[None]  # P^-1 = Sigma^(-1/2) Q^T, not symmetric
    assert whitening_error(rotated_inverse, sigma).item() < 1e-12
    # Two cameras: P^-1 = S^-1 (exact) and 2 S^-1 (whitened spectrum 4): errors 0 and 3.
    errors = whitening_error(torch.cat([inverse, 2.0 * inverse]), torch.cat([sigma, sigma]))
    torch.testing.assert_close(errors, torch.tensor([0.0, 3.0], dtype=torch.float64), atol=1e-12, rtol=0)
    errors32 = whitening_error(inverse.float(), sigma.float())
    expected = np.abs(np.linalg.eigvalsh(inverse[0].float().double().numpy().T @ sigma[0].float().double().numpy()
                                         @ inverse[0].float().double().numpy()) - 1.0).max()  # fmt: skip
    np.testing.assert_allclose(errors32.numpy(), [expected], rtol=1e-9, atol=1e-15)


def test_diagonal_only_preconditioner_is_the_damped_diagonal_root() -> None:
    result = compute_preconditioner(ROOM, damping=DampingConfig(diagonal_only=True))
    diagonal = torch.diagonal(result.gram[0])
    damped = diagonal + torch.clamp(0.1 * diagonal, min=1e-8)  # default damping_rel 0.1, damping_abs 1e-8
    torch.testing.assert_close(result.matrix[0], torch.diag(torch.sqrt(damped)), atol=0, rtol=1e-12)
    torch.testing.assert_close(result.inverse[0], torch.diag(1.0 / torch.sqrt(damped)), atol=0, rtol=1e-12)


def test_preconditioner_counts_the_valid_proxy_points() -> None:
    points = sample_proxy_points(ROOM, SamplingConfig(num_points=300))
    result = compute_preconditioner(ROOM, sampling=SamplingConfig(num_points=300))
    assert result.num_valid.tolist() == [points.shape[1]]  # the pyramid transform keeps every point in the image


def test_float32_inputs_give_the_float64_gram() -> None:
    room32 = Intrinsics.create(fx=793.13, fy=793.49, cx=389.25, cy=259.375, width=778, height=518, dtype=torch.float32)
    room64 = room32.to(dtype=torch.float64)  # the same (float32-rounded) values
    points = sample_proxy_points(room64, SamplingConfig(num_points=100))
    torch.testing.assert_close(sample_proxy_points(room32, SamplingConfig(num_points=100)), points, atol=1e-13, rtol=0)
    sigma64, _ = gram_from_points(points, room64)
    for intrinsics, pts in ((room32, points), (room64, points.float())):
        sigma, _ = gram_from_points(pts, intrinsics)
        assert sigma.dtype == torch.float64
        reference = sigma64 if pts.dtype == torch.float64 else gram_from_points(pts.double(), room64)[0]
        torch.testing.assert_close(sigma, reference, atol=1e-15, rtol=1e-12)


@pytest.mark.parametrize("sampler", ["random", "sobol"])
def test_seeded_samplers_follow_the_seed(sampler: str) -> None:
    seven = sample_proxy_points(ROOM, SamplingConfig(sampler=sampler, num_points=64, seed=7))
    default = sample_proxy_points(ROOM, SamplingConfig(sampler=sampler, num_points=64))
    torch.testing.assert_close(sample_proxy_points(ROOM, SamplingConfig(sampler=sampler, num_points=64, seed=7)), seven)
    assert not torch.equal(seven, default)


@pytest.mark.parametrize("radial", ["volume", "ray"])
def test_proxy_points_follow_the_radial_map(radial: str) -> None:
    """Contracted radius of each proxy point = Q_r(u1) of its lattice point (paper eq. 12, or CamP's uniform one)."""
    t_near, t_far = 0.4, 1.8
    unit = unit_cube_points("frolov", 200)
    points = sample_proxy_points(ROOM, SamplingConfig(num_points=200, t_near=t_near, t_far=t_far, radial=radial))
    r = points[0].norm(dim=-1)
    contracted = torch.where(r <= 1.0, r, 2.0 - 1.0 / r)  # paper eq. 10 by hand
    u1 = unit[:, 0].double()
    if radial == "ray":
        expected = t_near + u1 * (t_far - t_near)
    else:
        expected = (t_near**3 + u1 * (t_far**3 - t_near**3)) ** (1.0 / 3.0)
    torch.testing.assert_close(contracted, expected, atol=1e-12, rtol=0)


@pytest.mark.parametrize(
    ("config", "message"),
    [
        (SamplingConfig(t_near=-0.1, t_far=1.5), r"^t_near must lie in \[0, inf\)"),
        (SamplingConfig(t_near=1.0, t_far=1.0), r"^t_far must lie in \(1, 2\)"),
        (SamplingConfig(t_near=0.4, t_far=2.0), r"^t_far must lie in \(0.4, 2\)"),
        # One explicit end: room must be left for the chosen other end (min_width 0.2 inside [0.1, 1.99]).
        (SamplingConfig(t_near=-0.1), r"^t_near must lie in \[0, 1.79\]"),
        (SamplingConfig(t_near=1.8), r"^t_near must lie in \[0, 1.79\]"),
        (SamplingConfig(t_far=2.0), r"^t_far must lie in \[0.3, 2\)"),
        (SamplingConfig(t_far=0.25), r"^t_far must lie in \[0.3, 2\)"),
        (SamplingConfig(transform="cone"), "^transform must be one of"),  # type: ignore[arg-type]
    ],
)
def test_sampling_config_validates_itself(config: SamplingConfig, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        config.validate()


@pytest.mark.parametrize("radial", ["volume", "ray"])
def test_fisheye_proxy_points_lie_on_the_pixel_and_radius_of_their_lattice_point(radial: str) -> None:
    """Fisheye proxies: lattice point (u1, u2, u3) -> pixel (u3 W, u2 H) at contracted radius Q_r(u1) (eqs. 10, 12)."""
    t_near, t_far = 0.4, 1.8
    unit = unit_cube_points("frolov", 200).double()
    points = sample_proxy_points(FISHEYE, SamplingConfig(num_points=200, t_near=t_near, t_far=t_far, radial=radial))
    r = points.norm(dim=-1)
    contracted = torch.where(r <= 1.0, r, 2.0 - 1.0 / r)  # paper eq. 10 by hand
    u1 = unit[:, 0].expand(2, -1)
    if radial == "ray":
        expected = t_near + u1 * (t_far - t_near)
    else:
        expected = (t_near**3 + u1 * (t_far**3 - t_near**3)) ** (1.0 / 3.0)
    torch.testing.assert_close(contracted, expected, atol=1e-12, rtol=0)
    pixels, _ = project(points, FISHEYE)
    expected_pixels = torch.stack([unit[:, 2] * 640.0, unit[:, 1] * 480.0], dim=-1).expand(2, -1, -1)
    torch.testing.assert_close(pixels, expected_pixels, atol=1e-6, rtol=0)


def test_fisheye_proxy_points_follow_the_seed_and_are_computed_in_float64() -> None:
    seven = sample_proxy_points(FISHEYE, SamplingConfig(sampler="random", num_points=64, seed=7))
    default = sample_proxy_points(FISHEYE, SamplingConfig(sampler="random", num_points=64))
    assert not torch.equal(seven, default)
    torch.testing.assert_close(
        sample_proxy_points(FISHEYE, SamplingConfig(sampler="random", num_points=64, seed=7)), seven
    )
    fisheye32 = FISHEYE.to(dtype=torch.float32)
    points32 = sample_proxy_points(fisheye32, SamplingConfig(num_points=64))
    assert points32.dtype == torch.float64
    reference = sample_proxy_points(fisheye32.to(dtype=torch.float64), SamplingConfig(num_points=64))
    torch.testing.assert_close(points32, reference, atol=1e-12, rtol=0)


def _varied_cameras(n: int) -> Intrinsics:
    """Distinct, distorted cameras (no two share intrinsics)."""
    scale = torch.linspace(0.9, 1.1, n, dtype=torch.float64)
    return Intrinsics.create(
        fx=500.0 * scale, fy=498.0 * scale, cx=320.0 + scale, cy=240.0 - scale, width=640, height=480,
        k1=-0.01 * scale, k2=0.001,
    )  # fmt: skip


def _assert_same_bits(a, b) -> None:
    for name in ("matrix", "inverse", "gram", "num_valid"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize(
    "sampling",
    [
        SamplingConfig(num_points=500),
        SamplingConfig(num_points=333, transform="spherical"),
        SamplingConfig(num_points=200, sampler="sobol", transform="pixel", radial="ray"),
        SamplingConfig(num_points=300, sampler="halton"),
    ],
    ids=["frolov", "frolov-spherical", "sobol-pixel-ray", "halton"],
)
@pytest.mark.parametrize("chunk_size", [1, 3, 7, 16])
def test_chunked_preconditioner_is_bit_identical_to_unchunked(sampling: SamplingConfig, chunk_size: int) -> None:
    """Chunking bounds memory for 100k cameras; it must not change a single bit of P (every rank relies on it)."""
    cameras = _varied_cameras(37)
    whole = compute_preconditioner(cameras, sampling=sampling, chunk_size=None)
    chunked = compute_preconditioner(cameras, sampling=sampling, chunk_size=chunk_size)
    _assert_same_bits(whole, chunked)


@pytest.mark.parametrize("model", ["fisheye", "opencv"])
def test_chunked_preconditioner_is_bit_identical_for_fisheye_and_tangential_cameras(model: str) -> None:
    scale = torch.linspace(0.9, 1.1, 23, dtype=torch.float64)
    if model == "fisheye":
        cameras = Intrinsics.create(
            fx=170.0 * scale, fy=171.0 * scale, cx=320.0, cy=240.0, width=640, height=480,
            k1=0.03 * scale, k2=-0.002, k3=0.0005, k4=0.00005, model="fisheye",
        )  # fmt: skip
    else:
        cameras = Intrinsics.create(
            fx=410.0 * scale, fy=405.0 * scale, cx=330.0, cy=210.0, width=640, height=420,
            k1=-0.03 * scale, k2=0.004, p1=0.001, p2=-0.002,
        )  # fmt: skip
    whole = compute_preconditioner(cameras, chunk_size=None)
    for chunk_size in (1, 3, 7):
        _assert_same_bits(whole, compute_preconditioner(cameras, chunk_size=chunk_size))


def test_cameras_sharing_intrinsics_share_p_bit_for_bit() -> None:
    cameras = _varied_cameras(12)
    index = torch.tensor([3, 3, 7, 3, 10, 7, 11, 0])
    repeated = cameras[index]
    separate = compute_preconditioner(repeated, chunk_size=None, share_intrinsics=False)
    shared = compute_preconditioner(repeated)
    _assert_same_bits(separate, shared)
    assert torch.equal(shared.matrix, compute_preconditioner(cameras).matrix[index])
    assert torch.equal(shared.matrix[0], shared.matrix[1])


def test_chunk_size_is_validated() -> None:
    with pytest.raises(ValueError, match=r"^chunk_size must be an integer in \[1, inf\), got 0$"):
        compute_preconditioner(ROOM, chunk_size=0)


# ----------------------------------------------------------------------------------- per-camera proxy ranges


def _three_cameras() -> Intrinsics:
    """Two bitwise-equal room cameras and a distorted one."""
    return Intrinsics.create(
        fx=torch.tensor([793.13, 793.13, 410.0]),
        fy=torch.tensor([793.49, 793.49, 405.0]),
        cx=torch.tensor([389.25, 389.25, 330.0]),
        cy=torch.tensor([259.375, 259.375, 210.0]),
        width=torch.tensor([778.0, 778.0, 640.0]),
        height=torch.tensor([518.0, 518.0, 420.0]),
        k1=torch.tensor([0.0, 0.0, -0.03]),
        k2=torch.tensor([0.0, 0.0, 0.004]),
    )


def test_proxy_points_lie_in_each_cameras_own_range() -> None:
    ranges = torch.tensor([[0.2, 0.9], [0.6, 1.9], [0.4, 1.5]], dtype=torch.float64)
    points = sample_proxy_points(_three_cameras(), SamplingConfig(num_points=300), ranges=ranges)
    radius = points.norm(dim=-1)
    t = torch.where(radius <= 1.0, radius, 2.0 - 1.0 / radius)  # paper eq. 10, written out
    assert (t >= ranges[:, :1] - 1e-12).all() and (t <= ranges[:, 1:] + 1e-12).all()
    assert (t.amin(dim=-1) < ranges[:, 0] + 0.05).all() and (t.amax(dim=-1) > ranges[:, 1] - 0.05).all()


def test_a_range_given_for_every_camera_is_the_fixed_range_bit_for_bit() -> None:
    intrinsics = _three_cameras()
    fixed = compute_preconditioner(intrinsics, sampling=SamplingConfig(t_near=0.4, t_far=1.5))
    default = compute_preconditioner(intrinsics)  # both ends unset and no scene: the fallback (0.4, 1.5)
    ranges = torch.tensor([[0.4, 1.5]], dtype=torch.float64).expand(3, 2)
    per_camera = compute_preconditioner(intrinsics, ranges=ranges)
    for result in (default, per_camera):
        assert torch.equal(result.matrix, fixed.matrix) and torch.equal(result.gram, fixed.gram)


def test_the_range_enters_p_and_the_same_range_gives_the_same_bits() -> None:
    intrinsics = _three_cameras()
    ranges = torch.tensor([[0.4, 1.5], [0.6, 1.2], [0.3, 1.8]], dtype=torch.float64)
    result = compute_preconditioner(intrinsics, ranges=ranges)
    again = compute_preconditioner(intrinsics, ranges=ranges.clone())
    assert torch.equal(result.matrix, again.matrix) and torch.equal(result.inverse, again.inverse)
    # Cameras 0 and 1 have the same intrinsics but different ranges: they are no longer shared.
    assert (result.matrix[0] - result.matrix[1]).abs().max() > 1e-3 * result.matrix[0].abs().max()
    # Each camera's P is its own range's, whatever the batch or the chunking.
    for camera in range(3):
        alone = compute_preconditioner(intrinsics[camera : camera + 1], ranges=ranges[camera : camera + 1])
        assert torch.equal(alone.matrix[0], result.matrix[camera])
    chunked = compute_preconditioner(intrinsics, ranges=ranges, chunk_size=1, share_intrinsics=False)
    assert torch.equal(chunked.matrix, result.matrix) and torch.equal(chunked.gram, result.gram)


def test_per_camera_ranges_reach_fisheye_proxy_points() -> None:
    fisheye = Intrinsics.create(
        fx=torch.tensor([200.0, 200.0]), fy=200.0, cx=320.0, cy=240.0, width=640, height=480, model="fisheye"
    )
    ranges = torch.tensor([[0.3, 0.8], [1.2, 1.9]], dtype=torch.float64)
    radius = sample_proxy_points(fisheye, SamplingConfig(num_points=200), ranges=ranges).norm(dim=-1)
    t = torch.where(radius <= 1.0, radius, 2.0 - 1.0 / radius)
    assert (t >= ranges[:, :1] - 1e-12).all() and (t <= ranges[:, 1:] + 1e-12).all()


@pytest.mark.parametrize(
    ("ranges", "sampling", "message"),
    [
        (torch.tensor([[0.4, 1.5]]), SamplingConfig(), r"^ranges must have shape \[3, 2\]"),
        (torch.tensor([[0.4, 1.5]] * 2 + [[0.9, 0.9]]), SamplingConfig(), r"^ranges t_far - t_near must lie in"),
        (torch.tensor([[0.4, 2.0]] * 3), SamplingConfig(), r"^ranges t_far must lie in \(-inf, 2\)"),
        (torch.tensor([[0.4, 1.5]] * 3), SamplingConfig(sampler="camp-random"), "^ranges must be None for sampler"),
    ],
)
def test_bad_ranges_are_named(ranges: torch.Tensor, sampling: SamplingConfig, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        compute_preconditioner(_three_cameras(), sampling=sampling, ranges=ranges.double())


def test_a_sampling_config_saved_before_auto_range_existed_loads_with_its_default() -> None:
    """nerfstudio reloads config.yml with PyYAML, which builds the object from the saved fields only: a run saved
    before ``auto_range`` existed (with its explicit 0.4 / 1.5) must still load, and keep its fixed range."""
    import yaml

    saved = yaml.dump(SamplingConfig(t_near=0.4, t_far=1.5))
    old = "\n".join(line for line in saved.splitlines() if "auto_range" not in line and not line.startswith("  "))
    loaded = yaml.load(old, Loader=yaml.Loader)
    assert "auto_range" not in old and loaded.auto_range.rule == "moments"
    assert (loaded.t_near, loaded.t_far, loaded.auto) == (0.4, 1.5, False)
    loaded.validate()
    assert yaml.load(saved, Loader=yaml.Loader) == SamplingConfig(t_near=0.4, t_far=1.5)


@pytest.mark.parametrize(
    ("ranges", "message"),
    [
        (
            torch.tensor([[0.4, 1.5]], dtype=torch.float64),
            "ranges must have shape [3, 2] ([t_near, t_far] per camera), got (1, 2)",
        ),
        ([[0.4, 1.5]] * 3, "ranges must have shape [3, 2] ([t_near, t_far] per camera), got list"),
        (
            torch.tensor([[0.4, 1.5], [-0.1, 1.5], [0.4, 1.5]], dtype=torch.float64),
            "ranges t_near must lie in [0, inf), got -0.1 (element 1)",
        ),
    ],
    ids=["shape", "not-a-tensor", "negative-t-near"],
)
def test_bad_ranges_messages_name_the_parameter_the_value_and_the_allowed_range(ranges, message: str) -> None:
    with pytest.raises(ValueError) as error:
        compute_preconditioner(_three_cameras(), ranges=ranges)
    assert str(error.value) == message


def test_reexpress_adam_state_maps_the_moments_of_non_symmetric_preconditioners() -> None:
    """Every P = Q Sigma^(1/2) whitens (eqs. 18-19), so P need not be symmetric. With M = P_new P_old^-1,
    m_new = M^-T m_old = P_new^-T P_old^T m_old and v_new = (M^-T)^2 v_old (elementwise square), by hand for
    P_old = [[1, 1], [0, 1]], P_new = [[1, 0], [2, 1]]:
    M^-T = [[1, -2], [0, 1]] [[1, 0], [1, 1]] = [[-1, -2], [1, 1]]."""

    def preconditioner(matrix: list[list[float]], inverse: list[list[float]]) -> Preconditioner:
        p = torch.tensor([matrix], dtype=torch.float64)
        return Preconditioner(matrix=p, inverse=torch.tensor([inverse], dtype=torch.float64), gram=p, num_valid=p)

    old = preconditioner([[1.0, 1.0], [0.0, 1.0]], [[1.0, -1.0], [0.0, 1.0]])
    new = preconditioner([[1.0, 0.0], [2.0, 1.0]], [[1.0, 0.0], [-2.0, 1.0]])
    state = {"exp_avg": torch.tensor([[1.0, 2.0]]), "exp_avg_sq": torch.tensor([[1.0, 4.0]])}
    reexpress_adam_state(old, new, state)
    assert state["exp_avg"].tolist() == [[-5.0, 3.0]] and state["exp_avg"].dtype == torch.float32
    assert state["exp_avg_sq"].tolist() == [[17.0, 5.0]] and state["exp_avg_sq"].dtype == torch.float32


@pytest.mark.parametrize("radial", [None, "ray"], ids=["default-volume", "ray"])
def test_per_camera_ranges_give_fisheye_points_the_radius_of_their_lattice_point(radial: str | None) -> None:
    """Contracted radius of fisheye proxy n, l = Q_r(u1_l) on camera n's own [t_near, t_far] (paper eq. 12)."""
    ranges = torch.tensor([[0.3, 0.8], [1.2, 1.9]], dtype=torch.float64)
    sampling = SamplingConfig(num_points=200) if radial is None else SamplingConfig(num_points=200, radial=radial)
    radius = sample_proxy_points(FISHEYE, sampling, ranges=ranges).norm(dim=-1)
    contracted = torch.where(radius <= 1.0, radius, 2.0 - 1.0 / radius)  # paper eq. 10 by hand
    u1 = unit_cube_points("frolov", 200).double()[:, 0]
    near, far = ranges[:, :1], ranges[:, 1:]
    if radial == "ray":
        expected = near + u1 * (far - near)
    else:
        expected = (near**3 + u1 * (far**3 - near**3)) ** (1.0 / 3.0)
    torch.testing.assert_close(contracted, expected, atol=1e-12, rtol=0)


def test_a_reloaded_old_sampling_config_saves_every_field_again() -> None:
    """nerfstudio writes the loaded config back to config.yml: a field missing from an old file (here ``seed`` and
    ``ladder_p``) must come back with its default, not vanish from the next saved file."""
    import yaml

    saved = yaml.dump(SamplingConfig(t_near=0.4, t_far=1.5))
    old = "\n".join(line for line in saved.splitlines() if not line.startswith(("seed:", "ladder_p:")))
    assert "seed" not in old and "ladder_p" not in old
    assert yaml.dump(yaml.load(old, Loader=yaml.Loader)) == saved


def test_camp_random_uses_the_configured_ray_distances_ladder_and_seed() -> None:
    """CamP's sampler: ray distances (no contraction) from the config's t_near / t_far (0.4 / 1.5 when unset, CamP's
    0.4 / 1000 in CAMP_SAMPLING), on the power ladder of its ladder_p, from draws of a CPU generator seeded with its
    seed: [N, L, 3] uniforms whose third coordinate is the ladder's s (s2camp_ns/core/camp_sampling.py)."""
    from s2camp_ns.core.camp_sampling import ladder_distance
    from s2camp_ns.core.preconditioner import CAMP_SAMPLING

    assert SamplingConfig(sampler="camp-random").fixed_range() == (0.4, 1.5)
    assert SamplingConfig(sampler="camp-random", t_near=0.6, t_far=50.0).fixed_range() == (0.6, 50.0)
    assert CAMP_SAMPLING.fixed_range() == (0.4, 1000.0)
    sampling = SamplingConfig(sampler="camp-random", num_points=50, seed=3, t_near=0.6, t_far=50.0, ladder_p=-2.5)
    distance = sample_proxy_points(ROOM, sampling).norm(dim=-1)
    draws = torch.rand((1, 50, 3), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    torch.testing.assert_close(distance, ladder_distance(draws[..., 2], 0.6, 50.0, -2.5), atol=1e-12, rtol=1e-12)


def test_chunks_of_camp_random_cameras_continue_one_random_stream() -> None:
    """Passing one generator through the chunks gives the points of one unchunked call (up to the last bits of pow
    and undistortion, compute_preconditioner's docstring), so P agrees to rounding; fresh draws per chunk would not."""
    cameras = _varied_cameras(5)
    sampling = SamplingConfig(sampler="camp-random", num_points=64, seed=2)
    whole = compute_preconditioner(cameras, sampling=sampling, chunk_size=None)
    chunked = compute_preconditioner(cameras, sampling=sampling, chunk_size=2)
    torch.testing.assert_close(chunked.matrix, whole.matrix, rtol=1e-9, atol=1e-12)


def test_fixed_ranges_keep_the_configured_minimum_width_but_not_for_camp_random() -> None:
    """An explicit t_far = 0.5 leaves the default near end 0.4 too close: it moves to 0.5 - min_width (0.2 by default,
    0.3 here). CamP's ray distances are taken as given: t_near = 1.45 keeps the default far end 1.5."""
    from s2camp_ns.core.proxy_range import ProxyRangeConfig

    assert SamplingConfig(t_far=0.5).fixed_range() == pytest.approx((0.3, 0.5), abs=1e-15)
    wide = SamplingConfig(t_far=0.5, auto_range=ProxyRangeConfig(min_width=0.3))
    assert wide.fixed_range() == pytest.approx((0.2, 0.5), abs=1e-15)
    assert SamplingConfig(sampler="camp-random", t_near=1.45).fixed_range() == (1.45, 1.5)


def test_camp_random_cameras_with_equal_intrinsics_get_their_own_points() -> None:
    """CamP's per-camera random points are never shared: two bitwise-equal cameras get different points, so
    different P (the other samplers share one computation, bit-identical to separate ones)."""
    cameras = _varied_cameras(3)[torch.tensor([0, 0, 1])]
    result = compute_preconditioner(cameras, sampling=SamplingConfig(sampler="camp-random", num_points=64))
    assert float((result.matrix[0] - result.matrix[1]).abs().max()) > 1e-6 * float(result.matrix[0].abs().max())


def test_shared_computation_keeps_the_layout_damping_and_ranges() -> None:
    """Cameras 0 and 2 are equal in intrinsics and range, so they share one computation: it must use the caller's
    layout, damping and ranges, bit for bit as separate computations do."""
    cameras = _varied_cameras(2)[torch.tensor([0, 1, 0])]
    ranges = torch.tensor([[0.6, 1.2], [0.3, 1.8], [0.6, 1.2]], dtype=torch.float64)
    layout = ParameterLayout.from_preset("pose+focal")
    damping = DampingConfig(damping_rel=0.5)
    sampling = SamplingConfig(num_points=200, transform="spherical", radial="ray")
    shared = compute_preconditioner(cameras, layout, sampling, damping, ranges=ranges)
    separate = compute_preconditioner(cameras, layout, sampling, damping, ranges=ranges, share_intrinsics=False)
    _assert_same_bits(shared, separate)
    assert shared.matrix.shape == (3, 7, 7) and torch.equal(shared.matrix[0], shared.matrix[2])
    fisheye = FISHEYE[torch.tensor([0, 1, 0])]  # and the projection model
    _assert_same_bits(compute_preconditioner(fisheye), compute_preconditioner(fisheye, share_intrinsics=False))


def test_equal_cameras_are_computed_once_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    """compute_preconditioner's docstring: cameras with bitwise-equal intrinsics share one computation."""
    from s2camp_ns.core import preconditioner as module

    cameras_seen = []
    original = module.gram_from_points

    def counting(points, intrinsics, layout=None):
        cameras_seen.append(intrinsics.num_cameras)
        return original(points, intrinsics, layout)

    monkeypatch.setattr(module, "gram_from_points", counting)
    compute_preconditioner(_varied_cameras(2)[torch.tensor([0, 1, 0, 1])])
    assert cameras_seen == [2]
