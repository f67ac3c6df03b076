"""A training step, file by file, as docs/ARCHITECTURE.md lists it: the files of ours whose functions run in one step.

nerfstudio's Trainer built as ``ns-train`` builds it (``benchmarks/s2camp_bench/step_cost.py``), on the session's tiny
PINHOLE scene, with the viewer panel's per-step callback attached; a profiler hook records every function call of one
step after three uncounted ones. The files must be exactly those the document lists for the method.
"""

from __future__ import annotations

import re
import sys
import threading
from pathlib import Path

import pytest

import s2camp_ns

PACKAGE = Path(s2camp_ns.__file__).resolve().parent
DOC = PACKAGE.parent / "docs" / "ARCHITECTURE.md"


def documented_files(method: str) -> list[str]:
    """The files docs/ARCHITECTURE.md lists for ``method`` (its bullet "- `method`: ...", continued on the lines
    indented under it)."""
    text = DOC.read_text(encoding="utf8")
    match = re.search(rf"^- `{re.escape(method)}`:(.*(?:\n  .*)*)", text, flags=re.MULTILINE)
    assert match is not None, f"docs/ARCHITECTURE.md lists no files for {method}"
    return sorted(re.findall(r"`(s2camp_ns/[\w/]+\.py)`", match.group(1)))


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
def test_one_training_step_runs_the_files_the_architecture_lists(method: str, tiny_scene: Path, tmp_path: Path):
    from s2camp_bench.step_cost import attach_viewer_stand_in, build_trainer, training_step

    trainer = build_trainer(method, tiny_scene, tmp_path, "per-camera", rays_per_batch=256)
    assert attach_viewer_stand_in(trainer)
    for step in range(3):
        training_step(trainer, step)
    files = files_run_by(lambda: training_step(trainer, 3))
    assert "s2camp_ns/core/refiner.py" in files  # the hook sees ours
    assert files == documented_files(method)
