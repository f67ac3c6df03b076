"""``s2camp-bench``: run a benchmark, write its report under outputs/benchmarks/ (``--output-dir`` elsewhere, e.g.
docs/benchmarks for the committed reports), optionally print JSON rows."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Union

import tyro

from .anchors import AnchorsConfig
from .common import DEFAULT_OUTPUT_DIR, emit_json, log
from .dispersion import DispersionConfig
from .export_load import ExportLoadConfig
from .gram_error import GramErrorConfig
from .image_tracks_cost import ImageTracksCostConfig
from .robustness import RobustnessConfig
from .splat_bench import SplatBenchConfig
from .step_cost import StepCostConfig

MODULES = {
    StepCostConfig: "step_cost", RobustnessConfig: "robustness", SplatBenchConfig: "splat_bench",
    GramErrorConfig: "gram_error", DispersionConfig: "dispersion", ImageTracksCostConfig: "image_tracks_cost",
    AnchorsConfig: "anchors", ExportLoadConfig: "export_load",
}  # fmt: skip
"""Every benchmark, in the order ``s2camp-bench all`` runs them."""


@dataclass
class AllConfig:
    """Every benchmark in turn, each writing its own report."""

    quick: bool = False
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the reports and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""


Command = Union[
    Annotated[StepCostConfig, tyro.conf.subcommand("step-cost")],
    Annotated[RobustnessConfig, tyro.conf.subcommand("robustness")],
    Annotated[SplatBenchConfig, tyro.conf.subcommand("splat")],
    Annotated[GramErrorConfig, tyro.conf.subcommand("gram-error")],
    Annotated[DispersionConfig, tyro.conf.subcommand("dispersion")],
    Annotated[ImageTracksCostConfig, tyro.conf.subcommand("image-tracks")],
    Annotated[AnchorsConfig, tyro.conf.subcommand("anchors")],
    Annotated[ExportLoadConfig, tyro.conf.subcommand("export-load")],
    Annotated[AllConfig, tyro.conf.subcommand("all")],
]


def run_benchmark(config) -> list[dict]:
    """``run`` of the config's benchmark module, and its ``report`` unless ``write`` is off; the rows."""
    module = importlib.import_module(f"{__package__}.{MODULES[type(config)]}")
    rows = module.run(config)
    if config.write:
        log(f"wrote {module.report(rows, config)}")
    return rows


def main(config) -> list[dict]:
    if isinstance(config, AllConfig):
        configs = [kind(quick=config.quick, output_dir=config.output_dir) for kind in MODULES]
        return [row for each in configs for row in run_benchmark(each)]
    rows = run_benchmark(config)
    if config.json:
        emit_json(rows)
    return rows


def entrypoint() -> None:
    main(tyro.cli(Command, description=__doc__))
