"""``s2camp-eval``: PSNR / SSIM (/ LPIPS) of held-out views after test-time camera alignment (CamP's protocol).

After joint refinement the field's frame differs from the given cameras' (a similarity, plus what the field
absorbed), which ``ns-eval`` would measure too. This aligns every held-out camera first (``test_time_alignment``) and
reports the metrics before and after, for runs of s2camp, s2camp-camp, s2camp-so3xr3, s2camp-splat and
s2camp-splat-so3xr3. Progress goes to stderr (a line per view), the table of results and the protocol (``protocol``,
also in the JSON) to stdout. Loading does no track work (``method.pipeline``).

    s2camp-eval --load-config outputs/room/s2camp/<timestamp>/config.yml --output-path aligned.json
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from s2camp_ns.scripts.test_time_alignment import AlignedView, AlignmentConfig, evaluate_held_out_views
from s2camp_ns.tracks.build_progress import duration_text

CONSOLE = Console()
LOG = Console(stderr=True)
"""What the command is doing (stderr; the results go to ``CONSOLE``)."""


@dataclass
class EvalAlignedConfig:
    """Evaluate held-out views of a trained S2CamP run after test-time camera alignment."""

    load_config: Path
    """config.yml of the run (as for ns-eval)."""
    output_path: Path | None = None
    """Write the per-view and mean metrics here as JSON."""
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    """Camera-only optimisation of each held-out view."""


def protocol(alignment: AlignmentConfig) -> str:
    """The evaluation protocol in words (``test_time_alignment``), with the run's settings."""
    focal = " and a log focal scale" if alignment.refine_focal else ""
    return (
        "every held-out view: its camera mapped into the field's frame by the similarity taking the reference "
        "training-camera centres onto the refined ones (focal length scaled by their median ratio), then "
        f"{alignment.steps} seeded Adam steps (lr {alignment.lr:g} to {alignment.lr_final:g}) on a local se(3) "
        f"twist{focal} minimising the photometric MSE of that view against the frozen field; PSNR / SSIM / LPIPS "
        "of the full image through the aligned camera ('PSNR before': through the mapped camera, no steps). "
        "ns-eval scores the views unaligned."
    )


def _mean(values: list[float]) -> float:
    finite = [value for value in values if not math.isnan(value)]
    return sum(finite) / len(finite) if finite else math.nan


def _load(load_config: Path):
    """(pipeline, checkpoint, step) of the run by ``eval_setup`` (its output hidden)."""
    LOG.print(f"[dim]s2camp-eval: loading {load_config} (scene, checkpoint)", highlight=False)
    began = time.perf_counter()
    captured = io.StringIO()
    with contextlib.redirect_stdout(captured), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from nerfstudio.utils.eval_utils import eval_setup

        _, pipeline, checkpoint, step = eval_setup(load_config, test_mode="test")
    if not hasattr(pipeline.model, "refined_train_cameras"):
        raise ValueError(
            f"{load_config} is not a run of s2camp, s2camp-camp, s2camp-so3xr3, s2camp-splat or "
            "s2camp-splat-so3xr3 (its model has no refined training cameras)"
        )
    LOG.print(f"[dim]loaded step {step} in {duration_text(time.perf_counter() - began)}", highlight=False)
    return pipeline, checkpoint, step


def _aligned_views(pipeline, alignment: AlignmentConfig) -> list[AlignedView]:
    """``evaluate_held_out_views`` with a line per view done (and a bar on a terminal) on ``LOG``."""
    began = time.perf_counter()
    LOG.print(f"[dim]aligning the held-out views: {alignment.steps} camera-only steps each", highlight=False)
    progress = Progress(
        TextColumn("[dim]aligning"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
        console=LOG, transient=True, disable=not LOG.is_terminal,
    )  # fmt: skip
    total = len(pipeline.datamanager.eval_dataset)
    scored: list[AlignedView] = []

    def view_done(view: AlignedView) -> None:
        scored.append(view)
        LOG.print(
            f"[dim]  view {len(scored)}/{total} (eval image {view.index}): PSNR {view.psnr_unaligned:.2f} -> "
            f"{view.psnr:.2f} dB aligned ({duration_text(time.perf_counter() - began)})",
            highlight=False,
        )

    with progress:
        task = progress.add_task("align", total=None)
        views = evaluate_held_out_views(
            pipeline, alignment, lambda done, all_work: progress.update(task, completed=done, total=all_work), view_done
        )
    LOG.print(f"[dim]aligned {len(views)} views in {duration_text(time.perf_counter() - began)}", highlight=False)
    return views


def main(config: EvalAlignedConfig) -> dict:
    if not config.load_config.is_file():
        raise ValueError(f"load_config must be an existing config.yml, got {str(config.load_config)!r}")
    config.alignment.validate()
    pipeline, checkpoint, step = _load(config.load_config)
    views = _aligned_views(pipeline, config.alignment)
    table = Table(title=f"held-out views of {config.load_config.parent} (step {step})", title_justify="left")
    for column in ("view", "PSNR before", "PSNR", "SSIM", "LPIPS"):
        table.add_column(column, justify="right")
    for view in views:
        table.add_row(str(view.index), f"{view.psnr_unaligned:.2f}", f"{view.psnr:.2f}", f"{view.ssim:.4f}",
                      f"{view.lpips:.4f}")  # fmt: skip
    summary = {
        key: _mean([getattr(view, key) for view in views]) for key in ("psnr", "ssim", "lpips", "psnr_unaligned")
    }
    table.add_row("mean", f"{summary['psnr_unaligned']:.2f}", f"{summary['psnr']:.2f}", f"{summary['ssim']:.4f}",
                  f"{summary['lpips']:.4f}", end_section=True)  # fmt: skip
    CONSOLE.print(table)
    stated = protocol(config.alignment)
    CONSOLE.print(f"[dim]Protocol: {stated} LPIPS is NaN where its weights are not cached.")
    result = {
        "config": str(config.load_config),
        "checkpoint": str(checkpoint),
        "step": step,
        "protocol": stated,
        "alignment": asdict(config.alignment),
        "mean": summary,
        "views": [asdict(view) for view in views],
    }
    if config.output_path is not None:
        config.output_path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps(result, indent=2).replace("NaN", "null")
        config.output_path.write_text(text)
        CONSOLE.print(f"[dim]written to {config.output_path}")
    return result


def entrypoint() -> None:
    config = tyro.cli(EvalAlignedConfig, description=__doc__)
    try:
        main(config)
    except ValueError as error:
        CONSOLE.print(f"[bold red]s2camp-eval: {error}")
        raise SystemExit(2) from None


if __name__ == "__main__":
    entrypoint()
