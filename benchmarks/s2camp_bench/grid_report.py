"""What the reports of a grid of runs (``grid``) share: spreads over seeds, the seeds cell, the report order, and the
rows of names a benchmark no longer runs (kept in its committed rows file and reported apart)."""

from __future__ import annotations

import statistics
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass


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
    entries: Iterable[dict], scenes: Sequence[str], starts: Sequence[str], variants: Sequence[str],
    then: Sequence[str] = (),
) -> list[dict]:
    """``entries`` (dicts with "scene", "start" and "variant") sorted by scene, start and variant, each in the order
    the benchmark lists its names (names it no longer lists after them, alphabetically), then by the keys ``then``."""

    def position(names: Sequence[str]) -> Callable[[str], tuple[int, str]]:
        index = {name: i for i, name in enumerate(names)}
        return lambda name: (index.get(name, len(index)), name)

    scene, start, variant = position(scenes), position(starts), position(variants)
    key = lambda e: (scene(e["scene"]), start(e["start"]), variant(e["variant"]), *(e[k] for k in then))  # noqa: E731
    return sorted(entries, key=key)


def split_runnable(entries: Sequence[dict], variants: Sequence[str], starts: Sequence[str]) -> tuple[list, list]:
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
