"""A training step of ``ns-train s2camp`` is short to follow: the files of ours whose functions run in one step.

nerfstudio's Trainer built as ``ns-train`` builds it (``benchmarks/s2camp_bench/step_cost.py``), on the session's tiny PINHOLE
scene, with the viewer panel's per-step callback attached; a profiler hook records every function call of one step
after three uncounted ones. docs/ARCHITECTURE.md lists the same files in the order they run.
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import pytest

import s2camp_ns

PACKAGE = Path(s2camp_ns.__file__).resolve().parent
MOST_FILES = 8
"""The most files of ours a training step may run."""


def files_run_by(function) -> list[str]:
    """The package's files (relative to its parent) with a function call while ``function`` runs."""
    seen: set[str] = set()

    def profile(frame, event, arg) -> None:
        if event == "call":
            path = Path(frame.f_code.co_filename)
            if path.is_relative_to(PACKAGE):
                seen.add(str(path.relative_to(PACKAGE.parent)))

    threading.setprofile(profile)
    sys.setprofile(profile)
    try:
        function()
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    return sorted(seen)


@pytest.mark.parametrize("method", ["s2camp", "s2camp-splat"])
def test_one_training_step_runs_at_most_eight_files_of_ours(method: str, tiny_scene: Path, tmp_path: Path) -> None:
    from s2camp_bench.step_cost import attach_viewer_stand_in, build_trainer, training_step

    trainer = build_trainer(method, tiny_scene, tmp_path, "per-camera", rays_per_batch=256)
    assert attach_viewer_stand_in(trainer)
    for step in range(3):
        training_step(trainer, step)
    files = files_run_by(lambda: training_step(trainer, 3))
    assert "s2camp_ns/core/refiner.py" in files and "s2camp_ns/core/track_prior.py" in files  # the hook sees ours
    assert len(files) <= MOST_FILES, ", ".join(files)
