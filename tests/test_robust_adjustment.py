"""The SfM model's points re-adjusted with a robust loss (``tracks.robust_adjustment``): closer to the truth than
a least-squares adjustment leaves them when some keypoints are mismatched, in the model's own frame, used as the
anchor's points and not for the model check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from s2camp_ns.core.alignment import umeyama


def _least_squares_model(scene: Path, folder: Path, seed: int = 0) -> Path:
    """The tiny scene's exact model with 0.2 px keypoint noise and one keypoint in ten moved 3 px (within COLMAP's
    4 px filter: a mismatch the mapper keeps), adjusted in plain least squares as COLMAP's mapper ends, written to
    ``folder``."""
    reconstruction = pycolmap.Reconstruction(scene / "sparse" / "0")
    generator = np.random.default_rng(seed)
    for image in reconstruction.images.values():
        for index, point in enumerate(image.points2D):
            if point.has_point3D():
                shift = generator.normal(0.0, 0.2, 2)
                if generator.random() < 0.1:
                    angle = generator.uniform(0.0, 2.0 * np.pi)
                    shift += 3.0 * np.array([np.cos(angle), np.sin(angle)])
                image.points2D[index].xy = point.xy + shift
    options = pycolmap.BundleAdjustmentOptions(refine_principal_point=False, print_summary=False)
    pycolmap.bundle_adjustment(reconstruction, options)
    folder.mkdir(parents=True)
    reconstruction.write(folder)
    return folder


def _centres(reconstruction: pycolmap.Reconstruction, ids: list[int]) -> torch.Tensor:
    return torch.tensor(np.stack([reconstruction.images[i].projection_center() for i in ids]))


def test_the_robust_adjustment_brings_the_points_closer_to_the_truth_in_the_models_frame(tiny_scene, tmp_path):
    from s2camp_ns.tracks.robust_adjustment import readjusted_tracks

    model = _least_squares_model(tiny_scene, tmp_path / "model")
    truth = pycolmap.Reconstruction(tiny_scene / "sparse" / "0")
    given = pycolmap.Reconstruction(model)
    readjusted = readjusted_tracks(model)
    adjusted = readjusted.points
    assert sorted(adjusted) == sorted(given.points3D) and readjusted.keypoints == {}  # no images: not refined
    ids = sorted(truth.reg_image_ids())
    to_truth = umeyama(_centres(given, ids), _centres(truth, ids))  # the model's frame onto the truth's
    point_ids = sorted(given.points3D)
    true_xyz = torch.tensor(np.stack([truth.points3D[i].xyz for i in point_ids]))

    def median_error(xyz: list[np.ndarray]) -> float:
        mapped = to_truth.apply_to_points(torch.tensor(np.stack(xyz)))
        return float((mapped - true_xyz).norm(dim=-1).median())

    before = median_error([given.points3D[i].xyz for i in point_ids])
    after = median_error([adjusted[i] for i in point_ids])
    # The mismatches hold the least-squares points back; the Cauchy loss discounts them.
    assert after < 0.6 * before, (before, after)
    assert readjusted_tracks(model) is readjusted  # one adjustment per model, shared by the data parser's splits


def test_colmap_evidence_anchors_to_the_adjusted_points_and_checks_the_model_with_its_own(tiny_scene, monkeypatch):
    from s2camp_ns.core.tracks import track_reprojection_rms
    from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
    from s2camp_ns.data.dataparser import S2CampDataParserConfig
    from s2camp_ns.tracks import track_evidence
    from s2camp_ns.tracks.colmap_tracks import read_colmap_tracks
    from s2camp_ns.tracks.robust_adjustment import ReadjustedTracks

    outputs = S2CampDataParserConfig(data=tiny_scene, image_tracks="never").setup().get_dataparser_outputs("train")
    names = outputs.metadata["image_names"]
    model = tiny_scene / "sparse" / "0"
    own = read_colmap_tracks(model, names)
    moved = {point_id: np.full(3, float(point_id)) for point_id in pycolmap.Reconstruction(model).points3D}
    monkeypatch.setattr(track_evidence, "readjusted_tracks", lambda folder, images: ReadjustedTracks(moved))
    rms, evidence = track_evidence.colmap_track_evidence(outputs.cameras, model, names, outputs)
    expected = torch.tensor(np.stack([moved[i] for i in sorted(moved)]), dtype=torch.float64)
    assert torch.equal(evidence.tracks.points.sort(dim=0).values, expected.sort(dim=0).values)
    assert torch.equal(evidence.tracks.pixels, own.pixels) and torch.equal(evidence.tracks.point, own.point)
    # The exact model's own points fit the given (true) cameras to float precision: the check sees them, not the
    # moved ones, which no camera would fit.
    assert float(rms.max()) < 1e-3
    at_moved = track_reprojection_rms(evidence.tracks, evidence.c2w, intrinsics_from_cameras(outputs.cameras))
    assert float(at_moved.min()) > 1.0


def test_tracks_of_images_take_positions_by_point_id_and_keypoints_by_image_id(tiny_scene):
    from s2camp_ns.tracks.colmap_tracks import read_colmap_tracks
    from s2camp_ns.tracks.robust_adjustment import ReadjustedTracks

    model = tiny_scene / "sparse" / "0"
    names = sorted(image.name for image in pycolmap.Reconstruction(model).images.values())[:3]
    own = read_colmap_tracks(model, names)
    points = pycolmap.Reconstruction(model).points3D
    offset = {i: points[i].xyz + 1.0 for i in points}
    shifted = read_colmap_tracks(model, names, adjusted=ReadjustedTracks(offset))
    torch.testing.assert_close(shifted.points, own.points + 1.0, rtol=0, atol=1e-12)
    # Keypoints by image id replace the model's, observation for observation; images without any keep theirs.
    image = next(image for image in pycolmap.Reconstruction(model).images.values() if image.name == names[1])
    moved = np.asarray([point.xy for point in image.points2D]) + 0.25
    refined = read_colmap_tracks(model, names, adjusted=ReadjustedTracks(offset, {image.image_id: moved}))
    expected = own.pixels + 0.25 * (own.image == 1)[:, None].double()
    torch.testing.assert_close(refined.pixels, expected, rtol=0, atol=1e-12)


def test_the_adjusted_points_are_cached_for_the_next_process_by_the_models_content(tiny_scene, tmp_path, monkeypatch):
    from s2camp_ns.tracks import robust_adjustment

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    model = _least_squares_model(tiny_scene, tmp_path / "model")
    first = robust_adjustment.readjusted_tracks(model).points
    cache = tmp_path / "xdg" / "s2camp-ns" / "readjusted_points"
    entries = sorted(cache.iterdir())
    assert len(entries) == 1 and entries[0].suffix == ".npz"  # no lock or temporary file left beside it

    def no_adjustment(*args, **kwargs):
        raise AssertionError("adjusted again")

    robust_adjustment._cached.cache_clear()  # a new process
    monkeypatch.setattr(pycolmap, "bundle_adjustment", no_adjustment)
    again = robust_adjustment.readjusted_tracks(model).points
    assert list(again) == list(first) and all(np.array_equal(again[i], first[i]) for i in first)  # bit-identical
    # Another model (one point moved) is another entry: it is adjusted, not read.
    edited = pycolmap.Reconstruction(model)
    point_id = next(iter(edited.points3D))
    edited.points3D[point_id].xyz = edited.points3D[point_id].xyz + 0.01
    (tmp_path / "edited").mkdir()
    edited.write(tmp_path / "edited")
    with pytest.raises(AssertionError, match="adjusted again"):
        robust_adjustment.readjusted_tracks(tmp_path / "edited")
    # A cache folder that cannot be written: adjusted in memory.
    monkeypatch.undo()
    (tmp_path / "blocked").write_text("a file, not a folder")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "blocked"))
    robust_adjustment._cached.cache_clear()
    in_memory = robust_adjustment.readjusted_tracks(model).points
    assert all(np.allclose(in_memory[i], first[i], rtol=0, atol=1e-9) for i in first)
    assert sorted(cache.iterdir()) == entries
