"""``python -m s2camp_bench.gpu_check.regime``: do the images add to the tracks at real resolution?

One ``ns-train s2camp`` run of about ``passes`` passes over the training pixels (passes = steps x rays / training
pixels) of the check's scene (images of 640x480) with nerfacto's own field, from CamP's perturbation of the training
cameras. Beside it, with the same evidence (tracks made from the images with the perturbed cameras; nothing made from
the true cameras feeds any method):

- ``tracks-alone``: ``--pipeline.model.camera-optimizer.photometric False``, every camera at its track prior's
  anchor; its errors are read straight after set-up, with no training (first);
- ``images-alone``: ``train_commands.PHOTOMETRIC_ONLY`` (no prior, no removal of the common rotation), trained like
  s2camp, after it, in the time left.

The variants run in one process (``measured_train``), each appending its camera errors against the true cameras
every ``errors_every`` steps to ``errors/<variant>.jsonl`` as it goes; training stops cleanly before ``--deadline``.
The report is built from those files when the process ends, and ``--report-from FOLDER`` rebuilds it for a run that
was cut: the figures logged so far are there either way.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import tyro

from s2camp_bench.report import markdown_table, write_report
from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import PHOTOMETRIC_ONLY, SMALL_MODEL
from s2camp_ns.core.validation import check_choice, check_positive_int

from .camera_error_log import REFINED, START, read_camera_errors
from .config import LEASE_SCENE, SMOKE_SCENE, STOP_RESERVE_S
from .environment import GpuCheckError, detect_environment, require_cuda
from .measured_train import TrainPlan, TrainSpec
from .processes import Deadline, failure, run_logged
from .records import StageResult, append_record, read_records
from .scene_stage import prepare_scene
from .timing import PERTURBED, run_arguments

COMMAND = "python -m s2camp_bench.gpu_check.regime"
EVAL_INTERVAL = 8
"""The data parser's held-out interval (every 8th image): the rest are the training images."""
VARIANTS = ("tracks-alone", "s2camp", "images-alone")
"""The runs, in the order they run."""
VARIANT_ARGUMENTS = {
    "s2camp": [],
    "tracks-alone": ["--pipeline.model.camera-optimizer.photometric", "False"],
    "images-alone": PHOTOMETRIC_ONLY,
}
"""Options beyond s2camp's defaults (the tracks and the images as evidence)."""
LABELS = {"s2camp": "s2camp (tracks and images)", "images-alone": "images alone"}


@dataclass
class RegimeConfig:
    """s2camp at about one pass over real-resolution images, beside the tracks alone and the images alone."""

    output_dir: Path = Path("outputs/regime")
    """Records, logs and the report ``regime.md`` go here."""
    scene_dir: Path | None = None
    """The scene folder (None: <output_dir>/scene). The GPU check's (``<its output>/scene``) is reused, image tracks
    included, when its settings are these."""
    scene: MakeSceneConfig = field(default_factory=lambda: replace(LEASE_SCENE))
    """The generated scene (s2camp-make-scene options)."""
    passes: float = 1.0
    """Passes over the training pixels: the run's steps are ceil(passes x training pixels / rays_per_batch)."""
    rays_per_batch: int = 4096
    """Training rays per step (nerfacto's default)."""
    errors_every: int = 250
    """Steps between camera errors."""
    variants: tuple[str, ...] = VARIANTS
    deadline: float | None = None
    """Seconds from the start by which the command must be done (training stops cleanly before); None: none."""
    run_timeout_minutes: float = 30.0
    """The training process taking longer than this is stopped."""
    report_from: Path | None = None
    """Run nothing: rebuild the report from the folder of an earlier run of this command, into output_dir."""
    cpu_smoke: bool = False
    """Test this command itself without a GPU: a small scene, the small nerfacto field, a few steps on the CPU. Its
    numbers mean nothing and its report says so."""

    def effective(self) -> RegimeConfig:
        """This configuration, or with ``cpu_smoke`` the smoke sizes where the command line left the defaults."""
        if not self.cpu_smoke:
            return self
        smoke = dict(scene=replace(self.scene, **SMOKE_SCENE), passes=0.02, rays_per_batch=256, errors_every=3)
        default = RegimeConfig()
        chosen = {key: value for key, value in smoke.items() if getattr(self, key) == getattr(default, key)}
        return replace(self, **chosen)

    def validate(self) -> None:
        if not self.variants or len(set(self.variants)) != len(self.variants):
            raise ValueError(f"variants must name each of {', '.join(VARIANTS)} at most once, got {self.variants!r}")
        for variant in self.variants:
            check_choice("variants", variant, VARIANTS)
        for name in ("rays_per_batch", "errors_every"):
            check_positive_int(name, getattr(self, name))
        for name in ("passes", "run_timeout_minutes"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a number > 0, got {value!r}")
        if self.deadline is not None and not self.deadline > 0:
            raise ValueError(f"deadline must be a number of seconds > 0 (or None: no deadline), got {self.deadline!r}")
        if self.report_from is not None and not (self.report_from / "runs.jsonl").is_file():
            raise ValueError(f"report_from must be the folder of an earlier regime run, got {str(self.report_from)!r}")

    @property
    def iterations(self) -> int:
        s = self.scene
        training_pixels = (s.num_cameras - math.ceil(s.num_cameras / EVAL_INTERVAL)) * s.width * s.height
        return math.ceil(self.passes * training_pixels / self.rays_per_batch)


def errors_log(root: Path, variant: str) -> Path:
    return root / "errors" / f"{variant}.jsonl"


def variant_arguments(config: RegimeConfig, variant: str, scene: Path) -> list[str]:
    """``ns-train s2camp`` of one variant: the method's defaults and nerfacto's own field (``--cpu-smoke``: the small
    one on the CPU), the run's length and ray batch, no camera errors of its own (they are logged here), the
    variant's options, the perturbed start."""
    cpu = ["--machine.device-type", "cpu", *SMALL_MODEL] if config.cpu_smoke else []
    return [
        "s2camp", *run_arguments(scene, config.output_dir / "ns-train", "regime", variant, config.iterations),
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.rays_per_batch),
        "--pipeline.model.camera-error-every", "0", *cpu, *VARIANT_ARGUMENTS[variant], *PERTURBED,
    ]  # fmt: skip


def train_variants(config: RegimeConfig, scene: Path, deadline: Deadline) -> StageResult:
    """The variants in one ``measured_train`` process, in ``VARIANTS`` order, until they end or the deadline nears."""
    runs = [
        TrainSpec(variant_arguments(config, variant, scene), errors_log=str(errors_log(config.output_dir, variant)),
                  errors_every=config.errors_every, setup_only=variant == "tracks-alone")
        for variant in VARIANTS if variant in config.variants
    ]  # fmt: skip
    plan = TrainPlan(runs, deadline.stop_at(STOP_RESERVE_S)).write(config.output_dir / "logs" / "plan.json")
    log_path = config.output_dir / "logs" / "train.log"
    timeout_s = deadline.limit(60.0 * config.run_timeout_minutes)
    began = time.perf_counter()
    status = run_logged([sys.executable, "-m", "s2camp_bench.gpu_check.measured_train", str(plan)], log_path, timeout_s)
    detail = f"ended; log {log_path}" if status == 0 else failure("training", status, log_path, timeout_s)
    return StageResult("training", status == 0, detail, time.perf_counter() - began)


def error_rows(config: RegimeConfig, root: Path) -> list[dict]:
    """Table rows: the start, the tracks alone at their anchor, then s2camp and the images alone at every logged
    step (with the passes over the training pixels it stands for)."""

    def row(evidence: str, record, step: bool) -> dict:
        cell = lambda value, pattern: "-" if value is None else pattern.format(value)  # noqa: E731
        passes = record.step * config.passes / config.iterations if step else None
        return {"evidence": evidence, "step": str(record.step) if step else "-", "passes": cell(passes, "{:.2f}"),
                "rot": cell(record.rot_err, "{:.4f}"), "pos": cell(record.pos_err, "{:.2e}"),
                "focal": cell(record.focal_err, "{:.3f}"), "drift": cell(record.drift_px, "{:.3f}")}  # fmt: skip

    logs = {variant: read_camera_errors(errors_log(root, variant)) for variant in VARIANTS}
    starts = [record for records in logs.values() for record in records if record.label == START]
    rows = [row("start (CamP's perturbation)", starts[0], False)] if starts else []
    anchor = [record for record in logs["tracks-alone"] if record.label == REFINED]
    if anchor:
        rows.append(row("tracks alone (the track prior's anchor, no training)", anchor[-1], False))
    for variant, label in LABELS.items():
        rows += [row(label, record, True) for record in logs[variant] if record.label == REFINED]
    return rows


def setup_text(config: RegimeConfig) -> str:
    s = config.scene
    smoke = "**CPU smoke run of the command itself (`--cpu-smoke`): the numbers mean nothing.** "
    return (smoke if config.cpu_smoke else "") + (
        f"`ns-train s2camp` with nerfacto's own field on a generated scene of {s.num_cameras} images "
        f"{s.width}x{s.height} (every 8th held out), from CamP's perturbation of the training cameras: "
        f"{config.iterations} steps of {config.rays_per_batch} rays, {config.passes:g} pass(es) over the training "
        "pixels, inside s2camp's camera warm-up (at least 2500 steps). Every variant has the same evidence: tracks "
        "made from the images with the perturbed cameras; the true cameras only measure. tracks alone: "
        "`--pipeline.model.camera-optimizer.photometric False`, read after set-up. images alone: "
        f"`train_commands.PHOTOMETRIC_ONLY`. Errors every {config.errors_every} steps, mean over the training "
        "cameras after a similarity alignment to the true ones: rotation (deg), position (scene units), focal (px), "
        "the RMS reprojection drift of the scene's points (px)."
    )


def build_report(config: RegimeConfig, root: Path, command: str) -> Path:
    """Write ``<output_dir>/regime.md`` from the records of the folder ``root``; return its path."""
    rows = error_rows(config, root)
    columns = ["evidence", "step", "passes", "rot", "pos", "focal", "drift"]
    headers = ["evidence", "step", "passes", "rotation err (deg)", "position err", "focal err (px)", "drift (px)"]
    runs = [{"run": r.name, "result": r.outcome, "seconds": "-" if r.seconds is None else f"{r.seconds:.0f}",
             "detail": r.detail} for r in read_records(root / "runs.jsonl", StageResult)]  # fmt: skip
    sections = [
        setup_text(config), "## Camera errors",
        markdown_table(rows, columns, headers) if rows else "No camera errors were logged.",
        "## Runs", markdown_table(runs, ["run", "result", "seconds", "detail"]) if runs else "No run has ended.",
    ]  # fmt: skip
    return write_report(config.output_dir, "regime", "The regime at real resolution", command, sections)


def run(config: RegimeConfig) -> bool:
    """Run the variants (module docstring); True when the scene and the training process ended as they should."""
    config = config.effective()
    config.validate()
    if config.report_from is not None:
        path = build_report(config, config.report_from, f"{COMMAND} --report-from {config.report_from.as_posix()}")
        print(path.read_text(), flush=True)
        return True
    deadline = Deadline.after(config.deadline)
    if not config.cpu_smoke:
        require_cuda(detect_environment())
    root = config.output_dir
    root.mkdir(parents=True, exist_ok=True)
    for path in (root / "runs.jsonl", *(errors_log(root, variant) for variant in VARIANTS)):
        path.unlink(missing_ok=True)  # an earlier run's, which this report must not show
    scene_dir = config.scene_dir if config.scene_dir is not None else root / "scene"
    print(">>> scene and image tracks", flush=True)
    results = [prepare_scene(config.scene, scene_dir, root / "logs" / "tracks.log", deadline)]
    append_record(root / "runs.jsonl", results[0])
    if results[0].passed:
        print(f">>> {', '.join(config.variants)}: {config.iterations} steps", flush=True)
        results.append(train_variants(config, scene_dir, deadline))
        append_record(root / "runs.jsonl", results[-1])
    path = build_report(config, root, COMMAND)
    print(path.read_text(), flush=True)
    return all(result.passed for result in results)


def main(config: RegimeConfig) -> int:
    try:
        passed = run(config)
    except (GpuCheckError, ValueError) as error:
        print(f"regime: {error}", flush=True)
        return 2
    return 0 if passed else 1


if __name__ == "__main__":
    raise SystemExit(main(tyro.cli(RegimeConfig, description=__doc__)))
