"""The regime stage: do the images add to the tracks at real resolution?

One ``ns-train s2camp`` run of about ``regime_passes`` passes over the training pixels (steps x rays / training
pixels) of the check's scene (640x480) with nerfacto's own field, from CamP's perturbation of the training cameras,
beside the same evidence alone (tracks made from the images with the perturbed cameras; the true cameras only
measure): ``tracks-alone`` (``--pipeline.model.camera-optimizer.photometric False``: every camera at its track
prior's anchor, read after set-up, first) and ``images-alone`` (``train_commands.PHOTOMETRIC_ONLY``, after s2camp, in
the time left). The variants run in one process (``measured_train``), each appending its camera errors every
``errors_every`` steps to ``errors/<variant>.jsonl`` as it goes; training stops cleanly before the deadline. The
report's section (``regime_section``) is built from those files, for a cut run too.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from s2camp_bench.report import markdown_table
from s2camp_bench.train_commands import PHOTOMETRIC_ONLY

from .config import CheckFolder, GpuCheckConfig
from .measured_train import TrainPlan, TrainSpec
from .processes import Deadline, failure, run_logged
from .records import StageResult
from .run_logs import REFINED, START, read_camera_errors
from .timing import PERTURBED, cpu_arguments, run_arguments

VARIANT_ARGUMENTS = {
    "tracks-alone": ["--pipeline.model.camera-optimizer.photometric", "False"],
    "s2camp": [],
    "images-alone": PHOTOMETRIC_ONLY,
}
"""Options beyond s2camp's defaults (the tracks and the images as evidence)."""
LABELS = {"s2camp": "s2camp (tracks and images)", "images-alone": "images alone"}


def variant_arguments(config: GpuCheckConfig, variant: str, scene: Path) -> list[str]:
    """``ns-train s2camp`` of one variant: the method's defaults, nerfacto's own field (``--cpu-smoke``: the small one
    on the CPU), the run's length and ray batch, no camera errors of its own, the variant's options, the perturbed
    start."""
    return [
        "s2camp", *run_arguments(scene, config.output_dir / "ns-train", "regime", variant, config.regime_steps),
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.regime_rays),
        "--pipeline.model.camera-error-every", "0", *cpu_arguments(config.cpu_smoke), *VARIANT_ARGUMENTS[variant],
        *PERTURBED,
    ]  # fmt: skip


def run_regime(config: GpuCheckConfig, scene: Path, deadline: Deadline, reserve_s: float) -> StageResult:
    """The variants in one ``measured_train`` process, in ``REGIME_VARIANTS`` order, until they end or ``reserve_s``
    before the deadline."""
    folder, began = config.folder, time.perf_counter()
    runs = []
    for variant in config.regime_variants:
        folder.errors_log(variant).unlink(missing_ok=True)
        arguments = variant_arguments(config, variant, scene)
        runs.append(TrainSpec(arguments, errors_log=str(folder.errors_log(variant)), errors_every=config.errors_every,
                              setup_only=variant == "tracks-alone"))  # fmt: skip
    plan = TrainPlan(runs, deadline.stop_at(reserve_s)).write(folder.root / "logs" / "plan-regime.json")
    log_path = folder.root / "logs" / "regime.log"
    timeout_s = deadline.limit(config.run_timeout_s)
    status = run_logged([sys.executable, "-m", "s2camp_bench.gpu_check.measured_train", str(plan)], log_path, timeout_s)
    last = {v: [r.step for r in read_camera_errors(folder.errors_log(v)) if r.label == REFINED] for v in LABELS}
    steps = ", ".join(f"{v} {s[-1] if s else 0} steps" for v, s in last.items() if v in config.regime_variants)
    detail = f"{steps} of {config.regime_steps}" if status == 0 else failure("training", status, log_path, timeout_s)
    return StageResult("regime", status == 0, detail, time.perf_counter() - began)


def error_rows(config: GpuCheckConfig, folder: CheckFolder) -> list[dict]:
    """The start, the tracks alone at their anchor, then s2camp and the images alone at every logged step (with the
    passes over the training pixels it stands for)."""

    def row(evidence: str, record, step: bool) -> dict:
        cell = lambda value, pattern: "-" if value is None else pattern.format(value)  # noqa: E731
        passes = record.step * config.regime_passes / config.regime_steps if step else None
        return {"evidence": evidence, "step": str(record.step) if step else "-", "passes": cell(passes, "{:.2f}"),
                "rot": cell(record.rot_err, "{:.4f}"), "pos": cell(record.pos_err, "{:.2e}"),
                "focal": cell(record.focal_err, "{:.3f}"), "drift": cell(record.drift_px, "{:.3f}")}  # fmt: skip

    logs = {variant: read_camera_errors(folder.errors_log(variant)) for variant in VARIANT_ARGUMENTS}
    starts = [record for records in logs.values() for record in records if record.label == START]
    rows = [row("start (CamP's perturbation)", starts[0], False)] if starts else []
    anchor = [record for record in logs["tracks-alone"] if record.label == REFINED]
    if anchor:
        rows.append(row("tracks alone (the track prior's anchor, no training)", anchor[-1], False))
    for variant, label in LABELS.items():
        rows += [row(label, record, True) for record in logs[variant] if record.label == REFINED]
    return rows


def regime_section(config: GpuCheckConfig, folder: CheckFolder) -> list[str]:
    """The report's section: what ran, and the camera errors table (none if nothing was logged)."""
    rows = error_rows(config, folder)
    if not rows:
        return []
    s = config.scene
    text = (
        f"`ns-train s2camp` with nerfacto's own field on the scene ({s.num_cameras} images {s.width}x{s.height}) from "
        f"CamP's perturbation: {config.regime_steps} steps of {config.regime_rays} rays, {config.regime_passes:g} "
        "pass(es) over the training pixels; beside it the same evidence alone (module docstring of "
        f"`benchmarks/s2camp_bench/gpu_check/regime.py`). Errors every {config.errors_every} steps after a similarity "
        "alignment to the true cameras: rotation (deg), position (scene units), focal (px), drift (px)."
    )
    columns = ["evidence", "step", "passes", "rot", "pos", "focal", "drift"]
    headers = ["evidence", "step", "passes", "rotation err (deg)", "position err", "focal err (px)", "drift (px)"]
    return ["## The regime at real resolution", text, markdown_table(rows, columns, headers)]
