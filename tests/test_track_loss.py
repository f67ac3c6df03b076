"""The tracks as a loss term (``core.track_loss``): its cost, its noise estimate, its units and its weight."""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.track_loss import noise_variance, photometric_weight, refine_points, track_cost, track_term
from s2camp_ns.core.tracks import Tracks


def _one_point_scene(world_scale: float = 1.0, offset_px: float = 0.0):
    """One camera at the origin looking down +z (OpenCV), f = 100 px, centre (50, 40); one point on the axis at
    z = 4 observed at the centre shifted right by ``offset_px``."""
    intrinsics = Intrinsics.create(fx=100.0, fy=100.0, cx=50.0, cy=40.0, width=100.0, height=80.0)
    c2w = torch.eye(3, 4, dtype=torch.float64)[None]
    tracks = Tracks(
        points=torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64),
        image=torch.tensor([0]),
        point=torch.tensor([0]),
        pixels=torch.tensor([[50.0 + offset_px, 40.0]], dtype=torch.float64),
    )
    return TrackEvidence(tracks=tracks, c2w=c2w, world_scale=world_scale), intrinsics


def test_a_translation_costs_the_cauchy_loss_of_its_pixel_shift_in_the_tracks_world() -> None:
    # Moving the camera by t along its x axis moves the point to x = -t in its frame: u = 50 - 100 t / 4.
    # In a training frame twice the tracks' world the same move is a delta of 2 t.
    evidence, intrinsics = _one_point_scene(world_scale=2.0)
    term = track_term(evidence, intrinsics, torch.zeros(1, 16, dtype=torch.float64))
    deltas = torch.zeros(1, 16, dtype=torch.float64)
    deltas[0, 0] = 2.0 * 0.02  # t = 0.02 in the tracks' world: a shift of 0.5 px
    assert float(track_cost(term, deltas, intrinsics)) == pytest.approx(math.log1p(0.5**2), rel=1e-9)
    deltas[0, 0] = 2.0 * 0.4  # 10 px: the Cauchy cost grows logarithmically, not with the square
    assert float(track_cost(term, deltas, intrinsics)) == pytest.approx(math.log1p(100.0), rel=1e-9)


def test_the_cost_pulls_the_camera_to_where_its_tracks_put_it() -> None:
    evidence, intrinsics = _one_point_scene(offset_px=-2.0)  # the point is seen 2 px left: camera at t = 0.08
    term = track_term(evidence, intrinsics, torch.zeros(1, 16, dtype=torch.float64))
    shift = torch.zeros(1, dtype=torch.float64, requires_grad=True)  # the x translation alone
    optimizer = torch.optim.SGD([shift], lr=1e-4)
    for _ in range(300):
        optimizer.zero_grad()
        deltas = torch.cat([shift, torch.zeros(15, dtype=torch.float64)])[None]
        track_cost(term, deltas, intrinsics).backward()
        optimizer.step()
    assert float(shift.detach()) == pytest.approx(0.08, abs=1e-4)


def test_noise_variance_is_the_median_squared_distance_over_that_of_a_chi_square_with_two_degrees() -> None:
    # Isotropic 2D Gaussian noise of sigma 0.7 px per axis, 2% of the observations gross mismatches (the mean of s
    # would be 3600 times too large; the median moves by 3%).
    generator = torch.Generator().manual_seed(0)
    residual = 0.7 * torch.randn(20000, 2, generator=generator, dtype=torch.float64)
    residual[:400] += 300.0
    assert noise_variance(residual.square().sum(dim=-1)) == pytest.approx(0.49, rel=0.05)
    with pytest.raises(ValueError, match="at least one valid track observation"):
        noise_variance(torch.zeros(0, dtype=torch.float64))


def test_observations_behind_their_camera_are_left_out() -> None:
    evidence, intrinsics = _one_point_scene()
    behind = Tracks(
        points=torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, -4.0]], dtype=torch.float64),
        image=torch.tensor([0, 0]),
        point=torch.tensor([0, 1]),
        pixels=torch.tensor([[50.0, 40.0], [50.0, 40.0]], dtype=torch.float64),
    )
    term = track_term(TrackEvidence(behind, evidence.c2w, 1.0), intrinsics, torch.zeros(1, 16, dtype=torch.float64))
    assert term.image.tolist() == [0]


def test_the_weight_is_the_photometric_variance_over_three_pixels_and_the_track_variance() -> None:
    # sigma_c^2 = 0.003 per channel over 1000 pixels, sigma_t^2 = 0.25 px^2: 0.003 / (3 * 1000 * 0.25).
    assert float(photometric_weight(torch.tensor(0.003), 1000, 0.25)) == pytest.approx(4e-6, rel=1e-12)


def test_the_optimizers_track_loss_alone_brings_perturbed_cameras_to_their_anchor(tiny_scene) -> None:
    # The adapter end to end: the data parser's evidence (a similarity away from the training frame), shared
    # intrinsics, Adam on the whitened latent with the track loss alone: the cameras reach where the tracks put them.
    from test_track_fit import _optimizer_from
    from test_transforms_tracks import perturbed_with_scene_tracks

    optimizer = _optimizer_from(perturbed_with_scene_tracks(tiny_scene), track_loss=True)
    assert optimizer.get_loss_dict({}) is None  # no photometric loss, no track term (the splat models' case)
    pose, intrinsics = optimizer.prior_anchor_latents()
    adam = torch.optim.Adam(list(optimizer.parameters()), lr=2e-3)
    for step in range(600):
        for group in adam.param_groups:
            group["lr"] = 2e-3 if step < 400 else 2e-4
        adam.zero_grad()
        losses = {"rgb_loss": torch.tensor(0.01)}
        optimizer.get_loss_dict(losses)
        losses["track_loss"].backward()
        adam.step()
    torch.testing.assert_close(optimizer.whitened_delta.double(), pose, atol=2e-4, rtol=0)
    torch.testing.assert_close(optimizer.whitened_intrinsics.double(), intrinsics, atol=2e-4, rtol=0)


def test_the_intrinsics_only_prior_moves_the_shared_intrinsics_latent_and_no_pose(tiny_scene) -> None:
    # Benchmark candidate (``track_prior_intrinsics_only``): the proximal step on the per-camera intrinsics only.
    from test_track_fit import _optimizer_from
    from test_transforms_tracks import perturbed_with_scene_tracks

    optimizer = _optimizer_from(perturbed_with_scene_tracks(tiny_scene), track_prior_intrinsics_only=True)
    _, intrinsics = optimizer.prior_anchor_latents()
    with torch.no_grad():  # back at the given cameras (every camera with tracks starts at its anchor)
        for latent in optimizer.parameters():
            latent.zero_()
    pose_before = optimizer.whitened_delta.detach().clone()
    optimizer.prior_radius.fill_(0.01)
    optimizer.prior_radius_intrinsics.fill_(0.01)
    optimizer.apply_track_prior(lr=1e-3)
    assert torch.equal(optimizer.whitened_delta.detach(), pose_before)
    torch.testing.assert_close(
        optimizer.whitened_intrinsics.double(), intrinsics * (1e-3 / 0.011), rtol=1e-5, atol=1e-9
    )


def test_free_points_step_to_where_their_observations_meet() -> None:
    # Two cameras 1 unit apart along x, both looking down +z; the point (0.2, -0.1, 4) seen exactly by both. Started
    # 0.3 units off, a few robust Gauss-Newton steps bring it back to (0.2, -0.1, 4) (each step solves the point's
    # 3 x 3 normal equations; the Cauchy weights at 1 px scale need more than one step from tens of pixels off).
    intrinsics = Intrinsics.create(fx=100.0, fy=100.0, cx=50.0, cy=40.0, width=100.0, height=80.0)
    intrinsics = intrinsics.to(dtype=torch.float64)[torch.tensor([0, 0])]
    c2w = torch.eye(3, 4, dtype=torch.float64)[None].repeat(2, 1, 1)
    c2w[1, 0, 3] = 1.0
    truth = torch.tensor([0.2, -0.1, 4.0], dtype=torch.float64)
    pixels = torch.tensor([[50.0 + 100 * 0.2 / 4, 40.0 - 100 * 0.1 / 4], [50.0 - 100 * 0.8 / 4, 40.0 - 100 * 0.1 / 4]])
    tracks = Tracks(
        points=(truth + torch.tensor([0.3, 0.2, -0.3], dtype=torch.float64))[None],
        image=torch.tensor([0, 1]),
        point=torch.tensor([0, 0]),
        pixels=pixels.to(torch.float64),
    )
    evidence = TrackEvidence(tracks=tracks, c2w=c2w, world_scale=1.0)
    deltas = torch.zeros(2, 16, dtype=torch.float64)
    term = track_term(evidence, intrinsics, deltas, points_free=True)
    points = term.points
    for _ in range(30):
        points = refine_points(term, points, deltas, intrinsics)
    assert torch.allclose(points[0], truth, atol=1e-6)
    assert float(track_cost(term, deltas, intrinsics, points)) < 1e-9


def test_splatfactos_l1_loss_weighs_the_tracks_half_and_free_points_move_with_the_cameras(tiny_scene) -> None:
    # splatfacto's main_loss is mostly L1: its Laplace likelihood gives half eq. (1)'s weight for the same running
    # loss (camera_optimizer.get_loss_dict). With the points free, every call steps the points towards their optimum
    # at the current (perturbed) cameras, and the term stays differentiable in the cameras' latent.
    from test_track_fit import _optimizer_from
    from test_transforms_tracks import perturbed_with_scene_tracks

    evidence = perturbed_with_scene_tracks(tiny_scene)
    nerfacto, splat = ({"rgb_loss": torch.tensor(0.01)}, {"main_loss": torch.tensor(0.01)})
    _optimizer_from(evidence, track_loss=True).get_loss_dict(nerfacto)
    _optimizer_from(evidence, track_loss=True).get_loss_dict(splat)
    assert float(splat["track_loss"]) == pytest.approx(0.5 * float(nerfacto["track_loss"]), rel=1e-6)

    free = _optimizer_from(evidence, track_loss=True, track_loss_points_free=True)
    start = free.refiner.track_term.points.clone()
    losses = {"rgb_loss": torch.tensor(0.01)}
    free.get_loss_dict(losses)
    assert float((free.refiner._track_points - start).norm(dim=-1).max()) > 1e-6
    losses["track_loss"].backward()
    assert float(free.whitened_delta.grad.abs().max()) > 0.0
