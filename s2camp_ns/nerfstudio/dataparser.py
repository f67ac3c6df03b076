"""Data parser for S2CamP: mip-NeRF 360 COLMAP scenes or nerfstudio transforms.json, optional CamP perturbation.

``--data`` may point at

- a mip-NeRF 360 style scene: ``images/``, ``images_2/``, ``images_4/``, ... and ``sparse/0/`` (or nerfstudio's own
  ``colmap/sparse/0``), read through nerfstudio's ``ColmapDataParser``;
- a nerfstudio scene: ``transforms.json`` (or the json file itself), read through nerfstudio's parser.

Downscaled images are taken from the pre-made ``images_{k}`` folder; nothing is regenerated (nerfstudio would ask
on the terminal and exit). Intrinsics are rescaled to the actual size of those images: mip-NeRF 360's
``images_4`` round the sizes (3114 -> 779) where nerfstudio floors them (778), which would shift the principal
point by half a pixel.

Before training, the scene is validated (corrupt or truncated model files, a transforms.json that is not valid JSON,
lacks a key, holds a NaN or infinite number or lists an image in two frames (``transforms_file``), images listed but
missing on disk or that cannot be decoded in full (``image_check``), images whose size is not the one the COLMAP
camera or the transforms.json ``w``/``h`` declare, unsupported camera models, empty scenes) with errors that name the
file (and the frame or image) and what was expected. Both formats get the same image
size check and intrinsics fit (``scene_formats.fit_intrinsics_to_images``), against the images the parser actually uses.

Camera models: COLMAP SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV (k4 = k5 = k6 = 0) and
OPENCV_FISHEYE; transforms.json with camera_model OPENCV or OPENCV_FISHEYE (what ``ns-process-data`` writes).
COLMAP parameters map explicitly to nerfstudio's distortion_params [k1, k2, k3, k4, p1, p2]
(``core.colmap_models``): nerfstudio's own COLMAP reader refuses FULL_OPENCV and any nonzero k4, including the
OPENCV_FISHEYE k4 it does represent, so this parser fills the distortion in itself.

The CamP perturbation (off by default; ``ns-train s2camp --data D s2camp-data --perturbation.enabled True``) is applied
to the training cameras after nerfstudio's orientation and scale normalization, so its sigmas are in normalized
scene units (the cameras fit in [-1, 1]^3), as CamP applies them in its own normalized scene. The unperturbed
cameras of the split are kept in ``metadata["reference_cameras"]``; evaluation cameras are never perturbed. The
scene's own tracks, made with the unperturbed cameras, would tell the track prior where the reference is: perturbed
cameras get tracks made from the images with the perturbed cameras instead, or no prior.

Tracks (``tracks``): each training camera's reprojection error against the COLMAP model's tracks, as the cameras are
given (after any perturbation), ``metadata["track_rms_px"]`` (``core.tracks``), and the tracks with those cameras in
the model's world, ``metadata["track_evidence"]``, from which the camera optimizer's track prior takes its anchor and
scale (``core.track_fit``): COLMAP scenes with points, and transforms.json scenes with the model ns-process-data leaves
beside them (``colmap/sparse/0``, cameras checked against it, ``transforms_tracks``); images the model does not hold
get NaN. Scenes without them get tracks made from their images (``image_tracks``: SIFT matches, points triangulated
with the given training cameras, bundle-adjusted with them and aligned to them by a similarity; built once, on the
CPU, and cached, ``track_cache``). With the perturbation on, the scene's own tracks (made with the unperturbed
cameras) are never used: the perturbed cameras get tracks made from the images (``image_tracks`` auto or always) or
none (never), and the log says which.

``_reference_cameras`` and ``_perturb`` are the two steps a subclass may replace (where the reference cameras come
from, how the training cameras are perturbed).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs

from s2camp_ns.core.camera import Intrinsics, camera_model_of
from s2camp_ns.core.perturbation import PerturbationConfig
from s2camp_ns.core.validation import check_range
from s2camp_ns.nerfstudio.camera_conversion import group_identical_intrinsics
from s2camp_ns.nerfstudio.camera_perturbation import perturb_nerfstudio_cameras
from s2camp_ns.nerfstudio.colmap_scene import parse_colmap
from s2camp_ns.nerfstudio.scene_formats import ParsedSplit, check_supported_cameras, detect_format
from s2camp_ns.nerfstudio.track_evidence import track_evidence
from s2camp_ns.nerfstudio.transforms_scene import parse_transforms


@dataclass
class S2CampDataParserConfig(DataParserConfig):
    """S2CamP data parser: mip-NeRF 360 / COLMAP or transforms.json scenes, optional CamP camera perturbation."""

    _target: type = field(default_factory=lambda: S2CampDataParser)
    """Target class to instantiate."""
    data: Path = Path()
    """Scene folder (mip-NeRF 360 layout or transforms.json), or a transforms json file."""
    data_format: Literal["auto", "colmap", "nerfstudio"] = "auto"
    """Scene format; auto detects a COLMAP model (sparse/0) first, then transforms.json."""
    downscale_factor: int | None = None
    """Use the pre-downscaled images_{k} folder; None picks images_4 when present, else the full-size images."""
    colmap_path: Path | None = None
    """COLMAP model folder relative to data; None tries sparse/0, colmap/sparse/0, sparse. For a transforms.json
    scene, the model of its tracks, relative to the json's folder (None: colmap/sparse/0)."""
    images_path: Path = Path("images")
    """Full-size image folder relative to data (the downscaled ones are its siblings with suffix _k)."""
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
    """Measure each training camera against the scene's SfM tracks, from which the track prior takes its anchor and
    scale (module docstring); scenes without them get tracks made from their images. False: nothing, no prior."""
    image_tracks: Literal["auto", "always", "never"] = "auto"
    """Tracks made from the scene's own images, built once and cached: auto where the scene has no SfM tracks or
    its cameras are perturbed, always in place of the scene's own, never only the scene's."""
    image_tracks_cache: Path | None = None
    """Folder of the image tracks' cache, read and written; None: ``s2camp_image_tracks`` in the scene folder, or
    ``$XDG_CACHE_HOME/s2camp-ns/image_tracks`` where that cannot be written (``track_cache``)."""
    perturbation: PerturbationConfig = field(default_factory=PerturbationConfig)
    """CamP perturbation of the training cameras (evaluation protocol, off by default)."""


@dataclass
class S2CampDataParser(DataParser):
    """See the module docstring."""

    config: S2CampDataParserConfig

    def __init__(self, config: S2CampDataParserConfig):
        super().__init__(config=config)
        self.config = config

    def _validate_config(self) -> None:
        config = self.config
        check_range("scale_factor", config.scale_factor, low=0.0, low_inclusive=False)
        check_range("scene_scale", config.scene_scale, low=0.0, low_inclusive=False)
        check_range("train_split_fraction", config.train_split_fraction, low=0.0, high=1.0)
        if (
            isinstance(config.eval_interval, bool)
            or not isinstance(config.eval_interval, int)
            or config.eval_interval < 1
        ):
            raise ValueError(f"eval_interval must be an integer in [1, inf), got {config.eval_interval!r}")
        config.perturbation.validate()
        saved = vars(config).get("reference_model")  # a run's config.yml from an earlier version
        if saved is not None and not hasattr(type(config), "reference_model"):
            raise ValueError(
                f"reference_model {saved}: this run's config.yml takes its reference cameras from a COLMAP model, "
                "which this version's s2camp-data no longer reads (s2camp-bench-data does); load the run with the "
                "version that trained it"
            )

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        self._validate_config()
        config = self.config
        data_format, source = detect_format(config)
        if data_format == "colmap":
            outputs, parsed = parse_colmap(config, Path(config.data), source, split)
        else:
            outputs, parsed = parse_transforms(config, source, split)
        intrinsics = check_supported_cameras(outputs.cameras, source)
        reference = self._reference_cameras(data_format, source, outputs, parsed)
        perturbed = split == "train" and config.perturbation.enabled
        cameras = self._perturb(outputs.cameras) if perturbed else outputs.cameras
        # One id per physical camera: images whose reference intrinsics agree (COLMAP's camera_id in practice; the
        # global intrinsics of a transforms.json), grouped before any perturbation. The refiner shares intrinsics
        # over these groups and the image tracks' adjustment models the same cameras.
        camera_ids = group_identical_intrinsics(reference)
        evidence = track_evidence(
            config, data_format, source, cameras, outputs, parsed, split, perturbed, camera_ids=camera_ids
        )
        metadata = {**outputs.metadata, **parsed.metadata()}
        if evidence is not None:
            metadata["track_rms_px"], metadata["track_evidence"] = evidence
        metadata.update(self._split_metadata(data_format, source, outputs, reference, intrinsics, perturbed))
        metadata["camera_ids"] = camera_ids.tolist()
        return dataclasses.replace(outputs, cameras=cameras, metadata=metadata)

    def _reference_cameras(
        self, data_format: str, source: Path, outputs: DataparserOutputs, parsed: ParsedSplit
    ) -> Cameras:
        """The split's reference cameras (``metadata["reference_cameras"]``: the camera errors, the viewer's
        reference frusta, the held-out views): a copy of the input cameras, before any perturbation."""
        return copy.deepcopy(outputs.cameras)

    def _perturb(self, cameras: Cameras) -> Cameras:
        """The training cameras perturbed (``perturbation.enabled``): CamP's protocol."""
        return perturb_nerfstudio_cameras(cameras, self.config.perturbation)

    @staticmethod
    def _split_metadata(
        data_format: str,
        source: Path,
        outputs: DataparserOutputs,
        reference: Cameras,
        intrinsics: Intrinsics,
        perturbed: bool,
    ) -> dict:
        """The metadata entries of the split that the camera optimizer, the model and the export read (beside
        ``camera_ids``, which the track evidence shares)."""
        return dict(
            reference_cameras=reference,
            # The COLMAP model whose distortion the camera optimizer's "all" preset refines (sizes its latent before
            # DDP wraps the model and before the optimizers are built).
            camera_model=camera_model_of(intrinsics),
            dataparser_scale=float(outputs.dataparser_scale),
            dataparser_transform=outputs.dataparser_transform.clone(),
            perturbed=perturbed,
            source_format=data_format,
            source_path=source.resolve(),
        )


__all__ = ["S2CampDataParser", "S2CampDataParserConfig"]


def _specification():
    from nerfstudio.plugins.registry_dataparser import DataParserSpecification

    return DataParserSpecification(
        config=S2CampDataParserConfig(),
        description="mip-NeRF 360 / COLMAP layout or transforms.json, with optional CamP camera perturbation",
    )


s2camp_dataparser = _specification()
"""Registered as ``s2camp-data`` (entry point ``nerfstudio.dataparser_configs``): nerfstudio exposes dataparser
options only after the dataparser's subcommand, e.g.
``ns-train s2camp --data scene s2camp-data --perturbation.enabled True``."""
