"""The options of a scene as the S2CamP data parser reads it: its files, format, images, split and tracks.

The format readers (``colmap_scene``, ``transforms_scene``, ``scene_formats``) and the track evidence
(``tracks.track_evidence``) take this config; the data parser's own (``dataparser.S2CampDataParserConfig``) adds the
CamP perturbation and the class it builds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig


@dataclass
class SceneConfig(DataParserConfig):
    """Where a scene's files are and how it is read (COLMAP layout or transforms.json)."""

    data: Path = Path()
    """Scene folder (mip-NeRF 360 layout or transforms.json), or a transforms json file."""
    data_format: Literal["auto", "colmap", "nerfstudio"] = "auto"
    """Scene format; auto detects a COLMAP model (sparse/0) first, then transforms.json."""
    downscale_factor: int | None = None
    """Use the pre-downscaled images_{k} folder; None picks images_4 when present, else the full-size images."""
    colmap_path: Path | None = None
    """COLMAP model folder relative to data (None: sparse/0, colmap/sparse/0, sparse); for a transforms.json, the
    model of its tracks relative to the json's folder (None: colmap/sparse/0)."""
    images_path: Path = Path("images")
    """Full-size image folder relative to data (downscaled ones are its siblings with suffix _k)."""
    scale_factor: float = 1.0
    """Extra scale applied to the camera centres after the automatic scaling."""
    scene_scale: float = 1.0
    """Half side of the scene box."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    """Orientation normalization of nerfstudio."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """Centring normalization of nerfstudio."""
    auto_scale_poses: bool = True
    """Scale the camera centres into [-1, 1]^3 (the perturbation sigmas are in these units)."""
    eval_mode: Literal["fraction", "filename", "interval", "all"] = "interval"
    """Train / eval split; interval takes every eval_interval-th image for eval (the mip-NeRF 360 protocol)."""
    train_split_fraction: float = 0.9
    """Fraction of the images used for training with eval_mode fraction."""
    eval_interval: int = 8
    """Every eval_interval-th image is held out with eval_mode interval."""
    load_3D_points: bool = True
    """Load the COLMAP sparse points into metadata (needed by point-initialized models; cheap)."""
    tracks: bool = True
    """Measure each training image against the scene's SfM tracks (else tracks made from its images) for the track
    prior; False: no prior."""
    image_tracks: Literal["auto", "always", "never"] = "auto"
    """Tracks made from the scene's images, cached: auto where the scene has no SfM tracks or its cameras are
    perturbed, always in place of the scene's own, never only the scene's."""
    refine_keypoints: bool = True
    """Align each track's image patches to refine its keypoints before the tracks place the cameras (SfM's tracks and
    those made from the images; docs/IMAGE-TRACKS.md); False: the detected keypoints."""
    image_tracks_cache: Path | None = None
    """Folder of the image tracks' cache; None: ``s2camp_image_tracks`` in the scene folder, or the user's cache
    folder where that cannot be written (``track_cache``)."""


__all__ = ["SceneConfig"]
