"""``s2camp-bench``: run a benchmark, write its report under outputs/benchmarks/ (``--output-dir`` elsewhere, e.g.
docs/benchmarks for the committed tables), optionally print JSON rows."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Union

import tyro

from .common import DEFAULT_OUTPUT_DIR, emit_json, log
from .dispersion import DispersionConfig
from .gram_error import GramErrorConfig
from .image_tracks_cost import ImageTracksCostConfig
from .lattice_search import LatticeSearchConfig
from .proxy_range import ProxyRangeBenchConfig
from .recovery import RecoveryConfig
from .robustness import RobustnessConfig
from .scaling import ScalingConfig
from .shared_intrinsics import SharedIntrinsicsConfig
from .speed import SpeedConfig
from .splat_bench import SplatBenchConfig
from .step_cost import StepCostConfig
from .train_time import TrainTimeConfig

MODULES = {
    DispersionConfig: "dispersion",
    GramErrorConfig: "gram_error",
    SpeedConfig: "speed",
    RecoveryConfig: "recovery",
    ScalingConfig: "scaling",
    TrainTimeConfig: "train_time",
    SharedIntrinsicsConfig: "shared_intrinsics",
    ProxyRangeBenchConfig: "proxy_range",
    RobustnessConfig: "robustness",
    SplatBenchConfig: "splat_bench",
    StepCostConfig: "step_cost",
    ImageTracksCostConfig: "image_tracks_cost",
}
"""The benchmarks ``s2camp-bench all`` runs."""
TOOLS = {LatticeSearchConfig: "lattice_search"}
"""Offline tools with the same command-line shape, not part of ``all``."""


@dataclass
class AllConfig:
    """Every benchmark in turn, each writing its own report."""

    quick: bool = False
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""


Command = Union[
    Annotated[DispersionConfig, tyro.conf.subcommand("dispersion")],
    Annotated[GramErrorConfig, tyro.conf.subcommand("gram-error")],
    Annotated[SpeedConfig, tyro.conf.subcommand("speed")],
    Annotated[RecoveryConfig, tyro.conf.subcommand("recovery")],
    Annotated[ScalingConfig, tyro.conf.subcommand("scaling")],
    Annotated[TrainTimeConfig, tyro.conf.subcommand("train-time")],
    Annotated[SharedIntrinsicsConfig, tyro.conf.subcommand("shared-intrinsics")],
    Annotated[ProxyRangeBenchConfig, tyro.conf.subcommand("proxy-range")],
    Annotated[RobustnessConfig, tyro.conf.subcommand("robustness")],
    Annotated[SplatBenchConfig, tyro.conf.subcommand("splat")],
    Annotated[StepCostConfig, tyro.conf.subcommand("step-cost")],
    Annotated[ImageTracksCostConfig, tyro.conf.subcommand("image-tracks")],
    Annotated[LatticeSearchConfig, tyro.conf.subcommand("lattice-search")],
    Annotated[AllConfig, tyro.conf.subcommand("all")],
]


def run_benchmark(config) -> list[dict]:
    module = importlib.import_module(f"{__package__}.{({**MODULES, **TOOLS})[type(config)]}")
    rows = module.run(config)
    if config.write:
        log(f"wrote {module.report(rows, config)}")
    return rows


def main(config) -> list[dict]:
    if isinstance(config, AllConfig):
        rows = []
        for config_type in MODULES:
            rows.extend(run_benchmark(config_type(quick=config.quick, output_dir=config.output_dir)))
        return rows
    rows = run_benchmark(config)
    if config.json:
        emit_json(rows)
    return rows


def entrypoint() -> None:
    main(tyro.cli(Command, description=__doc__))


__all__ = ["entrypoint", "main"]
