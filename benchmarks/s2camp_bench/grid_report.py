"""What the reports of a grid of runs (``grid``) share: spreads over seeds, the seeds cell, the report order, the
rows of names a benchmark no longer runs (kept in its committed rows file and reported apart), and the plot."""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Spread:
    """Mean, min and max of one metric over seeds."""

    mean: float
    low: float
    high: float
    count: int

    @classmethod
    def of(cls, values: list[float]) -> Spread:
        return cls(statistics.fmean(values), min(values), max(values), len(values))

    @property
    def width(self) -> float:
        return self.high - self.low

    def cell(self, digits: int = 3) -> str:
        if self.count == 1:
            return f"{self.mean:.{digits}g}"
        return f"{self.mean:.{digits}g} [{self.low:.{digits}g}, {self.high:.{digits}g}]"


def seeds_cell(seeds: list[int]) -> str:
    """The number of runs; a seed run more than once (ns-train on a CPU is not bit-reproducible, so a repeat is
    another sample, not a copy) is named, so that the count is never read as that many distinct seeds."""
    repeated = sorted({seed for seed in seeds if seeds.count(seed) > 1})
    if not repeated:
        return str(len(seeds))
    names = ", ".join(f"{seed} x{seeds.count(seed)}" for seed in repeated)
    return f"{len(seeds)} runs, {len(set(seeds))} seeds (seed {names})"


def in_report_order(
    entries: Iterable[dict],
    scenes: Sequence[str],
    starts: Sequence[str],
    variants: Sequence[str],
    then: Sequence[str] = (),
) -> list[dict]:
    """``entries`` (dicts with "scene", "start" and "variant") sorted by scene, start and variant, each in the order
    the benchmark lists its names (names it no longer lists after them, alphabetically), then by the keys ``then``."""

    def position(names: Sequence[str]) -> Callable[[str], tuple[int, str]]:
        index = {name: i for i, name in enumerate(names)}
        return lambda name: (index.get(name, len(index)), name)

    scene, start, variant = position(scenes), position(starts), position(variants)
    return sorted(
        entries,
        key=lambda e: (scene(e["scene"]), start(e["start"]), variant(e["variant"]), *(e[key] for key in then)),
    )


def split_runnable(
    entries: Sequence[dict], variants: Sequence[str], starts: Sequence[str]
) -> tuple[list[dict], list[dict]]:
    """``entries`` (dicts with "variant" and "start") split into those this code can still run (variant in
    ``variants`` and start in ``starts``) and the others, committed rows of names that no longer run; each part in
    the given order."""
    current = [entry for entry in entries if entry["variant"] in variants and entry["start"] in starts]
    old = [entry for entry in entries if not (entry["variant"] in variants and entry["start"] in starts)]
    return current, old


NO_LONGER_RUN_HEADING = "## Rows of variants no longer run"


def no_longer_run_section(table: str) -> list[str]:
    """The report's section of the rows whose variant or start no longer runs (``table``: their results table);
    what each name ran is in docs/RESULTS.md, "Names that no longer run"."""
    text = (
        "Rows of the committed rows file whose variant or start this code no longer runs (its name is no longer "
        'accepted); what each name ran: docs/RESULTS.md, "Names that no longer run". Columns as in the results '
        "above; the comparisons with other rows are computed over every row, these included."
    )
    return [NO_LONGER_RUN_HEADING, text, table]


def plot(summary: list[dict], path: Path) -> None:
    """Held-out PSNR and drift (``Spread`` entries "psnr" and "drift_px") per variant and start, one column per scene,
    error bars from the seed range."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(entry["scene"] for entry in summary))
    variants = list(dict.fromkeys(entry["variant"] for entry in summary))
    starts = list(dict.fromkeys(entry["start"] for entry in summary))
    keys = (("psnr", "held-out PSNR (dB)"), ("drift_px", "drift (px RMS)"))
    figure, axes = plt.subplots(len(keys), len(scenes), figsize=(4.2 * len(scenes), 6.0), squeeze=False)
    width = 0.8 / len(starts)
    for column, scene in enumerate(scenes):
        for row_index, (key, label) in enumerate(keys):
            axis = axes[row_index][column]
            # The first entry of each start and variant (reversed: the first one written last wins).
            by_name = {(e["start"], e["variant"]): e[key] for e in reversed(summary) if e["scene"] == scene}
            for offset, start in enumerate(starts):
                chosen = [by_name.get((start, variant)) for variant in variants]
                xs = [i + (offset - (len(starts) - 1) / 2) * width for i in range(len(variants))]
                means = [s.mean if s else math.nan for s in chosen]
                # Clamped: the mean of equal values can differ from them in the last bit.
                errors = [
                    [max(s.mean - s.low, 0.0) if s else 0.0 for s in chosen],
                    [max(s.high - s.mean, 0.0) if s else 0.0 for s in chosen],
                ]
                axis.bar(xs, means, width, yerr=errors, capsize=3, label=start)
            axis.set_xticks(range(len(variants)), variants, rotation=20, fontsize=8)
            axis.set_title(f"{scene}: {label}", fontsize=9)
            axis.grid(True, axis="y", alpha=0.3)
            if key == "psnr":
                axis.set_ylim(bottom=max(0.0, min(e["psnr"].low for e in summary if e["scene"] == scene) - 2.0))
        axes[0][column].legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
