"""TEMPORARY STUB by the lead so other modules import; helper A replaces this file entirely."""

from __future__ import annotations

import torch


def unit_cube_points(kind: str, num_points: int, seed: int = 0) -> torch.Tensor:
    if kind in ("sobol", "frolov", "halton"):
        engine = torch.quasirandom.SobolEngine(3, scramble=True, seed=seed)
        return engine.draw(num_points, dtype=torch.float64)
    return torch.rand(num_points, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
