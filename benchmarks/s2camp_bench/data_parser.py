"""``s2camp-bench-data``: the S2CamP data parser with the benchmarks' two starts that no user command needs.

- ``--drift.enabled True`` (with ``--perturbation.enabled True``): the visual-inertial drift of the "phone" start
  (``phone_drift``), drawn after CamP's steps from the same seeded stream;
- ``--reference-model``: the true cameras of a COLMAP model as the reference cameras (``reference_model``), the
  sfm starts' truth.

Everything else is ``s2camp-data``'s (``s2camp_ns.data.dataparser``). It is not an installed entry point, so
a user's ``ns-train`` never imports the benchmarks: the benchmarks' ``ns-train`` runs get it through nerfstudio's
``NERFSTUDIO_DATAPARSER_CONFIGS`` variable (``ns_train_environment``) and take it after the method's options:
``ns-train s2camp --data D s2camp-bench-data --reference-model truth/sparse/0``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs

from s2camp_bench.train_commands import training_environment
from s2camp_ns.data.camera_perturbation import perturb_nerfstudio_cameras
from s2camp_ns.data.dataparser import S2CampDataParser, S2CampDataParserConfig
from s2camp_ns.data.scene_formats import ParsedSplit

from .phone_drift import DriftConfig, perturb_with_drift
from .reference_model import reference_from_model

SUBCOMMAND = "s2camp-bench-data"
"""The data parser's subcommand."""
REGISTRY_VARIABLE = "NERFSTUDIO_DATAPARSER_CONFIGS"
"""nerfstudio's list of extra data parsers, ``name=module:attribute`` separated by commas."""


@dataclass
class BenchDataParserConfig(S2CampDataParserConfig):
    """S2CamP data parser plus the benchmarks' VIO drift and reference model (module docstring)."""

    _target: type = field(default_factory=lambda: BenchDataParser)
    """Target class to instantiate."""
    drift: DriftConfig = field(default_factory=DriftConfig)
    """Visual-inertial odometry drift added after CamP's steps (needs ``perturbation.enabled``; off by default)."""
    reference_model: Path | None = None
    """COLMAP model of the true cameras (images matched by name, COLMAP scenes only): the reference cameras of the
    camera errors, the viewer's reference frusta and the held-out views, similarity-aligned into the input's frame."""


@dataclass
class BenchDataParser(S2CampDataParser):
    """See the module docstring."""

    config: BenchDataParserConfig

    def _validate_config(self) -> None:
        super()._validate_config()
        self.config.drift.validate()
        if self.config.drift.enabled and not self.config.perturbation.enabled:
            raise ValueError(
                "drift.enabled needs perturbation.enabled True: the drift draws from the perturbation's seeded "
                "stream after CamP's steps (set CamP's four sigmas to 0 for the drift alone)"
            )

    def _reference_cameras(
        self, data_format: str, source: Path, outputs: DataparserOutputs, parsed: ParsedSplit
    ) -> Cameras:
        """The input cameras, or those of ``reference_model`` (COLMAP scenes only: images are matched by name)."""
        config = self.config
        if config.reference_model is None:
            return super()._reference_cameras(data_format, source, outputs, parsed)
        if data_format != "colmap":
            raise ValueError(
                f"reference_model {config.reference_model} needs a COLMAP scene (images matched by name), but "
                f"--data {config.data} is a {data_format} scene ({source})"
            )
        transform, scale = outputs.dataparser_transform, float(outputs.dataparser_scale)
        names = parsed.image_names
        return reference_from_model(config.reference_model, source, names, outputs.cameras, transform, scale)

    def _perturb(self, cameras: Cameras) -> Cameras:
        """CamP's perturbation, then the drift where it is on."""
        if not self.config.drift.enabled:
            return super()._perturb(cameras)
        with_drift = functools.partial(perturb_with_drift, drift=self.config.drift)
        return perturb_nerfstudio_cameras(cameras, self.config.perturbation, perturb=with_drift)


def _specification():
    from nerfstudio.plugins.registry_dataparser import DataParserSpecification

    return DataParserSpecification(
        config=BenchDataParserConfig(),
        description="s2camp-data with the benchmarks' VIO drift (--drift) and true cameras (--reference-model)",
    )


bench_dataparser = _specification()
"""Registered as ``s2camp-bench-data`` in the ``ns-train`` runs of the benchmarks (``ns_train_environment``)."""


def ns_train_environment() -> dict[str, str]:
    """``training_environment`` with ``s2camp-bench-data`` added to ``REGISTRY_VARIABLE``'s data parsers."""
    environment = training_environment()
    entry = f"{SUBCOMMAND}={__name__}:bench_dataparser"
    present = [item for item in environment.get(REGISTRY_VARIABLE, "").split(",") if item and item != entry]
    environment[REGISTRY_VARIABLE] = ",".join([*present, entry])
    return environment


__all__ = ["SUBCOMMAND", "BenchDataParser", "BenchDataParserConfig", "bench_dataparser", "ns_train_environment"]
