"""``s2camp-bench dispersion`` (paper Table 1 and Fig. 4): the deterministic Frolov lattice against random points.

For each reference frustum ("room": mip-NeRF 360 room at 1/4 resolution; "wide": 90 degrees, 3:2), transform and L,
the dispersion (radius of the largest empty ball with centre in the contracted frustum, ``dispersion_bound``) of the
Frolov lattice (``s2camp_ns.core.lattice.frolov_lattice``) and, the baseline, of uniform random points through the
same transform (the mean over the seeds).
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from s2camp_bench.report import markdown_table
from s2camp_ns.core.frustum import sample_frustum
from s2camp_ns.core.lattice import frolov_lattice, random_points

from .common import DEFAULT_OUTPUT_DIR, log, write_report
from .dispersion_bound import dispersion, reference_tangent_bounds


@dataclass
class DispersionConfig:
    """Dispersion of deterministic vs random frustum samples (paper Table 1, Fig. 4)."""

    frusta: tuple[str, ...] = ("room", "wide")
    """Reference frusta (``dispersion_bound.reference_tangent_bounds``)."""
    transforms: tuple[str, ...] = ("pyramid", "spherical")
    num_points: tuple[int, ...] = (100, 500, 5000)
    """Values of L."""
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    """Seeds of the random baseline."""
    t_near: float = 0.0
    """Near contracted radius; 0 puts the frustum apex on the camera centre, as in the paper's figures."""
    t_far: float = 1.99
    tolerance: float = 1e-3
    """Stop refining when the upper bound is within this of the attained value."""
    quick: bool = False
    """Small run for CI: room frustum, pyramid, L = 100 and 500, two seeds."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plot (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False

    def effective(self) -> DispersionConfig:
        if not self.quick:
            return self
        return replace(self, frusta=("room",), transforms=("pyramid",), num_points=(100, 500), seeds=(0, 1))


def measure(unit: torch.Tensor, bounds: torch.Tensor, transform: str, config: DispersionConfig):
    """The ``DispersionResult`` of the unit-cube points ``unit`` through ``transform`` into the frustum."""
    points = sample_frustum(unit, bounds, config.t_near, config.t_far, transform).contracted
    return dispersion(points, bounds, config.t_near, config.t_far, transform, config.tolerance)


def run(config: DispersionConfig) -> list[dict]:
    """One row per frustum, transform, sampler and L (the random rows: means over the seeds)."""
    config = config.effective()
    rows: list[dict] = []
    for frustum in config.frusta:
        bounds = reference_tangent_bounds(frustum)
        for transform in config.transforms:
            for num_points in config.num_points:
                log(f"dispersion: {frustum} {transform} L={num_points}")
                sets = {"deterministic": [frolov_lattice(num_points)]}
                sets["random"] = [random_points(num_points, seed) for seed in config.seeds]
                for sampler, units in sets.items():
                    results = [measure(unit, bounds, transform, config) for unit in units]
                    values = [float(result.value[0]) for result in results]
                    rows.append({
                        "frustum": frustum, "transform": transform, "sampler": sampler, "L": num_points,
                        "dispersion": statistics.fmean(values),
                        "dispersion_std": statistics.pstdev(values) if len(values) > 1 else 0.0,
                        "error_bound": max(float(result.error_bound[0]) for result in results),
                        "seeds": len(units) if sampler == "random" else 0,
                    })  # fmt: skip
    return rows


def plot(rows: list[dict], config: DispersionConfig, path: Path, num_points: int = 500) -> None:
    """Fig. 4 in two dimensions: the deterministic and the random points of the room frustum (pyramid transform),
    seen from above (x across, depth z up), with their measured dispersion where ``rows`` has it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bounds = reference_tangent_bounds("room")
    units = {"deterministic (Frolov)": frolov_lattice(num_points), "random (seed 0)": random_points(num_points, 0)}
    room = [r for r in rows if (r["frustum"], r["transform"]) == ("room", "pyramid")]
    measured = {(r["sampler"], r["L"]): r["dispersion"] for r in room}
    figure, axes = plt.subplots(1, 2, figsize=(9, 4.5), sharey=True)
    for axis, (label, unit) in zip(axes, units.items(), strict=True):
        points = sample_frustum(unit, bounds, config.t_near, config.t_far, "pyramid").contracted[0]
        axis.scatter(points[:, 0], points[:, 2], s=4, color="red")
        sampler = label.split(" ")[0]
        value, mean = measured.get((sampler, num_points)), " (mean of the seeds)" if sampler == "random" else ""
        axis.set_title(f"{label}, L = {num_points}" + ("" if value is None else f"\ndispersion {value:.3f}{mean}"))
        axis.set(xlabel="x (contracted)", aspect="equal")
    axes[0].set_ylabel("z, depth (contracted)")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def summary(rows: list[dict]) -> list[dict]:
    """One line per frustum, transform and L: the deterministic and the random dispersion and their ratio."""
    keyed = {(r["frustum"], r["transform"], r["L"], r["sampler"]): r["dispersion"] for r in rows}
    lines = []
    for (frustum, transform, num_points, sampler), value in keyed.items():
        random = keyed.get((frustum, transform, num_points, "random"))
        if sampler == "deterministic" and random is not None:
            lines.append({"frustum": frustum, "transform": transform, "L": num_points, "deterministic": value,
                          "random": random, "ratio": value / random})  # fmt: skip
    return lines


def report(rows: list[dict], config: DispersionConfig) -> Path:
    """Write <output_dir>/dispersion.md (the summary and every row) and the Fig. 4 plot."""
    config = config.effective()
    plot(rows, config, config.output_dir / "dispersion-fig4.png")
    protocol = (
        "Dispersion = radius of the largest empty ball whose centre lies in the contracted frustum of the transform "
        f"(contracted radius in [{config.t_near}, {config.t_far}]); the ball may stick out of the frustum. Computed "
        "by branch and bound over frustum-parameter cells (`benchmarks/s2camp_bench/dispersion_bound.py`): the "
        "value is attained at a point of the frustum, and the true dispersion lies in [dispersion, dispersion + "
        "error_bound] to first order in the final cell size. 'random' = uniform random points in the cube through "
        f"the same transform, the mean over seeds {list(config.seeds)} (std over the seeds)."
    )
    sections = [
        "## Summary",
        markdown_table(summary(rows), ["frustum", "transform", "L", "deterministic", "random", "ratio"],
                       ["frustum", "transform", "L", "deterministic", "random (mean)", "det / random"]),  # fmt: skip
        protocol,
        "![Fig. 4](dispersion-fig4.png)",
        "## All rows",
        markdown_table(rows, ["frustum", "transform", "sampler", "L", "dispersion", "dispersion_std", "error_bound"]),
    ]
    command = "s2camp-bench dispersion" + (" --quick" if config.quick else "")
    title = "Dispersion of frustum samples (paper Table 1)"
    return write_report(config.output_dir, "dispersion", title, command, sections)
