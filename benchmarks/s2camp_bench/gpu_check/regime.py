"""``python -m s2camp_bench.gpu_check.regime``: do the images add to the tracks at real resolution?

One ``ns-train s2camp`` run of about ``passes`` passes over the training pixels (passes = steps x rays / training
pixels) of the check's scene (images of 640x480) with nerfacto's own field, from CamP's perturbation of the training
cameras. Beside it, with the same evidence (tracks made from the images with the perturbed cameras; nothing made from
the true cameras feeds any method):

- ``tracks-alone``: ``--pipeline.model.camera-optimizer.photometric False``, every camera at its track prior's
  anchor; its errors are read straight after set-up, with no training;
- ``images-alone``: ``train_commands.PHOTOMETRIC_ONLY`` (no prior, no removal of the common rotation), trained like
  s2camp: after it, or beside it with ``--concurrent`` (both then share the GPU).

Every run appends its camera errors against the true cameras every ``errors_every`` steps (``camera_error_log``),
and the report (``regime_report``) is rebuilt from those files every ``report_every_s`` seconds while the runs train,
so the figures are there even if the command is cut; ``--report-from FOLDER`` rebuilds it. Training stops cleanly
before ``--deadline``.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import tyro
from rich.console import Console

from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import PHOTOMETRIC_ONLY, SMALL_MODEL
from s2camp_ns.core.validation import check_choice, check_positive_int

from . import regime_report
from .config import LEASE_SCENE, STOP_RESERVE_S
from .environment import GpuCheckError, detect_environment, require_cuda
from .measured_train import TrainPlan, TrainSpec
from .processes import Deadline, start_logged, stop
from .records import StageResult, append_record, skipped
from .scene_stage import prepare_scene
from .train_arguments import PERTURBED, run_arguments

CONSOLE = Console()
EVAL_INTERVAL = 8
"""The data parser's held-out interval (every 8th image): the rest are the training images."""
MINIMUM_RUN_S = 60.0
"""The least time a training variant is started with (its set-up and the first logged errors)."""
VARIANTS = ("s2camp", "tracks-alone", "images-alone")
VARIANT_ARGUMENTS = {
    "s2camp": [],
    "tracks-alone": ["--pipeline.model.camera-optimizer.photometric", "False"],
    "images-alone": PHOTOMETRIC_ONLY,
}
"""Options beyond s2camp's defaults (the tracks and the images as evidence)."""


@dataclass(frozen=True)
class RegimeFolder:
    root: Path

    def errors_log(self, variant: str) -> Path:
        return self.root / "errors" / f"{variant}.jsonl"

    def steps_log(self, variant: str) -> Path:
        return self.root / "steps" / f"{variant}.jsonl"

    @property
    def runs_path(self) -> Path:
        """One ``StageResult`` per variant, appended as its process ends."""
        return self.root / "runs.jsonl"

    @property
    def logs_dir(self) -> Path:
        return self.root / "logs"

    @property
    def report_path(self) -> Path:
        return self.root / "regime.md"


@dataclass
class RegimeConfig:
    """s2camp at about one pass over real-resolution images, beside the tracks alone and the images alone."""

    output_dir: Path = Path("outputs/regime")
    """Errors, logs and the report ``regime.md`` go here."""
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
    """The runs: s2camp, tracks-alone (set-up only, beside the first training run), images-alone (after s2camp)."""
    concurrent: bool = False
    """Train images-alone beside s2camp (sharing the GPU) instead of after it."""
    deadline: float | None = None
    """Seconds from the start by which the command must be done (training stops cleanly before); None: none."""
    report_every_s: float = 20.0
    """Seconds between rebuilds of the report while the runs train."""
    run_timeout_minutes: float = 30.0
    """A run's process taking longer than this is stopped."""
    report_from: Path | None = None
    """Run nothing: rebuild the report from the folder of an earlier run of this command, into output_dir."""
    cpu_smoke: bool = False
    """Test this command itself without a GPU: a small scene, the small nerfacto field, a few steps on the CPU. Its
    numbers mean nothing and its report says so."""

    def effective(self) -> RegimeConfig:
        """This configuration, or with ``cpu_smoke`` the smoke sizes where the command line left the defaults."""
        if not self.cpu_smoke:
            return self
        scene = replace(self.scene, num_cameras=16, width=320, height=240, points_per_image=100)
        smoke = dict(scene=scene, passes=0.02, rays_per_batch=256, errors_every=3, report_every_s=2.0)
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
        for name in ("passes", "report_every_s", "run_timeout_minutes"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a number > 0, got {value!r}")
        if self.deadline is not None and not self.deadline > 0:
            raise ValueError(f"deadline must be a number of seconds > 0 (or None: no deadline), got {self.deadline!r}")
        if self.report_from is not None and not RegimeFolder(self.report_from).runs_path.parent.is_dir():
            raise ValueError(f"report_from must be the folder of an earlier regime run, got {str(self.report_from)!r}")

    @property
    def folder(self) -> RegimeFolder:
        return RegimeFolder(self.output_dir)

    @property
    def scene_folder(self) -> Path:
        return self.scene_dir if self.scene_dir is not None else self.output_dir / "scene"

    @property
    def training_pixels(self) -> int:
        s = self.scene
        return (s.num_cameras - math.ceil(s.num_cameras / EVAL_INTERVAL)) * s.width * s.height

    @property
    def iterations(self) -> int:
        return math.ceil(self.passes * self.training_pixels / self.rays_per_batch)


def variant_arguments(config: RegimeConfig, variant: str, scene: Path) -> list[str]:
    """``ns-train s2camp`` of one variant: the method's defaults and nerfacto's own field (``--cpu-smoke``: the small
    one on the CPU), the run's length and ray batch, no camera errors of its own (they are logged here), the
    variant's options, the perturbed start."""
    cpu = ["--machine.device-type", "cpu", *SMALL_MODEL] if config.cpu_smoke else []
    return [
        "s2camp",
        *run_arguments(scene, config.output_dir / "ns-train", "regime", variant, config.iterations),
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.rays_per_batch),
        "--pipeline.model.camera-error-every", "0",
        *cpu,
        *VARIANT_ARGUMENTS[variant],
        *PERTURBED,
    ]  # fmt: skip


@dataclass
class Launched:
    """A variant's process under way."""

    variant: str
    process: subprocess.Popen
    log_path: Path
    began: float


def launch(config: RegimeConfig, variant: str, scene: Path, stop_at: float | None) -> Launched:
    """Start one variant in a process of its own (``measured_train``), its errors and step times logged as it goes."""
    folder = config.folder
    spec = TrainSpec(
        variant_arguments(config, variant, scene),
        steps_log=str(folder.steps_log(variant)),
        errors_log=str(folder.errors_log(variant)),
        errors_every=config.errors_every,
        setup_only=variant == "tracks-alone",
    )
    plan = TrainPlan([spec], stop_at).write(folder.logs_dir / f"plan-{variant}.json")
    log_path = folder.logs_dir / f"{variant}.log"
    CONSOLE.print(f">>> {variant}: ns-train {' '.join(spec.arguments)}", highlight=False)
    command = [sys.executable, "-m", "s2camp_bench.gpu_check.measured_train", str(plan)]
    return Launched(variant, start_logged(command, log_path), log_path, time.perf_counter())


def watch(config: RegimeConfig, running: list[Launched], deadline: Deadline) -> None:
    """Wait for ``running``: the report rebuilt every ``report_every_s`` with a progress line, each variant recorded
    as it ends, those still running at the deadline or past their time limit stopped."""
    limit_s = 60.0 * config.run_timeout_minutes
    while running:
        time.sleep(max(0.5, min(config.report_every_s, deadline.remaining())))
        for launched in list(running):
            status = launched.process.poll()
            overdue = time.perf_counter() - launched.began > limit_s or deadline.remaining() <= 0
            if status is None and overdue:
                stop(launched.process)
            if status is not None or overdue:
                running.remove(launched)
                record_variant(config, launched, status)
        rebuild(config)
        CONSOLE.print(f"    {regime_report.progress(config.folder, VARIANTS)}", highlight=False)


def record_variant(config: RegimeConfig, launched: Launched, status: int | None) -> None:
    seconds = time.perf_counter() - launched.began
    if status == 0:
        result = StageResult(launched.variant, True, f"ended; log {launched.log_path}", seconds)
    elif status is None:
        result = StageResult(launched.variant, False, f"stopped at its limit; log {launched.log_path}", seconds)
    else:
        result = StageResult(launched.variant, False, f"exited with status {status}; log {launched.log_path}", seconds)
    append_record(config.folder.runs_path, result)
    CONSOLE.print(f"    {result.name}: {result.outcome}: {result.detail}", highlight=False)


def rebuild(config: RegimeConfig, folder: RegimeFolder | None = None, command: str | None = None) -> Path:
    return regime_report.build(config, folder or config.folder, command or regime_report.COMMAND)


def run_variants(config: RegimeConfig, deadline: Deadline) -> None:
    """tracks-alone beside s2camp (and images-alone with ``concurrent``), then images-alone while time remains."""
    stop_at = None if deadline.end is None else deadline.end - STOP_RESERVE_S
    later = [] if config.concurrent else ["images-alone"]
    first = [v for v in config.variants if v not in later]
    if first:
        watch(config, [launch(config, v, config.scene_folder, stop_at) for v in first], deadline)
    needs_s = STOP_RESERVE_S + MINIMUM_RUN_S
    for variant in (v for v in later if v in config.variants):
        if deadline.allows(needs_s):
            watch(config, [launch(config, variant, config.scene_folder, stop_at)], deadline)
        else:
            append_record(config.folder.runs_path, skipped(variant, needs_s, deadline.remaining()))


def run(config: RegimeConfig) -> bool:
    """Run the three variants (module docstring); True when every variant that ran ended as it should."""
    config = config.effective()
    config.validate()
    if config.report_from is not None:
        folder = RegimeFolder(config.report_from)
        path = rebuild(config, folder, f"{regime_report.COMMAND} --report-from {folder.root.as_posix()}")
        print(path.read_text(), flush=True)
        return True
    deadline = Deadline.after(config.deadline)
    if not config.cpu_smoke:
        require_cuda(detect_environment())
    folder = config.folder
    folder.root.mkdir(parents=True, exist_ok=True)
    folder.runs_path.unlink(missing_ok=True)
    for variant in VARIANTS:  # an earlier run's, which this report must not show
        folder.errors_log(variant).unlink(missing_ok=True)
        folder.steps_log(variant).unlink(missing_ok=True)
    CONSOLE.print(">>> scene and image tracks", highlight=False)
    scene = prepare_scene(config.scene, config.scene_folder, folder.logs_dir / "tracks.log", deadline)
    append_record(folder.runs_path, scene)
    CONSOLE.print(f"    {scene.name}: {scene.outcome}: {scene.detail}", highlight=False)
    if scene.passed:
        run_variants(config, deadline)
    path = rebuild(config)
    print(path.read_text(), flush=True)
    CONSOLE.print(f"report: {path}")
    return all(r.passed is not False for r in regime_report.read_runs(folder))


def main(config: RegimeConfig) -> int:
    try:
        passed = run(config)
    except (GpuCheckError, ValueError) as error:
        CONSOLE.print(f"[bold red]regime: {error}", highlight=False)
        return 2
    return 0 if passed else 1


if __name__ == "__main__":
    raise SystemExit(main(tyro.cli(RegimeConfig, description=__doc__)))
