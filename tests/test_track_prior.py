"""The track prior: reprojection error of SfM tracks under the given cameras (``core.tracks``), its reading from a
COLMAP model, the data parser's ``track_rms_px`` and the camera optimizer's proximal step."""

from __future__ import annotations

import math

import numpy as np
import pycolmap
import pytest
import torch
from test_camera_optimizer_shared import make_optimizer
from test_transforms_tracks import perturbed_track_rms

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.tracks import Tracks, track_reprojection_rms

IDENTITY_C2W = torch.cat([torch.eye(3, dtype=torch.float64), torch.zeros(3, 1, dtype=torch.float64)], dim=1)


def _pinhole(n: int) -> Intrinsics:
    return Intrinsics.create(fx=[100.0] * n, fy=[100.0] * n, cx=[50.0] * n, cy=[40.0] * n, width=[100] * n,
                             height=[80] * n, dtype=torch.float64)  # fmt: skip


def test_rms_per_camera_from_hand_projected_points() -> None:
    # Camera 0 at the origin looking down +z: (0.1, 0, 1) projects to (100 * 0.1 + 50, 40) = (60, 40) and (0, 0.2, 2)
    # to (50, 100 * 0.1 + 40) = (50, 50). Observed 3-4-5 px and 0 px off: RMS sqrt(25 / 2). Camera 1 is camera 0
    # moved 1 unit along +x: the first point then lies at x = -0.9, u = -40; observed at u = -40 + 6: RMS 6. Camera 2
    # observes only a point behind it: left out, NaN.
    points = torch.tensor([[0.1, 0.0, 1.0], [0.0, 0.2, 2.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    tracks = Tracks(
        points=points,
        image=torch.tensor([0, 0, 1, 2]),
        point=torch.tensor([0, 1, 0, 2]),
        pixels=torch.tensor([[63.0, 44.0], [50.0, 50.0], [-34.0, 40.0], [50.0, 40.0]], dtype=torch.float64),
    )
    c2w = IDENTITY_C2W.expand(3, 3, 4).clone()
    c2w[1, 0, 3] = 1.0
    rms = track_reprojection_rms(tracks, c2w, _pinhole(3))
    assert rms[0].item() == pytest.approx(math.sqrt(25.0 / 2.0), rel=1e-12)
    assert rms[1].item() == pytest.approx(6.0, rel=1e-12)
    assert math.isnan(rms[2].item())


def test_rms_is_unchanged_by_a_similarity_of_points_and_cameras() -> None:
    generator = torch.Generator().manual_seed(0)
    points = torch.randn(20, 3, generator=generator, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, 3.0])
    image = torch.arange(40) % 2
    point = torch.arange(40) % 20
    c2w = IDENTITY_C2W.expand(2, 3, 4).clone()
    c2w[1, :, 3] = torch.tensor([0.2, -0.1, 0.1])
    pixels = torch.rand(40, 2, generator=generator, dtype=torch.float64) * 80.0
    before = track_reprojection_rms(Tracks(points, image, point, pixels), c2w, _pinhole(2))
    angle = 0.3
    rotation = torch.tensor([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0],
                             [0.0, 0.0, 1.0]], dtype=torch.float64)  # fmt: skip
    scale, shift = 2.5, torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    moved_c2w = torch.cat([rotation @ c2w[:, :, :3], (scale * c2w[:, :, 3] @ rotation.T + shift)[:, :, None]], -1)
    moved_points = scale * points @ rotation.T + shift
    after = track_reprojection_rms(Tracks(moved_points, image, point, pixels), moved_c2w, _pinhole(2))
    assert torch.allclose(before, after, rtol=1e-10, atol=0.0)
    assert bool((before > 1.0).all())  # the observations are random: far from the projections


def test_tracks_indexing_out_of_range_is_refused_by_name() -> None:
    tracks = Tracks(torch.zeros(2, 3), torch.tensor([0, 3]), torch.tensor([0, 1]), torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"tracks.image must index the 2 cameras, got values in \[0, 3\]"):
        track_reprojection_rms(tracks, IDENTITY_C2W.expand(2, 3, 4), _pinhole(2))


def _tiny_model(folder, observations: list[tuple[str, list[tuple[float, float, int]]]], points: dict[int, list]):
    """A COLMAP model with one PINHOLE camera, images named by ``observations`` (pixel x, y, index of the observed
    point in ``points`` or -1), written the way ``make_scene`` writes its model."""
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="PINHOLE", width=100, height=80, params=[100, 100, 50, 40], camera_id=1)
    reconstruction.add_camera_with_trivial_rig(camera)
    tracks: dict[int, list] = {index: [] for index in points}
    for image_id, (name, observed) in enumerate(observations, start=1):
        keypoints = np.array([[x, y] for x, y, _ in observed], dtype=np.float64)
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=image_id)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d())
        for keypoint, (_, _, index) in enumerate(observed):
            if index >= 0:
                tracks[index].append(pycolmap.TrackElement(image_id, keypoint))
    for index, xyz in points.items():
        colour = np.zeros(3, np.uint8)
        reconstruction.add_point3D(np.array(xyz, dtype=np.float64), pycolmap.Track(tracks[index]), colour)
    folder.mkdir(parents=True)
    reconstruction.write_binary(str(folder))
    for extra in ("rigs.bin", "frames.bin"):
        (folder / extra).unlink(missing_ok=True)
    return folder


def test_read_colmap_tracks_follows_the_requested_names_and_image_size(tmp_path) -> None:
    from s2camp_ns.tracks.colmap_tracks import read_colmap_tracks

    model = _tiny_model(
        tmp_path / "sparse",
        [("a.png", [(10.0, 20.0, 1), (30.0, 40.0, -1)]), ("b.png", [(50.0, 60.0, 2), (70.0, 8.0, 1)])],
        {1: [0.0, 0.0, 1.0], 2: [0.1, 0.0, 1.0]},
    )
    # The model's camera is 100 x 80; images of 50 x 20 halve u and quarter v.
    tracks = read_colmap_tracks(model, ["b.png", "a.png"], image_size=torch.tensor([[50, 20], [50, 20]]))
    assert tracks.image.tolist() == [0, 0, 1]  # b's two tracked points, then a's one (its -1 is not a track)
    rows = tracks.point.tolist()
    assert tracks.points[rows].tolist() == [[0.1, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    assert tracks.pixels.tolist() == [[25.0, 15.0], [35.0, 2.0], [5.0, 5.0]]
    assert read_colmap_tracks(model, ["a.png"]).pixels.tolist() == [[10.0, 20.0]]  # the model's own pixels
    with pytest.raises(ValueError, match=r"holds no image named 'c.png'"):
        read_colmap_tracks(model, ["c.png"])


def test_data_parser_measures_exact_tracks_at_zero_and_moved_cameras_above(tiny_scene) -> None:
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    accurate = S2CampDataParserConfig(data=tiny_scene).setup().get_dataparser_outputs("train")
    rms = accurate.metadata["track_rms_px"]
    assert rms.shape == (accurate.cameras.shape[0],)
    # The generated tracks are the exact projections of the generated points (float32 storage of the poses).
    assert float(rms.max()) < 1e-3
    assert float(perturbed_track_rms(tiny_scene).min()) > 0.1
    off = S2CampDataParserConfig(data=tiny_scene, tracks=False).setup().get_dataparser_outputs("train")
    assert "track_rms_px" not in off.metadata


def test_prior_step_shrinks_each_latent_by_its_radius_and_leaves_untracked_images() -> None:
    optimizer = make_optimizer(track_prior=True)  # 4 images of width 64, two physical cameras: images 0, 2 and 1, 3
    optimizer.set_track_prior(torch.tensor([0.64, 6.4, float("nan"), 1.28]))
    with torch.no_grad():
        optimizer.refiner.whitened_delta.fill_(1.0)
        optimizer.refiner.whitened_intrinsics.fill_(1.0)
    optimizer.refiner.apply_track_prior(lr=1e-3)
    # Errors in whitened units 0.01, 0.1, none, 0.02; without observation counts each image counts once, so the poses'
    # radii are the standard errors r / sqrt(2); factor 1 / (1 + lr / r) towards the anchor (zero: the given cameras).
    expected = [1 / (1 + 1e-3 * math.sqrt(2) / r) if r else 1.0 for r in (0.01, 0.1, None, 0.02)]
    assert optimizer.refiner.whitened_delta[:, 0].tolist() == pytest.approx(expected, rel=1e-6)
    assert bool(
        (optimizer.refiner.whitened_delta == optimizer.refiner.whitened_delta[:, :1]).all()
    )  # every coordinate alike
    # Shared intrinsics: the standard error r / sqrt(2 O) of a fit to O observations of pooled RMS r. Without the
    # observation counts (track_rms_px alone) each image counts once. Camera A (images 0 and 2): only image 0 has
    # tracks, 0.01 / sqrt(2); camera B: images 1 and 3, radii 0.1 and 0.02 pooled over 2 observations.
    radius_b = math.sqrt((0.1**2 + 0.02**2) / 2) / math.sqrt(2 * 2)
    shared = [1 / (1 + 1e-3 / r) for r in (0.01 / math.sqrt(2), radius_b)]
    labels = optimizer.refiner.camera_of_image.tolist()
    assert optimizer.refiner.whitened_intrinsics[labels[0], 0].item() == pytest.approx(shared[0], rel=1e-6)
    assert optimizer.refiner.whitened_intrinsics[labels[1], 0].item() == pytest.approx(shared[1], rel=1e-6)


def test_shared_intrinsics_radius_is_the_standard_error_of_every_observation(monkeypatch) -> None:
    # The anchor's fit (stubbed: its RMS and observation counts per image) sets the radii: each image's pose the
    # standard error of its own fit, r_i / sqrt(2 O_i), each physical camera's intrinsics that of the pooled fit,
    # sqrt(sum O_i r_i^2) / (sqrt(2) sum O_i). Camera A holds images 0 and 2, camera B images 1 and 3
    # (``make_optimizer``), width 64.
    import s2camp_ns.camera_optimizer as module
    from s2camp_ns.core.track_fit import TrackEvidence, TrackFit

    rms = torch.tensor([0.64, 6.4, 1.28, 3.2], dtype=torch.float64)
    observations = torch.tensor([100.0, 300.0, 50.0, 20.0], dtype=torch.float64)
    fit = TrackFit(torch.zeros(4, 16, dtype=torch.float64), rms, rms, 1, observations, torch.tensor([True, True]))
    monkeypatch.setattr(module, "fit_anchor", lambda *args, **kwargs: fit)
    optimizer = make_optimizer(track_prior=True)
    index = torch.zeros(1, dtype=torch.long)
    tracks = Tracks(torch.zeros(1, 3), index, index, torch.zeros(1, 2))
    evidence = TrackEvidence(tracks, IDENTITY_C2W.expand(4, 3, 4), 1.0)
    optimizer.set_track_prior(None, evidence)
    expected = [r / math.sqrt(2 * o) for r, o in zip((0.01, 0.1, 0.02, 0.05), (100, 300, 50, 20), strict=True)]
    assert optimizer.refiner.prior_radius.tolist() == pytest.approx(expected, rel=1e-12)
    camera_a = math.sqrt(100 * 0.01**2 + 50 * 0.02**2) / (math.sqrt(2) * 150)
    camera_b = math.sqrt(300 * 0.1**2 + 20 * 0.05**2) / (math.sqrt(2) * 320)
    labels = optimizer.refiner.camera_of_image.tolist()
    assert optimizer.refiner.prior_radius_intrinsics[labels[0]].item() == pytest.approx(camera_a, rel=1e-12)
    assert optimizer.refiner.prior_radius_intrinsics[labels[1]].item() == pytest.approx(camera_b, rel=1e-12)


def test_prior_off_or_without_tracks_changes_nothing() -> None:
    # Off; on without tracks.
    off = make_optimizer(track_prior=False)
    for optimizer, rms in ((off, torch.full((4,), 0.5)), (make_optimizer(track_prior=True), None)):
        with torch.no_grad():
            optimizer.refiner.whitened_delta.fill_(1.0)
        optimizer.set_track_prior(rms)
        optimizer.refiner.apply_track_prior(lr=1e-2)
        assert bool((optimizer.refiner.whitened_delta == 1.0).all())


def test_prior_refuses_wrong_sizes_and_negative_errors() -> None:
    optimizer = make_optimizer(track_prior=True)
    with pytest.raises(ValueError, match="track_rms_px must hold 4 values"):
        optimizer.set_track_prior(torch.ones(3))
    with pytest.raises(ValueError, match=r"track_rms_px must be >= 0 \(pixels\), got minimum -1"):
        optimizer.set_track_prior(torch.tensor([1.0, -1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match=r"track_observations must hold 4 counts >= 0 .* got 3 with minimum 5"):
        optimizer.set_track_prior(torch.ones(4), track_observations=torch.full((3,), 5.0))


@pytest.mark.parametrize("noise", [False, True])
def test_adam_with_the_prior_settles_within_the_radius(noise: bool) -> None:
    # A gradient of constant sign: Adam's |m / sqrt(v)| -> 1, every coordinate settles at r. Pure noise of the same
    # size: a fraction of r (Adam's |m / sqrt(v)| is about 0.23 for beta1 0.9).
    optimizer = make_optimizer(parameters="pose", track_prior=True)
    # 0.05 in whitened units (width 64) from 2 observations each: radius 0.05 / sqrt(4) = 0.025, far above lr.
    optimizer.set_track_prior(torch.full((4,), 3.2), track_observations=torch.full((4,), 2.0))
    radius = 0.05 / 2.0
    adam = torch.optim.Adam([optimizer.refiner.whitened_delta], lr=1e-3)
    generator = torch.Generator().manual_seed(0)
    for _ in range(3000):
        adam.zero_grad()
        gradient = torch.randn(4, 6, generator=generator) if noise else -torch.ones(4, 6)
        optimizer.refiner.whitened_delta.grad = gradient
        adam.step()
        optimizer.refiner.apply_track_prior(lr=1e-3)
    latent = optimizer.refiner.whitened_delta.detach()
    if noise:
        assert float(latent.abs().max()) < 0.5 * radius
        assert float(latent.abs().max()) > 0.02 * radius  # noise does move it: the bound above is not vacuous
    else:
        assert latent.flatten().tolist() == pytest.approx([radius] * 24, rel=0.05)


def test_perturbed_cameras_never_get_the_tracks_of_the_unperturbed_ones(tiny_scene, monkeypatch, capsys) -> None:
    """The scene's tracks were made with the true cameras: a prior on them would lead perturbed cameras back to the
    reference. Perturbed cameras get tracks made from the images with the perturbed cameras, or none, and the log
    says which."""
    import s2camp_ns.tracks.track_evidence as track_evidence
    from s2camp_ns.data.dataparser import S2CampDataParserConfig
    from s2camp_ns.tracks.image_tracks import ImageTracks

    asked = []

    def fake_image_tracks(given, image_root, cache, **kwargs):
        asked.append(given)
        return ImageTracks(None, reason="not built in this test")

    monkeypatch.setattr(track_evidence, "image_tracks", fake_image_tracks)
    monkeypatch.setattr(track_evidence, "_SHOWN", set())  # the notes are shown once per process: earlier tests saw them
    config = S2CampDataParserConfig(data=tiny_scene, image_tracks="never")
    config.perturbation.enabled = True
    capsys.readouterr()
    outputs = config.setup().get_dataparser_outputs("train")
    assert "track_evidence" not in outputs.metadata and "track_rms_px" not in outputs.metadata
    assert not asked
    err = " ".join(capsys.readouterr().err.split())
    assert "Perturbed cameras: the scene's own tracks were made with the unperturbed cameras and are not used" in err
    assert "the track prior gets no track prior (image_tracks never)" in err

    config.image_tracks = "auto"  # the default: tracks made from the images, with the perturbed cameras
    outputs = config.setup().get_dataparser_outputs("train")
    assert "track_evidence" not in outputs.metadata  # the fake built none
    (given,) = asked
    names = outputs.metadata["image_names"]
    by_name = {image.name: image for image in given.images.values()}
    centres = torch.tensor(np.stack([by_name[name].projection_center() for name in names]))
    # The parser's cameras (perturbed) in COLMAP's world are the ones handed to the image tracks.
    from s2camp_ns.data.colmap_world import c2w_to_colmap_world

    scale = float(outputs.dataparser_scale)
    perturbed = c2w_to_colmap_world(outputs.cameras.camera_to_worlds, outputs.dataparser_transform, scale)
    torch.testing.assert_close(centres, perturbed[:, :, 3].double(), atol=1e-5, rtol=0.0)
    unperturbed = S2CampDataParserConfig(data=tiny_scene, image_tracks="never").setup()
    reference = unperturbed.get_dataparser_outputs("train").cameras.camera_to_worlds
    assert float((reference - outputs.cameras.camera_to_worlds).abs().max()) > 1e-3  # they were perturbed


def _moved_cameras_with_exact_tracks(scene, **optimizer_options):
    """The scene's training cameras moved by CamP's perturbation outside the data parser (which never gives perturbed
    cameras these tracks), an S2CamP optimizer on them with the exact tracks' prior, and the true cameras."""
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
    from s2camp_ns.core.perturbation import PerturbationConfig
    from s2camp_ns.data.camera_perturbation import perturb_nerfstudio_cameras
    from s2camp_ns.data.dataparser import S2CampDataParserConfig
    from s2camp_ns.data.scene_formats import detect_format
    from s2camp_ns.tracks.track_evidence import colmap_track_evidence

    config = S2CampDataParserConfig(data=scene, image_tracks="never")
    outputs = config.setup().get_dataparser_outputs("train")
    truth = outputs.cameras
    moved = perturb_nerfstudio_cameras(truth, PerturbationConfig(enabled=True))
    _, model = detect_format(config)
    rms, evidence = colmap_track_evidence(moved, model, outputs.metadata["image_names"], outputs)
    config = S2CampCameraOptimizerConfig(track_prior=True, **optimizer_options)
    optimizer = config.setup(num_cameras=truth.shape[0], device="cpu")
    optimizer.refiner.set_camera_groups(outputs.metadata["camera_ids"])
    optimizer.set_train_cameras(moved, points=outputs.metadata["points3D_xyz"])
    optimizer.set_track_prior(rms, evidence)
    assert float((moved.camera_to_worlds - truth.camera_to_worlds).abs().max()) > 1e-2  # there to be undone
    return optimizer, truth


def test_exact_tracks_anchor_moved_cameras_at_the_truth(tiny_scene) -> None:
    # The exact tracks say where the true cameras are, so the prior's anchor is the truth (``core.track_fit``) and,
    # with a radius of ~0, its proximal step ends there. Checked against the true cameras, not against the fit.
    optimizer, truth = _moved_cameras_with_exact_tracks(tiny_scene)
    for _ in range(3):
        optimizer.refiner.apply_track_prior(lr=1.0)
    torch.testing.assert_close(
        optimizer.refiner.refined_c2w(opengl=True), truth.camera_to_worlds.double(), atol=1e-4, rtol=0
    )
    torch.testing.assert_close(optimizer.refiner.refined_intrinsics().fx, truth.fx[:, 0].double(), atol=1e-2, rtol=0)


def test_tracks_alone_places_the_cameras_at_the_anchor_and_the_images_do_not_move_them(tiny_scene) -> None:
    optimizer, truth = _moved_cameras_with_exact_tracks(tiny_scene, photometric=False)
    expected = truth.camera_to_worlds.double()
    torch.testing.assert_close(optimizer.refiner.refined_c2w(opengl=True), expected, atol=1e-4, rtol=0)  # no step taken
    before = [p.detach().clone() for p in optimizer.parameters()]
    adam = torch.optim.Adam(optimizer.parameters(), lr=1e-2)
    for _ in range(3):  # a loss that would move every coordinate
        adam.zero_grad()
        loss = sum((p - 1.0).square().sum() for p in optimizer.parameters())
        loss.backward()
        assert all(p.grad is not None and not bool(p.grad.any()) for p in optimizer.parameters())
        adam.step()
    assert all(torch.equal(p, q) for p, q in zip(optimizer.parameters(), before, strict=True))
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig

    S2CampCameraOptimizerConfig(photometric=False).validate()  # the prior is on by default
    with pytest.raises(ValueError, match=r"photometric False .* needs camera-optimizer.track-prior True"):
        S2CampCameraOptimizerConfig(photometric=False, track_prior=False).validate()


def test_the_default_starts_at_the_anchor_and_the_images_still_move_the_cameras(tiny_scene) -> None:
    # The tracks-alone placement with the images left on. With exact tracks the anchor is the truth, so the cameras
    # start there before any step; a loss then moves them.
    optimizer, truth = _moved_cameras_with_exact_tracks(tiny_scene)
    torch.testing.assert_close(
        optimizer.refiner.refined_c2w(opengl=True), truth.camera_to_worlds.double(), atol=1e-4, rtol=0
    )
    torch.testing.assert_close(optimizer.refiner.refined_intrinsics().fx, truth.fx[:, 0].double(), atol=1e-2, rtol=0)
    before = optimizer.refiner.whitened_delta.detach().clone()
    adam = torch.optim.Adam([optimizer.refiner.whitened_delta], lr=1e-2)
    adam.zero_grad()
    (optimizer.refiner.whitened_delta - 1.0).square().sum().backward()
    adam.step()
    assert (
        float((optimizer.refiner.whitened_delta.detach() - before).abs().min()) > 5e-3
    )  # Adam's first step moves each by lr
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig

    with pytest.raises(ValueError, match=r"pose_prior_exponent must lie in \[0, 1\], got 1.5"):
        S2CampCameraOptimizerConfig(pose_prior_exponent=1.5).validate()
