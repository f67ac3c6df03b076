"""The tracks a run's anchors were fitted to, kept with the run (``ANCHOR_TRACKS_FILE``) for the export.

``fitted_anchor_tracks`` keeps the observations the anchor fit counted (``core.track_fit``: in front of the anchor
camera, its image fitted) of the points that keep two or more of them, with each image's plain reprojection RMS at
the anchor over exactly those observations: what an exported point's reprojection error is compared with.
``given_anchor_tracks`` does the same at the given cameras, for a run whose cameras were not fitted to the tracks.
Points are in the tracks' world (the input's COLMAP world, ``data.colmap_world``), pixels in the training images.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from s2camp_ns.core.camera import NUM_CAMERA_PARAMS, Intrinsics
from s2camp_ns.core.track_fit import TrackEvidence, TrackFit, points_in_given_cameras, reprojection_residuals
from s2camp_ns.core.tracks import Tracks, per_image_rms

ANCHOR_TRACKS_FILE = "anchor_tracks.pt"
"""File of a run's ``AnchorTracks``, beside its config.yml (written when training starts)."""
FORMAT = 1
"""Version of the file's layout."""
MIN_TRACK_LENGTH = 2
"""Observations a point keeps at least (one observation places no point)."""


@dataclass(frozen=True)
class AnchorTracks:
    """The anchors' tracks of a run's ``num_images`` training images; ``tracks`` None: the run had none."""

    num_images: int
    tracks: Tracks | None = None
    rms_px: Float[Tensor, " n"] | None = None
    """Plain reprojection RMS (px) per image at the anchor over ``tracks``' observations; NaN: none."""

    def save(self, path: Path) -> None:
        """Write to ``path`` atomically (a temporary file renamed onto it)."""
        state: dict = {"format": FORMAT, "num_images": self.num_images}
        if self.tracks is not None:
            tracks = self.tracks
            state.update(points=tracks.points, image=tracks.image, point=tracks.point, pixels=tracks.pixels)
            state["rms_px"] = self.rms_px
        temporary = path.with_name(path.name + ".partial")
        torch.save({k: v.detach().cpu() if isinstance(v, Tensor) else v for k, v in state.items()}, temporary)
        temporary.replace(path)

    @classmethod
    def load(cls, path: Path) -> AnchorTracks:
        """What ``save`` wrote; ValueError naming ``path`` for another file or layout."""
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as error:  # torch raises several types for a damaged or foreign file
            raise ValueError(f"{path}: not an anchor-tracks file written by s2camp ({error})") from error
        if not isinstance(state, dict) or state.get("format") != FORMAT:
            found = state.get("format") if isinstance(state, dict) else type(state).__name__
            raise ValueError(f"{path}: anchor-tracks format {found!r}, expected {FORMAT}")
        n = int(state["num_images"])
        if "points" not in state:
            return cls(n)
        tracks = Tracks(state["points"], state["image"], state["point"], state["pixels"])
        try:
            tracks.validate(n)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from error
        return cls(n, tracks, state["rms_px"])


def _kept(tracks: Tracks, keep: Bool[Tensor, " o"]) -> tuple[Tracks, Bool[Tensor, " o"]]:
    """``tracks`` with the observations ``keep`` and the points left with ``MIN_TRACK_LENGTH`` of them, renumbered;
    and the mask of the observations kept."""
    point = tracks.point.to("cpu", torch.long)
    keep = keep.to("cpu")
    length = torch.bincount(point[keep], minlength=tracks.points.shape[0])
    long_enough = length >= MIN_TRACK_LENGTH
    keep = keep & long_enough[point]
    number = torch.cumsum(long_enough.to(torch.long), 0) - 1  # new index of each kept point
    kept = Tracks(
        points=tracks.points.detach().to("cpu", torch.float64)[long_enough],
        image=tracks.image.to("cpu", torch.long)[keep],
        point=number[point[keep]],
        pixels=tracks.pixels.detach().to("cpu", torch.float64)[keep],
    )
    return kept, keep


def fitted_anchor_tracks(evidence: TrackEvidence, fit: TrackFit, intrinsics: Intrinsics) -> AnchorTracks:
    """The observations ``fit`` (``fit_anchor`` of ``evidence`` under the given ``intrinsics``) counted, and the
    images' RMS at the anchor over those kept."""
    return _anchor_tracks(evidence, fit.deltas, intrinsics, fitted=fit.observations > 0)


def given_anchor_tracks(evidence: TrackEvidence, intrinsics: Intrinsics) -> AnchorTracks:
    """The observations in front of the given cameras (no fit), and the images' RMS there over those kept."""
    n = evidence.c2w.shape[0]
    no_deltas = torch.zeros(n, NUM_CAMERA_PARAMS, dtype=torch.float64)
    return _anchor_tracks(evidence, no_deltas, intrinsics, fitted=torch.ones(n, dtype=torch.bool))


def _anchor_tracks(
    evidence: TrackEvidence, deltas: Float[Tensor, "n 16"], intrinsics: Intrinsics, fitted: Bool[Tensor, " n"]
) -> AnchorTracks:
    """The observations in front of the cameras ``deltas`` move the given ones to, of the ``fitted`` images, kept with
    ``_kept``; each image's RMS there over those kept."""
    tracks, n = evidence.tracks, evidence.c2w.shape[0]
    image = tracks.image.to("cpu", torch.long)
    residual, margin = reprojection_residuals(
        deltas.to("cpu", torch.float64)[image], points_in_given_cameras(tracks, evidence.c2w),
        intrinsics.to(device="cpu", dtype=torch.float64)[image], tracks.pixels.detach().to("cpu", torch.float64),
    )  # fmt: skip
    kept, final = _kept(tracks, (margin > 0) & fitted.to("cpu")[image])
    squared = residual.square().sum(dim=-1)[final]
    return AnchorTracks(n, kept, per_image_rms(squared, torch.ones_like(squared), kept.image, n))


__all__ = ["ANCHOR_TRACKS_FILE", "AnchorTracks", "fitted_anchor_tracks", "given_anchor_tracks"]
