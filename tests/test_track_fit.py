"""The track prior's anchor: the cameras that agree best with a scene's SfM tracks (``core.track_fit``), from the
core's fit through the data parser's ``track_evidence`` (COLMAP and ns-process-data layouts) to the camera
optimizer's anchor latent and proximal step."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from test_transforms_tracks import _ns_process_data_layout, _parse, perturbed_with_scene_tracks

from s2camp_ns.core.camera import Intrinsics, project, se3_exp
from s2camp_ns.core.perturbation import look_at_rotation
from s2camp_ns.core.track_fit import fit_anchor, fit_cameras_to_tracks
from s2camp_ns.core.tracks import Tracks, track_reprojection_rms

WIDTH, HEIGHT = 64, 48


def _ring(n: int, radius: float = 3.0) -> torch.Tensor:
    """OpenCV c2w of ``n`` cameras on a ring looking at the origin."""
    angle = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    eye = torch.stack([radius * angle.cos(), radius * angle.sin(), 0.5 + 0.1 * angle], dim=-1)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
    return torch.cat([look_at_rotation(eye, torch.zeros_like(eye), up), eye[:, :, None]], dim=-1)


def _intrinsics(n: int, fx: float = 60.0) -> Intrinsics:
    return Intrinsics.create(fx=[fx] * n, fy=[fx] * n, cx=[WIDTH / 2] * n, cy=[HEIGHT / 2] * n, width=[WIDTH] * n,
                             height=[HEIGHT] * n, k1=[0.01] * n)  # fmt: skip


def _observe(points: torch.Tensor, c2w: torch.Tensor, intrinsics: Intrinsics, noise_px: float = 0.0) -> Tracks:
    """Every point each camera sees inside its image, observed at its projection plus Gaussian noise."""
    generator = torch.Generator().manual_seed(1)
    image, point, pixels = [], [], []
    for i in range(c2w.shape[0]):
        local = (points - c2w[i, :, 3]) @ c2w[i, :, :3]
        uv, depth = project(local[None], intrinsics[i : i + 1])
        uv = uv[0]
        inside = (depth[0] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < WIDTH) & (uv[:, 1] > 0) & (uv[:, 1] < HEIGHT)
        seen = inside.nonzero()[:, 0]
        image.append(torch.full_like(seen, i))
        point.append(seen)
        pixels.append(uv[seen] + noise_px * torch.randn(seen.shape[0], 2, generator=generator, dtype=torch.float64))
    return Tracks(points, torch.cat(image), torch.cat(point), torch.cat(pixels))


def _points(count: int = 150) -> torch.Tensor:
    return (torch.rand(count, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5) * 1.2


def _moved(c2w: torch.Tensor, twist: torch.Tensor) -> torch.Tensor:
    """c2w exp(xi), the camera optimizer's pose update."""
    motion = se3_exp(twist)
    return torch.cat([c2w[:, :, :3] @ motion[:, :, :3], c2w[:, :, 3:] + c2w[:, :, :3] @ motion[:, :, 3:]], dim=-1)


def _perturbation(n: int) -> torch.Tensor:
    scale = torch.tensor([0.03, 0.03, 0.03, 0.01, 0.01, 0.01], dtype=torch.float64)
    return torch.randn(n, 6, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * scale


POSE_AND_INTRINSICS = tuple(range(10))  # pose, focal, principal point, skew


def test_exact_tracks_give_back_the_true_cameras_and_shared_intrinsics() -> None:
    n = 8
    truth_c2w, truth = _ring(n), _intrinsics(n)
    tracks = _observe(_points(), truth_c2w, truth)
    given_c2w = _moved(truth_c2w, _perturbation(n))
    change = torch.zeros(n, 16, dtype=torch.float64)
    change[:, 6], change[:, 7], change[:, 8] = 3.0, -1.0, 0.5  # one camera: focal +3 px, principal point (-1, 0.5)
    given = truth.with_delta(change)
    assert float(track_reprojection_rms(tracks, given_c2w, given).min()) > 0.5
    fit = fit_cameras_to_tracks(tracks, given_c2w, given, POSE_AND_INTRINSICS, torch.zeros(n, dtype=torch.long))
    torch.testing.assert_close(_moved(given_c2w, fit.deltas[:, :6]), truth_c2w, atol=1e-9, rtol=0)
    expected = torch.tensor([-3.0, 1.0, -0.5, 0.0], dtype=torch.float64).expand(n, 4)
    torch.testing.assert_close(fit.deltas[:, 6:10], expected, atol=1e-8, rtol=0)
    assert bool((fit.deltas[:, 10:] == 0).all())  # distortion was not free
    assert float(fit.rms_px.max()) < 1e-9
    assert fit.iterations <= 15  # Gauss-Newton's convergence: an approximate Jacobian would crawl


def test_noisy_tracks_leave_their_noise_as_the_rms_at_the_fit() -> None:
    n = 8
    truth_c2w, truth = _ring(n), _intrinsics(n)
    tracks = _observe(_points(400), truth_c2w, truth, noise_px=0.5)
    given = _moved(truth_c2w, 3.0 * _perturbation(n))
    fit = fit_cameras_to_tracks(tracks, given, truth, tuple(range(6)))
    # 2D Gaussian noise of 0.5 px per axis: an RMS pixel distance near 0.5 sqrt(2), a little less after the fit.
    assert float(fit.rms_px.min()) > 0.6 and float(fit.rms_px.max()) < 0.8
    assert float(fit.rms_given_px.min()) > 1.0
    fitted_error = (_moved(given, fit.deltas[:, :6]) - truth_c2w).abs().amax(dim=(1, 2))
    given_error = (given - truth_c2w).abs().amax(dim=(1, 2))
    assert bool((fitted_error < 0.3 * given_error).all())  # the noise averages out over a few hundred observations


def test_only_the_free_parameters_move_and_barely_observed_images_stay() -> None:
    n = 6
    truth_c2w, truth = _ring(n), _intrinsics(n)
    tracks = _observe(_points(), truth_c2w, truth)
    # Image 5 keeps 9 observations (below MIN_OBSERVATIONS = 10: its pose would be barely determined), image 4 none.
    keep = (tracks.image < 4) | ((tracks.image == 5) & (torch.cumsum(tracks.image == 5, dim=0) <= 9))
    tracks = Tracks(tracks.points, tracks.image[keep], tracks.point[keep], tracks.pixels[keep])
    change = torch.zeros(n, 16, dtype=torch.float64)
    change[:, 6] = 2.0
    fit = fit_cameras_to_tracks(tracks, _moved(truth_c2w, _perturbation(n)), truth.with_delta(change), tuple(range(6)))
    assert bool((fit.deltas[:, 6:] == 0).all())  # pose only: the focal error stays and shows in the RMS
    assert float(fit.rms_px[:4].min()) > 1e-3  # small: moving the camera in (a dolly) absorbs most of it
    for image in (4, 5):
        assert bool((fit.deltas[image] == 0).all()) and math.isnan(float(fit.rms_px[image]))
    assert float(fit.rms_given_px[5]) > 0.1 and math.isnan(float(fit.rms_given_px[4]))


def test_a_similarity_of_the_world_scales_only_the_translation_deltas() -> None:
    n, scale = 6, 2.5
    truth_c2w, truth = _ring(n), _intrinsics(n)
    points = _points()
    tracks = _observe(points, truth_c2w, truth)
    given = _moved(truth_c2w, _perturbation(n))
    fit = fit_cameras_to_tracks(tracks, given, truth, tuple(range(6)))
    # Rotate and scale the world (points and cameras alike).
    rotation = look_at_rotation(
        torch.tensor([[0.3, -0.2, 1.0]], dtype=torch.float64),
        torch.zeros(1, 3, dtype=torch.float64),
        torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64),
    )[0]
    moved_tracks = Tracks(scale * points @ rotation.T, tracks.image, tracks.point, tracks.pixels)
    moved_given = torch.cat([rotation @ given[:, :, :3], scale * (rotation @ given[:, :, 3:])], dim=-1)
    moved_fit = fit_cameras_to_tracks(moved_tracks, moved_given, truth, tuple(range(6)))
    torch.testing.assert_close(moved_fit.deltas[:, 3:6], fit.deltas[:, 3:6], atol=1e-9, rtol=0)
    torch.testing.assert_close(moved_fit.deltas[:, :3], scale * fit.deltas[:, :3], atol=1e-9, rtol=0)


POSE_FOCAL = tuple(range(7))
POSE_INTRINSICS_DISTORTION = (*range(10), 10, 11)  # pose, focal, principal point, skew, k1, k2


def _sfm_like(noise_px: float) -> tuple[Tracks, torch.Tensor, Intrinsics]:
    """Noisy tracks of a ring and cameras as SfM leaves them: the best fit of SfM's own model (pose and one shared
    focal length; principal point and distortion held) to those tracks."""
    n = 8
    truth_c2w, truth = _ring(n), _intrinsics(n)
    tracks = _observe(_points(400), truth_c2w, truth, noise_px=noise_px)
    shared = torch.zeros(n, dtype=torch.long)
    sfm = fit_cameras_to_tracks(tracks, truth_c2w, truth, POSE_FOCAL, shared)
    return tracks, _moved(truth_c2w, sfm.deltas[:, :6]), truth.with_delta(sfm.deltas)


def test_anchor_keeps_intrinsics_that_noisy_tracks_do_not_contradict() -> None:
    # Cameras at the optimum of SfM's model: freeing the principal point, skew and distortion lets a refit chase the
    # noise (the focal length moves with them), which the likelihood-ratio test does not take as evidence.
    tracks, c2w, intrinsics = _sfm_like(noise_px=0.5)
    shared = torch.zeros(8, dtype=torch.long)
    refit = fit_cameras_to_tracks(tracks, c2w, intrinsics, POSE_INTRINSICS_DISTORTION, shared)
    assert float(refit.deltas[:, 6:12].abs().max()) > 1e-3  # the plain refit does move the intrinsics
    anchor = fit_anchor(tracks, c2w, intrinsics, POSE_INTRINSICS_DISTORTION, shared)
    assert anchor.intrinsics_held.tolist() == [True]
    assert bool((anchor.deltas[:, 6:] == 0).all())
    poses = fit_cameras_to_tracks(tracks, c2w, intrinsics, tuple(range(6)), shared)
    torch.testing.assert_close(anchor.deltas, poses.deltas, rtol=0, atol=0)  # the poses' fit with those intrinsics
    torch.testing.assert_close(anchor.rms_px, poses.rms_px, rtol=0, atol=0)


def test_anchor_refits_intrinsics_the_tracks_contradict() -> None:
    # The same cameras with the shared focal length 6 px (10%) off: the tracks call for it. (At 1 px the dolly of
    # the pose-only fit absorbs nearly all of it at this noise: a likelihood ratio of 9.8 on 6 parameters, no call.)
    tracks, c2w, intrinsics = _sfm_like(noise_px=0.5)
    change = torch.zeros(8, 16, dtype=torch.float64)
    change[:, 6] = 6.0
    shared = torch.zeros(8, dtype=torch.long)
    anchor = fit_anchor(tracks, c2w, intrinsics.with_delta(change), POSE_INTRINSICS_DISTORTION, shared)
    assert anchor.intrinsics_held.tolist() == [False]
    assert anchor.deltas[:, 6].tolist() == pytest.approx([-6.0] * 8, abs=0.5)
    # Per-image intrinsics (one physical camera each, 400 observations) decide per camera: only camera 3's focal
    # length is off, by 15 px.
    per_image = torch.zeros(8, 16, dtype=torch.float64)
    per_image[3, 6] = 15.0
    anchor = fit_anchor(tracks, c2w, intrinsics.with_delta(per_image), POSE_INTRINSICS_DISTORTION)
    assert anchor.intrinsics_held.tolist() == [True, True, True, False, True, True, True, True]
    # One image's focal length trades with its free k1, k2 on this small image: its fit scatters by about a pixel
    # with the noise (plain least squares and the robust fit alike), far below the 15 px it corrects.
    assert anchor.deltas[3, 6].item() == pytest.approx(-15.0, abs=1.0)
    assert bool((anchor.deltas[torch.arange(8) != 3, 6:] == 0).all())


def _with_wrong_matches(tracks: Tracks, share: float = 0.02) -> Tracks:
    """``tracks`` with a share of the observations moved 50-200 px in random directions (wrong matches)."""
    generator = torch.Generator().manual_seed(7)
    bad = torch.randperm(tracks.image.shape[0], generator=generator)[: int(share * tracks.image.shape[0])]
    angle = 2 * math.pi * torch.rand(bad.shape[0], generator=generator, dtype=torch.float64)
    size = 50.0 + 150.0 * torch.rand(bad.shape[0], generator=generator, dtype=torch.float64)
    pixels = tracks.pixels.clone()
    pixels[bad] += size[:, None] * torch.stack([angle.cos(), angle.sin()], dim=-1)
    return Tracks(tracks.points, tracks.image, tracks.point, pixels)


def test_anchor_decides_on_the_robust_cost_with_wrong_matches_among_the_tracks() -> None:
    # 2% of the matches 50-200 px off: the plain cost's noise variance grows a hundredfold and a plain test would keep
    # a focal length 6 px off; the robust one still keeps the SfM intrinsics and refits the wrong ones.
    tracks, c2w, intrinsics = _sfm_like(noise_px=0.5)
    tracks, shared = _with_wrong_matches(tracks), torch.zeros(8, dtype=torch.long)
    anchor = fit_anchor(tracks, c2w, intrinsics, POSE_INTRINSICS_DISTORTION, shared)
    assert anchor.intrinsics_held.tolist() == [True]
    change = torch.zeros(8, 16, dtype=torch.float64)
    change[:, 6] = 6.0
    anchor = fit_anchor(tracks, c2w, intrinsics.with_delta(change), POSE_INTRINSICS_DISTORTION, shared)
    assert anchor.intrinsics_held.tolist() == [False]
    assert anchor.deltas[:, 6].tolist() == pytest.approx([-6.0] * 8, abs=0.5)
    assert float(anchor.rms_px.min()) > 5.0  # the RMS stays plain: the wrong matches count with their square


def test_observations_count_each_images_valid_tracks() -> None:
    n = 4
    truth_c2w, truth = _ring(n), _intrinsics(n)
    tracks = _observe(_points(), truth_c2w, truth)
    fit = fit_cameras_to_tracks(tracks, truth_c2w, truth, tuple(range(6)))
    # Every generated observation lies inside its image, in front of the camera: all are valid.
    assert fit.observations.tolist() == torch.bincount(tracks.image, minlength=n).double().tolist()
    assert float(fit.observations.min()) >= 10


def test_fit_refuses_a_wrong_free_mask_and_camera_count() -> None:
    n = 3
    tracks = _observe(_points(), _ring(n), _intrinsics(n))
    with pytest.raises(ValueError, match=r"free must mask the 16 camera parameters, got shape \(10,\)"):
        fit_cameras_to_tracks(tracks, _ring(n), _intrinsics(n), torch.ones(10, dtype=torch.bool))
    with pytest.raises(ValueError, match="camera_of_image must hold one camera per image"):
        fit_cameras_to_tracks(tracks, _ring(n), _intrinsics(n), (0,), torch.zeros(2, dtype=torch.long))


# ------------------------------------------------------------------------------- data parser and camera optimizer
def _optimizer_from(outputs, **overrides):
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig

    config = S2CampCameraOptimizerConfig(track_prior=True, **overrides)
    optimizer = config.setup(num_cameras=outputs.cameras.shape[0], device="cpu")
    optimizer.refiner.set_camera_groups(outputs.metadata["camera_ids"])
    optimizer.set_train_cameras(outputs.cameras, points=outputs.metadata.get("points3D_xyz"))
    optimizer.set_track_prior(outputs.metadata["track_rms_px"], outputs.metadata["track_evidence"])
    return optimizer


def _assert_anchor_is_the_truth(outputs, optimizer) -> None:
    reference = outputs.metadata["reference_cameras"]
    pose, intrinsics = optimizer.refiner.prior_anchor_latents()
    with torch.no_grad():
        optimizer.refiner.whitened_delta.copy_(pose)
        if intrinsics is not None:
            optimizer.refiner.whitened_intrinsics.copy_(intrinsics)
    # The generated tracks are exact: the anchor is the true camera, up to the float32 storage of the cameras.
    refined = optimizer.refiner.refined_c2w(opengl=True)
    torch.testing.assert_close(refined, reference.camera_to_worlds.to(torch.float64), atol=2e-5, rtol=0)
    torch.testing.assert_close(
        optimizer.refiner.refined_intrinsics().fx, reference.fx[:, 0].double(), atol=1e-3, rtol=0
    )


def test_colmap_scene_anchor_is_the_true_camera_for_perturbed_cameras(tiny_scene: Path) -> None:
    outputs = perturbed_with_scene_tracks(tiny_scene)
    optimizer = _optimizer_from(outputs)
    assert float(outputs.metadata["track_rms_px"].min()) > 0.1  # the given cameras disagree with their tracks
    assert float(optimizer.refiner.prior_radius.max()) < 1e-6  # the anchor agrees: exact tracks, radius ~0
    _assert_anchor_is_the_truth(outputs, optimizer)


def test_ns_process_data_anchor_is_the_true_camera_too(tiny_scene: Path, tmp_path: Path) -> None:
    outputs = perturbed_with_scene_tracks(_ns_process_data_layout(tiny_scene, tmp_path / "ns"))
    assert outputs.metadata["source_format"] == "nerfstudio"
    _assert_anchor_is_the_truth(outputs, _optimizer_from(outputs))


def test_per_image_intrinsics_anchor_and_the_accurate_start_anchor_at_zero(tiny_scene: Path) -> None:
    perturbed = perturbed_with_scene_tracks(tiny_scene)
    _assert_anchor_is_the_truth(perturbed, _optimizer_from(perturbed, intrinsics="per-image"))
    accurate = _parse(tiny_scene)
    optimizer = _optimizer_from(accurate)
    assert float(optimizer.refiner.prior_anchor.abs().max()) < 1e-5


def test_proximal_step_pulls_towards_the_anchor_not_the_given_camera(tiny_scene: Path) -> None:
    outputs = perturbed_with_scene_tracks(tiny_scene)
    optimizer = _optimizer_from(outputs)
    pose, intrinsics = optimizer.refiner.prior_anchor_latents()
    torch.testing.assert_close(optimizer.refiner.whitened_delta.double(), pose, rtol=1e-6, atol=1e-9)  # started there
    with torch.no_grad():  # back at the given cameras
        for latent in optimizer.parameters():
            latent.zero_()
    optimizer.refiner.prior_radius.fill_(0.01)  # a finite radius: one step closes lr / (r + lr) of the gap
    optimizer.refiner.prior_radius_intrinsics.fill_(0.01)
    optimizer.refiner.apply_track_prior(lr=1e-3)
    torch.testing.assert_close(optimizer.refiner.whitened_delta.double(), pose * (1e-3 / 0.011), rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(
        optimizer.refiner.whitened_intrinsics.double(), intrinsics * (1e-3 / 0.011), rtol=1e-5, atol=1e-9
    )


def test_common_rotation_removal_keeps_the_rotation_the_anchors_share(tiny_scene: Path) -> None:
    # The anchors' own corrections share a rotation (their mean is not zero): with the tracks fixing the world it is
    # no gauge. At the anchor the removal must change nothing; without the prior it removes that mean.
    outputs = perturbed_with_scene_tracks(tiny_scene)
    optimizer = _optimizer_from(outputs, fix_common_rotation=True)
    pose, intrinsics = optimizer.refiner.prior_anchor_latents()
    with torch.no_grad():
        optimizer.refiner.whitened_delta.copy_(pose)
        optimizer.refiner.whitened_intrinsics.copy_(intrinsics)
    shared = optimizer.refiner.deltas()[:, 3:6].mean(dim=0)
    assert float(shared.abs().max()) > 1e-4  # the anchors do share a rotation
    optimizer.refiner.remove_common_motion()
    reference = outputs.metadata["reference_cameras"].camera_to_worlds.double()
    torch.testing.assert_close(optimizer.refiner.refined_c2w(opengl=True), reference, atol=2e-5, rtol=0)
    optimizer.refiner.has_track_prior = False  # as without tracks: the shared rotation is removed
    optimizer.refiner.remove_common_motion()
    assert float(optimizer.refiner.deltas()[:, 3:6].mean(dim=0).abs().max()) < 1e-9
