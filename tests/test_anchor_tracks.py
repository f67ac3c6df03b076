"""``core.anchor_tracks``: the observations the anchor fit kept, their RMS there, and the run's file."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_track_fit import POSE_AND_INTRINSICS, _intrinsics, _moved, _observe, _perturbation, _points, _ring

from s2camp_ns.core.anchor_tracks import AnchorTracks, fitted_anchor_tracks, given_anchor_tracks
from s2camp_ns.core.track_fit import TrackEvidence, fit_anchor
from s2camp_ns.core.tracks import Tracks, track_reprojection_rms


def _evidence(n: int = 8) -> tuple[TrackEvidence, torch.Tensor]:
    """Noisy tracks of perturbed ring cameras, plus a point seen by one image only and an observation of a point
    behind its camera; and the true c2w."""
    truth, intrinsics = _ring(n), _intrinsics(n)
    tracks = _observe(_points(), truth, intrinsics, noise_px=0.3)
    lonely = torch.tensor([[0.05, 0.05, 0.05]], dtype=torch.float64)  # a new point, observed by image 0 only
    behind = 2 * truth[1, :, 3]  # beyond camera 1 (behind it), ahead of cameras 4 and 5 across the ring
    points = torch.cat([tracks.points, lonely, behind[None]])
    p = tracks.points.shape[0]
    tracks = Tracks(
        points,
        torch.cat([tracks.image, torch.tensor([0, 1, 4, 5])]),
        torch.cat([tracks.point, torch.tensor([p, p + 1, p + 1, p + 1])]),
        torch.cat([tracks.pixels, torch.tensor([[30.0, 20.0], [31.0, 21.0], [32.0, 22.0], [33.0, 23.0]])]),
    )
    return TrackEvidence(tracks, _moved(truth, _perturbation(n)), 1.0), intrinsics


def test_fitted_tracks_keep_what_the_fit_counted_and_their_rms_at_the_anchor():
    evidence, intrinsics = _evidence()
    fit = fit_anchor(evidence.tracks, evidence.c2w, intrinsics, free=POSE_AND_INTRINSICS)
    anchor = fitted_anchor_tracks(evidence, fit, intrinsics)
    tracks, p = anchor.tracks, evidence.tracks.points.shape[0]
    # The lonely point is gone (one observation); the point behind camera 1 keeps its two other observations.
    assert tracks.points.shape[0] == p - 1
    assert tracks.image.shape[0] == evidence.tracks.image.shape[0] - 2
    assert torch.equal(tracks.points[-1], evidence.tracks.points[-1])
    assert torch.equal(tracks.image[tracks.point == p - 2], torch.tensor([4, 5]))
    assert int(torch.bincount(tracks.point).min()) >= 2
    # The RMS is that of the kept observations through the anchor cameras (pose and intrinsics of the fit).
    anchor_c2w = _moved(evidence.c2w, fit.deltas[:, :6])
    rms = track_reprojection_rms(tracks, anchor_c2w, intrinsics.with_delta(fit.deltas))
    torch.testing.assert_close(anchor.rms_px, rms, rtol=1e-9, atol=1e-12)
    # 0.3 px of noise per axis where no outlier is left (image 0's lonely observation went with its point).
    assert float(anchor.rms_px[[0, 1, 2, 3, 6, 7]].max()) < 0.6 < float(anchor.rms_px[4:6].min())


def test_given_tracks_keep_the_observations_in_front_of_the_given_cameras():
    evidence, intrinsics = _evidence()
    anchor = given_anchor_tracks(evidence, intrinsics)
    assert anchor.tracks.image.shape[0] == evidence.tracks.image.shape[0] - 2
    rms = track_reprojection_rms(anchor.tracks, evidence.c2w, intrinsics)
    torch.testing.assert_close(anchor.rms_px, rms, rtol=1e-9, atol=1e-12)


def test_the_file_reads_back_bit_for_bit_and_names_itself_when_wrong(tmp_path: Path):
    evidence, intrinsics = _evidence()
    anchor = given_anchor_tracks(evidence, intrinsics)
    anchor.save(tmp_path / "anchor_tracks.pt")
    loaded = AnchorTracks.load(tmp_path / "anchor_tracks.pt")
    assert loaded.num_images == anchor.num_images
    for name in ("points", "image", "point", "pixels"):
        assert torch.equal(getattr(loaded.tracks, name), getattr(anchor.tracks, name)), name
    assert torch.equal(loaded.rms_px, anchor.rms_px)
    AnchorTracks(5).save(tmp_path / "none.pt")
    assert AnchorTracks.load(tmp_path / "none.pt") == AnchorTracks(5)
    (tmp_path / "foreign.pt").write_text("not a tensor file")
    with pytest.raises(ValueError, match="foreign.pt: not an anchor-tracks file"):
        AnchorTracks.load(tmp_path / "foreign.pt")
    torch.save({"format": 99}, tmp_path / "future.pt")
    with pytest.raises(ValueError, match="future.pt: anchor-tracks format 99, expected 1"):
        AnchorTracks.load(tmp_path / "future.pt")
    torch.save({"format": 1, "num_images": 2, "points": anchor.tracks.points, "image": anchor.tracks.image,
                "point": anchor.tracks.point, "pixels": anchor.tracks.pixels, "rms_px": anchor.rms_px},
               tmp_path / "other.pt")  # fmt: skip
    with pytest.raises(ValueError, match="other.pt: tracks.image must index the 2 cameras"):
        AnchorTracks.load(tmp_path / "other.pt")
