"""Dispersion benchmark (paper Table 1 and Fig. 4): deterministic Frolov lattice vs random sampling.

For each reference frustum ("room": mip-NeRF 360 room camera at 1/4 resolution; "wide": 90 degree horizontal
field of view, 3:2), each transform ("pyramid", "spherical") and each L, the dispersion (radius of the largest
empty ball with centre in the contracted frustum, computed by
:func:`s2camp_bench.dispersion_bound.dispersion` with an upper bound) is measured for

- ``deterministic``: the Frolov lattice of :func:`s2camp_ns.core.lattice.frolov_lattice` through the transform,
- ``random``: uniform random points in the cube through the same transform (uniform in the frustum volume),
  mean over the seeds,
- ``camp``: a CamP-like random baseline (uniform pixel, uniform contracted distance along the ray), pyramid only;
  CamP's published sampler (power-ladder distances out to 1000, no contraction; s2camp_ns/core/camp_sampling.py)
  does not fill this normalized frustum, so its angular measure is kept with a radial measure that does,

and compared with the covering radius of the ideal body-centred cubic lattice of the same density.
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
from .dispersion_bound import covering_bound, dispersion, reference_tangent_bounds, transform_volume


@dataclass
class DispersionConfig:
    """Dispersion of deterministic vs random frustum samples (paper Table 1, Fig. 4)."""

    frusta: tuple[str, ...] = ("room", "wide")
    """Reference frusta (``reference_tangent_bounds``; same cameras as benchmarks/s2camp_bench/common.py FRUSTA)."""
    transforms: tuple[str, ...] = ("pyramid", "spherical")
    num_points: tuple[int, ...] = (100, 500, 5000)
    """Values of L."""
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    """Seeds of the random baselines."""
    t_near: float = 0.0
    """Near contracted radius; 0 puts the frustum apex on the camera centre, as in the paper's figures."""
    t_far: float = 1.99
    relative_tol: float = 0.01
    """Stop refining when the dispersion upper bound is within this fraction of the covering bound."""
    include_camp: bool = True
    """Also measure the CamP-like non-uniform random baseline (pyramid transform only)."""
    quick: bool = False
    """Small run for CI: room frustum, pyramid, L = 100 and 500, two seeds."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    """Write <output_dir>/dispersion.md and dispersion-fig4.png."""
    json: bool = False
    """Print one JSON object {"rows": [...]} on stdout."""

    def effective(self) -> DispersionConfig:
        if not self.quick:
            return self
        return replace(self, frusta=("room",), transforms=("pyramid",), num_points=(100, 500), seeds=(0, 1))


def _measure(
    points: torch.Tensor, bounds: torch.Tensor, config: DispersionConfig, transform: str, bound: float
) -> tuple[float, float]:
    result = dispersion(points, bounds, config.t_near, config.t_far, transform, tol=config.relative_tol * bound)
    return float(result.value[0]), float(result.error_bound[0])


def _row(
    frustum: str,
    transform: str,
    sampler: str,
    num_points: int,
    values: list[float],
    errors: list[float],
    bound: float,
    seeds: list[int],
) -> dict:
    mean = statistics.fmean(values)
    return {
        "frustum": frustum,
        "transform": transform,
        "sampler": sampler,
        "L": num_points,
        "dispersion": mean,
        "dispersion_std": statistics.pstdev(values) if len(values) > 1 else 0.0,
        "covering_bound": bound,
        "ratio_to_bound": mean / bound,
        "error_bound": max(errors),
        "seeds": seeds,
    }


def run(config: DispersionConfig) -> list[dict]:
    """Measure all (frustum, transform, sampler, L) combinations; one row each (random rows are seed means)."""
    config = config.effective()
    rows: list[dict] = []
    for frustum in config.frusta:
        bounds = reference_tangent_bounds(frustum)
        for transform in config.transforms:
            volume = float(transform_volume(bounds, config.t_near, config.t_far, transform)[0])
            for num_points in config.num_points:
                bound = float(covering_bound(volume, num_points))

                def in_frustum(unit: torch.Tensor, bounds=bounds, transform=transform) -> torch.Tensor:
                    return sample_frustum(unit, bounds, config.t_near, config.t_far, transform).contracted

                log(f"dispersion: {frustum} {transform} L={num_points}")
                value, error = _measure(in_frustum(frolov_lattice(num_points)), bounds, config, transform, bound)
                rows.append(_row(frustum, transform, "deterministic", num_points, [value], [error], bound, []))
                labels = ["random", "camp"] if config.include_camp and transform == "pyramid" else ["random"]
                for label in labels:
                    measured = []
                    for seed in config.seeds:
                        if label == "random":
                            points = in_frustum(random_points(num_points, seed))
                        else:
                            # Random (pixel, pixel, distance) draws as (u3, u2, u1) of the "pixel" / "ray" maps.
                            generator = torch.Generator().manual_seed(seed)
                            draws = torch.rand((1, num_points, 3), generator=generator, dtype=torch.float64)
                            draws = draws[..., [2, 1, 0]]
                            points = sample_frustum(draws, bounds, config.t_near, config.t_far, "pixel", "ray")
                            points = points.contracted
                        measured.append(_measure(points, bounds, config, transform, bound))
                    values, errors = [m[0] for m in measured], [m[1] for m in measured]
                    rows.append(_row(frustum, transform, label, num_points, values, errors, bound, list(config.seeds)))
    return rows


def fig4_samples(
    t_near: float = 0.0, t_far: float = 1.99, num_points: int = 500, seed: int = 0, transform: str = "pyramid"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Contracted room-frustum samples for Fig. 4: (deterministic [L, 3], uniform random [L, 3])."""
    bounds = reference_tangent_bounds("room")
    det = sample_frustum(frolov_lattice(num_points), bounds, t_near, t_far, transform).contracted[0]
    rnd = sample_frustum(random_points(num_points, seed), bounds, t_near, t_far, transform).contracted[0]
    return det, rnd


def _frustum_edges(bounds: torch.Tensor, t_far: float, steps: int = 32) -> list[torch.Tensor]:
    """Polylines of the pinhole frustum outline (4 side edges and the far-cap border), contracted space."""
    a0, a1, b0, b1 = bounds[0].tolist()
    lines = []
    for a, b in [(a0, b0), (a0, b1), (a1, b0), (a1, b1)]:
        d = torch.nn.functional.normalize(torch.tensor([a, b, 1.0], dtype=torch.float64), dim=0)
        lines.append(torch.stack([torch.zeros(3, dtype=torch.float64), t_far * d]))
    s = torch.linspace(0.0, 1.0, steps, dtype=torch.float64)
    for a_fn, b_fn in [
        (lambda s: a0 + s * (a1 - a0), lambda s: torch.full_like(s, b0)),
        (lambda s: a0 + s * (a1 - a0), lambda s: torch.full_like(s, b1)),
        (lambda s: torch.full_like(s, a0), lambda s: b0 + s * (b1 - b0)),
        (lambda s: torch.full_like(s, a1), lambda s: b0 + s * (b1 - b0)),
    ]:
        d = torch.nn.functional.normalize(torch.stack([a_fn(s), b_fn(s), torch.ones_like(s)], dim=-1), dim=-1)
        lines.append(t_far * d)
    return lines


def plot(
    rows: list[dict] | None,
    deterministic: torch.Tensor,
    random: torch.Tensor,
    out_png: Path | str,
    t_far: float = 1.99,
    frustum: str = "room",
) -> Path:
    """Fig. 4 style 3-D scatter: (a) deterministic and (b) random samples in the contracted room frustum.

    ``rows`` (optional) supplies the measured dispersion for the subplot titles.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    bounds = reference_tangent_bounds(frustum)
    num_points = deterministic.shape[0]
    titles = {"deterministic": "(a) deterministic (Frolov)", "random": "(b) random"}
    for row in rows or []:
        same = row["frustum"] == frustum and row["transform"] == "pyramid" and row["L"] == num_points
        if same and row["sampler"] in titles:
            titles[row["sampler"]] += f"\ndispersion {row['dispersion']:.3f}"
    fig = plt.figure(figsize=(11, 5))
    for index, (name, points) in enumerate([("deterministic", deterministic), ("random", random)]):
        ax = fig.add_subplot(1, 2, index + 1, projection="3d")
        for line in _frustum_edges(bounds, t_far):
            ax.plot(line[:, 0], line[:, 2], -line[:, 1], color="green", linewidth=0.8)
        p = points.detach().cpu()
        # Plot (x, z, -y): depth to the back, image-up upwards.
        ax.scatter(p[:, 0], p[:, 2], -p[:, 1], marker="*", color="red", s=8)
        ax.set_xlabel("x")
        ax.set_ylabel("z (depth)")
        ax.set_zlabel("-y")
        ax.set_title(f"{titles[name]}  (L = {num_points})")
        ax.set_box_aspect((2.0, 2.0, 1.4))
        ax.view_init(elev=22, azim=-50)
    fig.tight_layout()
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
    return out_png


def format_table(rows: list[dict]) -> str:
    """Markdown table: one line per (frustum, transform, L) with deterministic / random / camp values."""
    lines = [
        "| frustum | transform | L | deterministic | random (mean) | camp (mean) | det / random | det / bound | "
        "random / bound | BCC bound |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    keyed = {(r["frustum"], r["transform"], r["L"], r["sampler"]): r for r in rows}
    for (frustum, transform, num_points, sampler), det in keyed.items():
        if sampler != "deterministic":
            continue
        rnd = keyed.get((frustum, transform, num_points, "random"))
        camp = keyed.get((frustum, transform, num_points, "camp"))
        camp_text = f"{camp['dispersion']:.4f}" if camp else "-"
        lines.append(
            f"| {frustum} | {transform} | {num_points} | {det['dispersion']:.4f} | {rnd['dispersion']:.4f} | "
            f"{camp_text} | {det['dispersion'] / rnd['dispersion']:.3f} | {det['ratio_to_bound']:.3f} | "
            f"{rnd['ratio_to_bound']:.3f} | {det['covering_bound']:.4f} |"
        )
    return "\n".join(lines)


def report(rows: list[dict], config: DispersionConfig) -> Path:
    """Write <output_dir>/dispersion.md (summary and all rows) and the Fig. 4 scatter."""
    config = config.effective()
    png = config.output_dir / "dispersion-fig4.png"
    deterministic, random = fig4_samples(config.t_near, config.t_far)
    plot(rows, deterministic, random, png, t_far=config.t_far)
    protocol = (
        "Dispersion = radius of the largest empty ball whose centre lies in the contracted frustum of the transform "
        f"(contracted radius in [{config.t_near}, {config.t_far}]); the ball may stick out of the frustum. Computed "
        "by branch and bound over frustum-parameter cells (benchmarks/s2camp_bench/dispersion_bound.py); the true value lies in "
        "[dispersion, dispersion + error_bound] to first order in the final cell size. covering_bound = covering "
        "radius of the ideal body-centred cubic lattice with L points in the frustum volume (no boundary). "
        "'random' = uniform random points in the cube through the same transform, 'camp' = CamP-like random pixel and "
        "uniform contracted distance (CamP's published sampler reaches distance 1000 with a power ladder and is "
        f"not confined to this frustum); both averaged over seeds {list(config.seeds)}."
    )
    columns = [
        "frustum",
        "transform",
        "sampler",
        "L",
        "dispersion",
        "dispersion_std",
        "covering_bound",
        "ratio_to_bound",
        "error_bound",
    ]
    return write_report(
        config.output_dir,
        "dispersion",
        "Dispersion of frustum samples (paper Table 1)",
        "s2camp-bench dispersion",
        [
            "## Summary",
            format_table(rows),
            protocol,
            f"![Fig. 4]({png.name})",
            "## All rows",
            markdown_table(rows, columns),
        ],
    )


if __name__ == "__main__":
    import tyro

    result = run(tyro.cli(DispersionConfig))
    print(format_table(result))
