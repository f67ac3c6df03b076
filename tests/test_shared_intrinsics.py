"""Preconditioner for intrinsics shared by the images of one physical camera (block-triangular factor)."""

from __future__ import annotations

import pytest
import torch
from joint_latents import deltas_from_latents, joint_gram, joint_inverse

from s2camp_ns.core.camera import Intrinsics, ParameterLayout, project_with_delta
from s2camp_ns.core.preconditioner import (
    DampingConfig,
    SamplingConfig,
    compute_preconditioner,
    sample_proxy_points,
)
from s2camp_ns.core.shared_intrinsics import (
    block_triangular_factor,
    compute_shared_preconditioner,
    reexpress_latents,
)

ROOM = Intrinsics.create(fx=793.13, fy=793.49, cx=389.25, cy=259.375, width=778, height=518, k1=-0.02, k2=0.003)
NO_DAMPING = DampingConfig(damping_abs=1e-14, damping_rel=0.0)


def _spd(n: int, k: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 3 * k, k, generator=generator, dtype=torch.float64)
    return a.transpose(1, 2) @ a / (3 * k) + 0.05 * torch.eye(k, dtype=torch.float64)


def test_factor_is_block_upper_triangular_and_reproduces_the_damped_gram() -> None:
    sigma = _spd(3, 12, seed=1)
    matrix, inverse = block_triangular_factor(sigma, DampingConfig(damping_abs=1e-8, damping_rel=0.1))
    # Damping written out by hand: Sigma + diag(max(1e-8, 0.1 diag(Sigma))).
    damped = sigma + torch.diag_embed(torch.clamp(0.1 * torch.diagonal(sigma, dim1=-2, dim2=-1), min=1e-8))
    torch.testing.assert_close(matrix.transpose(-1, -2) @ matrix, damped, atol=1e-12, rtol=1e-12)  # eq. 17
    eye = torch.eye(12, dtype=torch.float64).expand(3, 12, 12)
    torch.testing.assert_close(matrix @ inverse, eye, atol=1e-12, rtol=0)
    assert torch.count_nonzero(matrix[:, 6:, :6]) == 0 and torch.count_nonzero(inverse[:, 6:, :6]) == 0
    # The pose block is the symmetric root of A (eq. 20 on the pose alone).
    torch.testing.assert_close(matrix[:, :6, :6] @ matrix[:, :6, :6], damped[:, :6, :6], atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("num_images", [1, 2, 5])
def test_whitened_joint_gram_is_identity_with_the_shared_block_counted_per_image(num_images: int) -> None:
    sigma = _spd(1, 12, seed=2)[0]
    _, inverse = block_triangular_factor(sigma[None], NO_DAMPING)
    whitened_inverse = joint_inverse(inverse[0], num_images)
    whitened = whitened_inverse.T @ joint_gram(sigma, num_images) @ whitened_inverse
    expected = torch.diag(torch.tensor([1.0] * (6 * num_images) + [float(num_images)] * 6, dtype=torch.float64))
    torch.testing.assert_close(whitened, expected, atol=1e-9, rtol=0)


def test_joint_gram_matches_stacked_jacobians() -> None:
    # Independent construction: stack per-image Jacobians into one (n L) x (6 n + m) matrix and take J^T J.
    generator = torch.Generator().manual_seed(3)
    jacobian = torch.randn(40, 9, generator=generator, dtype=torch.float64)
    sigma = jacobian.T @ jacobian
    stacked = torch.zeros(3 * 40, 6 * 3 + 3, dtype=torch.float64)
    for i in range(3):
        stacked[40 * i : 40 * (i + 1), 6 * i : 6 * (i + 1)] = jacobian[:, :6]
        stacked[40 * i : 40 * (i + 1), 18:] = jacobian[:, 6:]
    torch.testing.assert_close(joint_gram(sigma, 3), stacked.T @ stacked, atol=1e-10, rtol=1e-12)


def test_single_image_spectrum_equals_the_symmetric_root() -> None:
    # T = Q Sigma^(1/2) (eq. 19): P^-T Sigma P^-1 has the same eigenvalues for T and for the symmetric root.
    shared = compute_shared_preconditioner(ROOM)
    symmetric = compute_preconditioner(ROOM)
    sigma = shared.gram
    by_factor = torch.linalg.eigvalsh(shared.inverse.transpose(-1, -2) @ sigma @ shared.inverse)
    by_root = torch.linalg.eigvalsh(symmetric.inverse.transpose(-1, -2) @ symmetric.gram @ symmetric.inverse)
    torch.testing.assert_close(by_factor, by_root, atol=1e-9, rtol=1e-7)


def test_shared_focal_step_brings_its_compensating_pose_along() -> None:
    # A step of the shared latent moves the proxy projections less than the same intrinsics change with the pose
    # held fixed: the pose part of T^-1 [0; w] is the least-squares compensation -A^-1 B e.
    shared = compute_shared_preconditioner(ROOM)
    points = sample_proxy_points(ROOM, SamplingConfig())
    w = torch.zeros(1, 6, dtype=torch.float64)
    w[0, 0] = 1e-3  # along the first shared latent coordinate
    phi = deltas_from_latents(torch.zeros(1, 6, dtype=torch.float64), w, torch.tensor([0]), shared.inverse)
    bare = phi.clone()
    bare[:, :6] = 0.0
    base = project_with_delta(points, ROOM, torch.zeros(1, 12, dtype=torch.float64))
    moved = (project_with_delta(points, ROOM, phi) - base).norm(dim=-1).mean()
    unmatched = (project_with_delta(points, ROOM, bare) - base).norm(dim=-1).mean()
    assert float(phi[:, :6].abs().max()) > 0
    assert float(moved) < 0.8 * float(unmatched)


def test_reexpressing_keeps_every_camera_and_maps_the_first_moment_exactly() -> None:
    layout = ParameterLayout()
    old = compute_shared_preconditioner(
        Intrinsics.create(fx=[300.0, 500.0], fy=[300.0, 500.0], cx=160, cy=120, width=320, height=240), layout
    )
    new = compute_shared_preconditioner(
        Intrinsics.create(fx=[310.0, 480.0], fy=[310.0, 480.0], cx=162, cy=118, width=320, height=240, k1=0.01), layout
    )
    camera_of_image = torch.tensor([0, 1, 1, 0, 1])
    generator = torch.Generator().manual_seed(4)
    pose = torch.randn(5, 6, generator=generator, dtype=torch.float64) * 1e-2
    intrinsics = torch.randn(2, 6, generator=generator, dtype=torch.float64) * 1e-2
    target = torch.randn(5, 12, generator=generator, dtype=torch.float64)

    def gradients(matrix_inverse: torch.Tensor, z: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, ...]:
        z, w = z.clone().requires_grad_(True), w.clone().requires_grad_(True)
        phi = deltas_from_latents(z, w, camera_of_image, matrix_inverse)
        loss = ((phi - target) ** 2 * torch.arange(1, 13, dtype=torch.float64)).sum()
        return (phi.detach(), *torch.autograd.grad(loss, (z, w)))

    phi_before, grad_z, grad_w = gradients(old.inverse, pose, intrinsics)
    pose_state = {"exp_avg": grad_z.clone(), "exp_avg_sq": grad_z.square()}
    intrinsics_state = {"exp_avg": grad_w.clone(), "exp_avg_sq": grad_w.square()}
    reexpress_latents(
        pose, intrinsics, camera_of_image, old.matrix, old.inverse, new.matrix, new.inverse, pose_state,
        intrinsics_state,
    )  # fmt: skip
    phi_after, new_grad_z, new_grad_w = gradients(new.inverse, pose, intrinsics)
    torch.testing.assert_close(phi_after, phi_before, atol=1e-12, rtol=1e-10)
    # The gradient at the same cameras, taken in the new latent by autograd, is what the moment mapping predicts.
    torch.testing.assert_close(pose_state["exp_avg"], new_grad_z, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(intrinsics_state["exp_avg"], new_grad_w, atol=1e-9, rtol=1e-9)
    assert not torch.allclose(new_grad_w, grad_w)


def test_bad_camera_index_names_the_parameter() -> None:
    shared = compute_shared_preconditioner(ROOM)
    with pytest.raises(ValueError, match=r"camera_of_image must lie in \[0, 0\]"):
        deltas_from_latents(torch.zeros(2, 6), torch.zeros(1, 6), torch.tensor([0, 1]), shared.inverse)
    with pytest.raises(ValueError, match="shared intrinsics need the pose group"):
        compute_shared_preconditioner(ROOM, ParameterLayout(pose=False))
