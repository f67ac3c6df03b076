"""Visual-inertial drift of the benchmarks' phone start (``benchmarks/s2camp_bench/phone_drift.py``): growth along the
capture, gravity-held roll and pitch, one shared focal, CamP's result untouched, determinism, the up axis, input checks
and the CLI.

Expected values come from the model's stated equations (module docstring of ``s2camp_bench.phone_drift``)
and from geometry computed here, never from the drift code; the CamP reference numbers were recorded with the
committed CamP implementation before the drift existed."""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_bench.phone_drift import DriftConfig, perturb_with_drift
from s2camp_ns.core.perturbation import PerturbationConfig, look_at_rotation, perturb_cameras

NO_CAMP = {"sigma_look_at": 0.0, "sigma_position": 0.0, "sigma_dolly_z": 0.0, "sigma_focal_length": 0.0}
"""CamP's steps off: the drift alone."""
UP_Z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def ring(
    n: int, radius: float = 1.0, height: float = 0.0, up: torch.Tensor = UP_Z
) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV cameras in capture order on a ring about ``up`` (the plane normal to it, lifted by ``height``), all
    looking at the origin; focal 500 px. Consecutive centres are 2 radius sin(pi / n) apart."""
    angle = torch.linspace(0.0, 2 * math.pi, n + 1, dtype=torch.float64)[:-1]
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(a @ up)) > 0.9:
        a = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    a = a - (a @ up) * up
    a = a / torch.linalg.norm(a)
    b = torch.linalg.cross(up, a, dim=-1)
    centre = radius * (torch.cos(angle)[:, None] * a + torch.sin(angle)[:, None] * b) + height * up
    rotation = look_at_rotation(centre, torch.zeros_like(centre), up.expand(n, 3))
    return torch.cat([rotation, centre[:, :, None]], dim=-1), torch.full((n,), 500.0, dtype=torch.float64)


def drift_config(**drift) -> DriftConfig:
    return DriftConfig(enabled=True, **drift)


def drifted(c2w: torch.Tensor, f: torch.Tensor, drift: DriftConfig, seed: int = 0, fy: torch.Tensor | None = None):
    """The drift alone (CamP's sigmas zero) with perturbation seed ``seed``."""
    fy = f if fy is None else fy
    return perturb_with_drift(c2w, f, fy, PerturbationConfig(**NO_CAMP, seed=seed), drift)


def draws(c2w: torch.Tensor, f: torch.Tensor, drift: DriftConfig, seeds: int) -> list:
    return [drifted(c2w, f, drift, seed) for seed in range(seeds)]


def gravity_in_camera(before: torch.Tensor, after: torch.Tensor, up: torch.Tensor = UP_Z) -> torch.Tensor:
    """The world up as the perturbed camera sees it, mapped back through the unperturbed camera: R R'^T u. Equal to
    u when the perturbation keeps the camera's tilt (any rotation about u, the yaw, leaves it unchanged)."""
    seen = torch.einsum("...ji,j->...i", after[..., :3], up)  # R'^T u
    return torch.einsum("...ij,...j->...i", before[..., :3], seen)


def test_position_rms_grows_along_the_capture_to_the_stated_end_size():
    n, seeds, fraction = 41, 400, 0.02
    c2w, f = ring(n)
    outs = draws(c2w, f, drift_config(position_drift=fraction), seeds)
    error = torch.stack([out.c2w[:, :, 3] for out in outs]) - c2w[:, :, 3]  # [seeds, n, 3]
    rms = error.square().sum(dim=-1).mean(dim=0).sqrt()  # [n]
    travelled = (n - 1) * 2.0 * math.sin(math.pi / n)  # chord length of the ring times the n - 1 steps
    end = fraction * travelled
    assert float(error[:, 0].abs().max()) < 1e-12  # the first camera is where VIO starts: exact
    for k in (1, 5, 10, 20, 30, 40):  # RMS = end sqrt(k / (n - 1)); 400 draws of 3 axes: ~2% sampling error
        assert abs(float(rms[k]) / (end * math.sqrt(k / (n - 1))) - 1.0) < 0.08, k
    assert float(rms[1]) < 0.2 * end < 0.9 * float(rms[-1])
    # A random walk: steps are independent, so the error is correlated along the capture (not i.i.d. per frame).
    correlation = torch.corrcoef(torch.stack([error[:, 20].reshape(-1), error[:, 40].reshape(-1)]))[0, 1]
    assert abs(float(correlation) - math.sqrt(20 / 40)) < 0.08


def test_yaw_drifts_while_roll_and_pitch_stay_within_their_bound():
    n, seeds, yaw_deg, tilt_deg = 41, 400, 5.0, 0.3
    c2w, f = ring(n)  # level cameras: h1 = x (horizontal right), h2 = z (horizontal forward)
    outs = draws(c2w, f, drift_config(yaw_drift_deg=yaw_deg, tilt_deg=tilt_deg, position_drift=0.0), seeds)
    after = torch.stack([out.c2w for out in outs])  # [seeds, n, 3, 4]
    h1, h2 = c2w[:, :, 0], c2w[:, :, 2]
    z_new, x_new = after[..., :3, 2], after[..., :3, 0]
    # Heading change of the optical axis: a rotation by psi about +u takes h2 to h2 cos psi - h1 sin psi.
    yaw = torch.rad2deg(torch.atan2(-(z_new * h1).sum(-1), (z_new * h2).sum(-1)))  # [seeds, n]
    yaw_rms = yaw.square().mean(dim=0).sqrt()
    assert float(yaw[:, 0].abs().max()) < 1e-3  # no yaw at the first camera (tilt leaves ~1e-5 rad of heading)
    for k in (1, 10, 20, 40):  # RMS = yaw_deg sqrt(k / (n - 1)); 400 draws: ~3.5% sampling error
        assert abs(float(yaw_rms[k]) / (yaw_deg * math.sqrt(k / (n - 1))) - 1.0) < 0.12, k
    # Tilt: the gravity direction seen by each camera moves by pitch along h2 and by -roll along h1, never more.
    gravity = gravity_in_camera(c2w, after)  # [seeds, n, 3]
    pitch, roll = (gravity * h2).sum(-1), -(gravity * h1).sum(-1)
    bound = math.radians(tilt_deg)
    for angle in (pitch, roll):
        assert float(angle.abs().max()) <= bound + 1e-12
        assert float(angle.max()) > 0.98 * bound and float(angle.min()) < -0.98 * bound  # uniform: reaches it
        assert abs(float(angle.square().mean().sqrt()) / (bound / math.sqrt(3)) - 1.0) < 0.03
    assert float(yaw.abs().max()) > 20 * tilt_deg  # the yaw drifts far beyond the tilt bound
    # Conventions: positive pitch raises the optical axis, positive roll lowers the image's right side.
    torch.testing.assert_close(torch.asin(z_new[..., 2]), pitch, atol=1e-4, rtol=0)
    torch.testing.assert_close(torch.asin(x_new[..., 2]), -roll, atol=1e-4, rtol=0)
    rotation = after[..., :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(rotation)
    torch.testing.assert_close(rotation.transpose(-1, -2) @ rotation, eye, atol=1e-12, rtol=0)
    assert torch.all(torch.linalg.det(rotation) > 0.999999)


def test_focal_is_one_shared_factory_factor():
    n, seeds, sigma = 30, 300, 0.015
    c2w, f = ring(n, height=0.3)
    fy = f * 1.25
    outs = [drifted(c2w, f, drift_config(focal_error=sigma), s, fy) for s in range(seeds)]
    for out in outs[:20]:
        ratio = out.fx / f
        torch.testing.assert_close(ratio, ratio[0].expand(n), atol=0, rtol=1e-15)  # one factor for every image
        torch.testing.assert_close(out.fy / fy, ratio, atol=0, rtol=1e-15)
        torch.testing.assert_close(out.focal_scale, ratio, atol=0, rtol=1e-15)
    log_factor = torch.log(torch.stack([out.fx[0] for out in outs]) / 500.0)
    assert abs(float(log_factor.std()) / math.log1p(sigma) - 1.0) < 0.12
    assert abs(float(log_factor.mean())) < 4 * math.log1p(sigma) / math.sqrt(seeds)


# The committed CamP implementation's result, recorded before the drift existed: ring of 5 (radius 1, height 0.3),
# focals 500 / 625, seed 11, sigma_position = sigma_look_at = 0.05, sigma_dolly_z = 0.1, sigma_focal_length = 0.05.
CAMP_LAST_C2W = [
    [0.9462779589557815, 0.06363892869728188, -0.31703014233467225, 0.3567570742260148],
    [0.32332267464412406, -0.19993663143504967, 0.924925830254175, -1.0341465317501959],
    [-0.004524649759949021, -0.9777399604008559, -0.20977153615274502, 0.28095677130499125],
]
CAMP_FX = [589.8415236940974, 518.4175217424998, 503.39361110595746, 523.1506890890415, 529.4066818082139]
CAMP_FY = [737.3019046176217, 648.0219021781248, 629.2420138824468, 653.9383613613019, 661.7583522602674]
CAMP = {"seed": 11, "sigma_position": 0.05, "sigma_look_at": 0.05, "sigma_dolly_z": 0.1, "sigma_focal_length": 0.05}


def _ring_as_recorded() -> tuple[torch.Tensor, torch.Tensor]:
    angle = torch.linspace(0.0, 2 * math.pi, 6, dtype=torch.float64)[:-1]
    centre = torch.stack([torch.cos(angle), torch.sin(angle), torch.full_like(angle, 0.3)], -1)
    rotation = look_at_rotation(centre, torch.zeros_like(centre), UP_Z.expand(5, 3))
    return torch.cat([rotation, centre[:, :, None]], dim=-1), torch.full((5,), 500.0, dtype=torch.float64)


def test_camp_is_as_recorded_and_the_drift_draws_after_it():
    c2w, f = _ring_as_recorded()
    off = perturb_cameras(c2w, f, f * 1.25, PerturbationConfig(**CAMP))
    expected = torch.tensor(CAMP_LAST_C2W, dtype=torch.float64)
    torch.testing.assert_close(off.c2w[-1], expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(off.fx, torch.tensor(CAMP_FX, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(off.fy, torch.tensor(CAMP_FY, dtype=torch.float64), atol=1e-9, rtol=0)
    # The drift draws after CamP: with zero sizes it draws, and still returns CamP's cameras bit for bit.
    zero = DriftConfig(enabled=True, position_drift=0.0, yaw_drift_deg=0.0, tilt_deg=0.0, focal_error=0.0)
    zero_drift = perturb_with_drift(c2w, f, f * 1.25, PerturbationConfig(**CAMP), zero)
    for name in ("c2w", "fx", "fy", "focal_scale", "dolly_scale"):
        assert torch.equal(getattr(off, name), getattr(zero_drift, name)), name
    # And with its sizes on, CamP's dolly (drawn first) is unchanged while the cameras move.
    on = perturb_with_drift(c2w, f, f * 1.25, PerturbationConfig(**CAMP), DriftConfig(enabled=True))
    assert torch.equal(on.dolly_scale, off.dolly_scale)
    assert not torch.allclose(on.c2w, off.c2w)


def test_same_seed_is_bit_identical_and_seeds_differ():
    c2w, f = ring(24, height=0.3)
    drift = DriftConfig(enabled=True)
    a = perturb_with_drift(c2w, f, f, PerturbationConfig(seed=5), drift)  # CamP and drift together
    b = perturb_with_drift(c2w.clone(), f.clone(), f.clone(), PerturbationConfig(seed=5), DriftConfig(enabled=True))
    c = perturb_with_drift(c2w, f, f, PerturbationConfig(seed=6), drift)
    assert torch.equal(a.c2w, b.c2w) and torch.equal(a.fx, b.fx)
    assert not torch.allclose(a.c2w, c.c2w)
    single = ring(1, height=0.3)
    one = drifted(*single, drift_config(yaw_drift_deg=30.0))  # one camera: no walk, only tilt
    torch.testing.assert_close(one.c2w[:, :, 3], single[0][:, :, 3], atol=1e-12, rtol=0)
    assert bool(torch.isfinite(one.c2w).all())


def test_up_axis_is_the_yaw_axis():
    up_y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    c2w, f = ring(30, height=0.3, up=up_y)
    bound = math.radians(0.3)
    right = drift_config(yaw_drift_deg=10.0, up=(0.0, 2.0, 0.0))  # normalized before use
    wrong = drift_config(yaw_drift_deg=10.0)  # +z: this scene's yaw would tilt its gravity
    tilt_right = gravity_in_camera(c2w, drifted(c2w, f, right).c2w, up_y) - up_y
    tilt_wrong = gravity_in_camera(c2w, drifted(c2w, f, wrong).c2w, up_y) - up_y
    assert float(torch.linalg.norm(tilt_right, dim=-1).max()) <= math.sqrt(2) * bound + 1e-12
    assert float(torch.linalg.norm(tilt_wrong, dim=-1).max()) > 5 * bound


def test_camera_looking_along_up_is_tilted_within_the_bound():
    centre = torch.tensor([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0]], dtype=torch.float64)
    north = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(2, 3)
    rotation = look_at_rotation(centre, torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]).double(), north)
    c2w, f = torch.cat([rotation, centre[:, :, None]], dim=-1), torch.full((2,), 400.0, dtype=torch.float64)
    out = drifted(c2w, f, drift_config(tilt_deg=1.0))
    tilt = torch.linalg.norm(gravity_in_camera(c2w, out.c2w) - UP_Z, dim=-1)
    assert bool(torch.isfinite(out.c2w).all())
    assert float(tilt.max()) <= math.sqrt(2) * math.radians(1.0) + 1e-12 and float(tilt.min()) > 0


@pytest.mark.parametrize(
    ("drift", "message"),
    [
        ({"position_drift": -0.1}, r"drift\.position_drift must lie in \[0, 1\], got -0\.1"),
        ({"position_drift": float("nan")}, r"drift\.position_drift must lie in \[0, 1\], got nan"),
        ({"yaw_drift_deg": 200.0}, r"drift\.yaw_drift_deg must lie in \[0, 180\], got 200"),
        ({"tilt_deg": 20.0}, r"drift\.tilt_deg must lie in \[0, 10\], got 20"),
        ({"focal_error": 0.6}, r"drift\.focal_error must lie in \[0, 0\.5\], got 0\.6"),
        ({"up": (0.0, 0.0, 0.0)}, r"drift\.up must be 3 finite numbers of norm > 0, got \(0\.0, 0"),
        ({"up": (0.0, float("nan"), 1.0)}, r"drift\.up must be 3 finite numbers"),
        ({"up": (0.0, 1.0)}, r"drift\.up must be 3 finite numbers"),
    ],
)
def test_bad_drift_config_is_named(drift, message):
    c2w, f = ring(4)
    with pytest.raises(ValueError, match=message):
        perturb_with_drift(c2w, f, f, PerturbationConfig(), DriftConfig(enabled=True, **drift))
    with pytest.raises(ValueError, match=message):  # also when the drift is off: the config is wrong either way
        DriftConfig(enabled=False, **drift).validate()


def test_cli_names():
    """The options of the benchmarks' data parser as ns-train parses them ("--x True", not flags)."""
    import tyro

    from s2camp_bench.data_parser import BenchDataParserConfig

    args = [
        "--drift.enabled", "True", "--drift.position-drift", "0.02", "--drift.yaw-drift-deg", "2",
        "--drift.tilt-deg", "0.2", "--drift.focal-error", "0.01", "--drift.up", "0", "1", "0",
        "--perturbation.seed", "3",
    ]  # fmt: skip
    parse = tyro.conf.FlagConversionOff[BenchDataParserConfig]
    config = tyro.cli(parse, args=args)
    expected = DriftConfig(True, 0.02, 2.0, 0.2, 0.01, (0.0, 1.0, 0.0))
    assert config.drift == expected and config.perturbation.seed == 3
    assert tyro.cli(parse, args=[]).drift == DriftConfig()  # off by default
