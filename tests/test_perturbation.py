"""CamP perturbation protocol: statistics, determinism and input checks."""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_ns.core.alignment import rotation_angle
from s2camp_ns.core.perturbation import PerturbationConfig, look_at_rotation, perturb_cameras


def ring_cameras(n: int, radius: float = 1.0, height: float = 0.3) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV cameras on a ring, all looking at the origin, world up +z; focal 500 px."""
    angle = torch.linspace(0.0, 2 * math.pi, n + 1, dtype=torch.float64)[:-1]
    centre = torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), torch.full_like(angle, height)], -1)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
    rotation = look_at_rotation(centre, torch.zeros_like(centre), up)
    return torch.cat([rotation, centre[:, :, None]], dim=-1), torch.full((n,), 500.0, dtype=torch.float64)


def test_zero_sigmas_is_identity():
    c2w, f = ring_cameras(16)
    config = PerturbationConfig(sigma_look_at=0, sigma_position=0, sigma_dolly_z=0, sigma_focal_length=0)
    out = perturb_cameras(c2w, f, f * 1.01, config)
    torch.testing.assert_close(out.c2w, c2w, atol=1e-12, rtol=0)
    torch.testing.assert_close(out.fy, f * 1.01, atol=1e-12, rtol=0)


def test_statistics_match_sigmas():
    n = 2000
    c2w, f = ring_cameras(n)
    config = PerturbationConfig(sigma_dolly_z=0.0)  # dolly is one shared draw: checked separately
    out = perturb_cameras(c2w, f, config=config)
    shift = torch.linalg.norm(out.c2w[:, :, 3] - c2w[:, :, 3], dim=-1)
    torch.testing.assert_close(shift, torch.full_like(shift, config.sigma_position), atol=1e-12, rtol=0)
    log_ratio = torch.log(out.fx / f)
    assert abs(float(log_ratio.std()) / math.log1p(config.sigma_focal_length) - 1.0) < 0.06
    assert abs(float(log_ratio.mean())) < 4 * math.log1p(config.sigma_focal_length) / math.sqrt(n)
    # Angle between old and new optical axis: both the look-at and the eye move by 0.005 at distance ~1.04.
    angle = rotation_angle(out.c2w[:, :, :3], c2w[:, :, :3])
    distance = float(torch.linalg.norm(c2w[0, :, 3]))
    assert 0.2 < float(angle.mean()) / (0.01 / distance) < 1.2
    # Up vector kept: the new image x axis stays horizontal to first order.
    assert float(out.c2w[:, 2, 0].abs().max()) < 0.02
    assert torch.all(torch.linalg.det(out.c2w[:, :, :3]) > 0.999999)


def test_dolly_scales_z_translation_and_focal_together():
    c2w, f = ring_cameras(50)
    config = PerturbationConfig(sigma_look_at=0, sigma_position=0, sigma_focal_length=0, sigma_dolly_z=0.2)
    out = perturb_cameras(c2w, f, config=config, seed=3)
    scale = out.dolly_scale
    assert torch.allclose(scale, scale[0].expand_as(scale))  # single dolly: one shared scale
    assert abs(float(scale[0]) - 1.0) > 1e-4
    torch.testing.assert_close(out.fx / f, scale)
    t_old = -torch.einsum("nji,nj->ni", c2w[:, :, :3], c2w[:, :, 3])
    t_new = -torch.einsum("nji,nj->ni", out.c2w[:, :, :3], out.c2w[:, :, 3])
    torch.testing.assert_close(t_new[:, 2], t_old[:, 2] * scale)
    torch.testing.assert_close(t_new[:, :2], t_old[:, :2])
    torch.testing.assert_close(out.c2w[:, :, :3], c2w[:, :, :3])  # look-at unchanged on the axis: no rotation


def test_dolly_log_std_over_seeds():
    c2w, f = ring_cameras(4)
    config = PerturbationConfig(sigma_look_at=0, sigma_position=0, sigma_focal_length=0)
    draws = torch.stack([perturb_cameras(c2w, f, config=config, seed=s).dolly_scale[0] for s in range(400)])
    assert abs(float(torch.log(draws).std()) / math.log1p(config.sigma_dolly_z) - 1.0) < 0.12
    # One dolly shared by every camera (CamP's protocol): one factor, whatever the number of cameras.
    shared = perturb_cameras(ring_cameras(200)[0], torch.full((200,), 500.0, dtype=torch.float64), config=config)
    assert torch.equal(shared.dolly_scale, shared.dolly_scale[0].expand(200))


def test_deterministic_for_seed_and_different_across_seeds():
    c2w, f = ring_cameras(32)
    a = perturb_cameras(c2w, f, config=PerturbationConfig(seed=7))
    b = perturb_cameras(c2w.float(), f.float(), config=PerturbationConfig(seed=7))
    c = perturb_cameras(c2w, f, config=PerturbationConfig(seed=8))
    torch.testing.assert_close(a.c2w, b.c2w, atol=1e-6, rtol=0)  # float32 input: same draws
    assert torch.equal(a.c2w, perturb_cameras(c2w, f, config=PerturbationConfig(seed=7)).c2w)
    assert not torch.allclose(a.c2w, c.c2w)


def test_camera_looking_away_is_not_turned_around():
    c2w, f = ring_cameras(8)
    c2w[:, :, :3] = c2w[:, :, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))  # look out
    out = perturb_cameras(c2w, f, config=PerturbationConfig(sigma_dolly_z=0))
    assert float(rotation_angle(out.c2w[:, :, :3], c2w[:, :, :3]).max()) < 0.05


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sigma_position": -0.1}, "sigma_position"),
        ({"sigma_look_at": float("nan")}, "sigma_look_at"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_config_is_named(kwargs, message):
    c2w, f = ring_cameras(4)
    with pytest.raises(ValueError, match=message):
        perturb_cameras(c2w, f, config=PerturbationConfig(**kwargs))


def test_bad_shapes_and_focals():
    c2w, f = ring_cameras(4)
    with pytest.raises(ValueError, match="c2w must have shape"):
        perturb_cameras(c2w[:, :3, :3], f)
    with pytest.raises(ValueError, match="fx"):
        perturb_cameras(c2w, -f)
