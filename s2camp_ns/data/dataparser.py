"""Data parser for S2CamP: mip-NeRF 360 COLMAP scenes or nerfstudio transforms.json, optional CamP perturbation.

``--data`` is a COLMAP scene (``images/``, ``images_k/``, ``sparse/0`` or ``colmap/sparse/0``; ``colmap_scene``) or a
transforms.json (``transforms_scene``), validated first with errors that name the file and what was expected.
Downscaled images come from the pre-made ``images_{k}`` folder and the intrinsics are fitted to their actual size.
Camera models: COLMAP SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV (k4 = k5 = k6 = 0) and
OPENCV_FISHEYE; transforms.json OPENCV or OPENCV_FISHEYE.

The CamP perturbation (``--perturbation.enabled True``) applies to the training cameras after nerfstudio's
normalization (sigmas in normalized scene units, as in CamP); the unperturbed cameras are kept in
``metadata["reference_cameras"]``. ``track_evidence`` adds ``metadata["track_rms_px"]`` and
``metadata["track_evidence"]`` for the track prior. A subclass may replace ``_reference_cameras`` and ``_perturb``.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs

from s2camp_ns.compat import refuse_removed_fields
from s2camp_ns.core.camera import Intrinsics, camera_model_of
from s2camp_ns.core.perturbation import PerturbationConfig
from s2camp_ns.core.validation import check_range
from s2camp_ns.data.camera_conversion import group_identical_intrinsics
from s2camp_ns.data.camera_perturbation import perturb_nerfstudio_cameras
from s2camp_ns.data.colmap_scene import parse_colmap
from s2camp_ns.data.scene_config import SceneConfig
from s2camp_ns.data.scene_formats import ParsedSplit, check_supported_cameras, detect_format
from s2camp_ns.data.transforms_scene import parse_transforms
from s2camp_ns.tracks.track_evidence import track_evidence


@dataclass
class S2CampDataParserConfig(SceneConfig):
    """S2CamP data parser: mip-NeRF 360 / COLMAP or transforms.json scenes, optional CamP camera perturbation."""

    _target: type = field(default_factory=lambda: S2CampDataParser)
    """Target class to instantiate."""
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
        interval = config.eval_interval
        if isinstance(interval, bool) or not isinstance(interval, int) or interval < 1:
            raise ValueError(f"eval_interval must be an integer in [1, inf), got {config.eval_interval!r}")
        config.perturbation.validate()
        if not hasattr(type(config), "reference_model"):  # the benchmarks' data parser still has the field
            refuse_removed_fields("dataparser", config)

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
        # One id per physical camera (images whose reference intrinsics agree), grouped before any perturbation.
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
        """The split's reference cameras (``metadata["reference_cameras"]``): a copy of the unperturbed cameras."""
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
        """The split's metadata for the camera optimizer, the model and the export (beside ``camera_ids``)."""
        return dict(
            reference_cameras=reference,
            # The distortion model the camera optimizer's "all" preset refines (sizes its latent before DDP wraps it).
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
"""Registered as ``s2camp-data`` (entry point ``nerfstudio.dataparser_configs``); its options follow the subcommand:
``ns-train s2camp --data scene s2camp-data --perturbation.enabled True``."""
