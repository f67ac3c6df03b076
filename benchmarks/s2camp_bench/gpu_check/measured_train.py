"""Training runs of the GPU check, one after the other in one process, measured as they go.

    python -m s2camp_bench.gpu_check.measured_train PLAN.json

``PLAN.json`` is a ``TrainPlan``. Each run is nerfstudio's own ``ns-train`` path (``main``'s config preparation,
``train_loop``'s seed, set-up and training) plus what its ``TrainSpec`` asks for (``run_logs``): every step's time,
stamped after ``torch.cuda.synchronize()`` (CUDA queues work: without it a stamp says when a step was queued), the
steps that refreshed P marked, the peak CUDA memory and P's refresh timed apart after training; the camera errors
every ``errors_every`` steps (``setup_only``: of the cameras as set up, no training); and a clean stop before the
plan's ``stop_at``: nerfstudio's loop ends after the current step as after its last, everything measured written.
"""

from __future__ import annotations

import gc
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from .records import as_record
from .run_logs import REFINED, START, RunEnd, StepLog, log_camera_errors

MINIMUM_RUN_S = 30.0
"""Without ``share``, a run that trains is not started with less than this left before the plan's ``stop_at`` (its
set-up alone takes a good part of it)."""


@dataclass
class TrainSpec:
    """One run: its ``ns-train`` arguments (method first) and what to measure."""

    arguments: list[str]
    steps_log: str | None = None
    """Step log file (``run_logs.StepLog``); None: none."""
    log_every: int = 10
    """Steps between appends to the step log."""
    errors_log: str | None = None
    """Camera-error log file (``run_logs.log_camera_errors``); None: none."""
    errors_every: int = 0
    """Steps between camera errors (0: at the start and the end only)."""
    refresh_repeats: int = 0
    """Times P's refresh is timed after training (S2CamP methods; none for the others)."""
    setup_only: bool = False
    """Set up, log the camera errors, train nothing."""


@dataclass
class TrainPlan:
    runs: list[TrainSpec]
    stop_at: float | None = None
    """``time.time()`` by which training stops; a run not started by then is left out."""
    share: bool = False
    """Share the time left before ``stop_at`` evenly among the runs not yet started (a deadline cuts every run of a
    timing group, not the last ones away); else each run may use all of it."""

    def write(self, path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(asdict(self), indent=1))
        return path

    @classmethod
    def read(cls, path: Path) -> TrainPlan:
        values = json.loads(path.read_text())
        return cls([as_record(TrainSpec, run) for run in values["runs"]], values.get("stop_at"), values.get("share"))


def refiner_of(model):
    """S2CamP's refiner of ``model`` (None for other camera optimizers, and with camera refinement off)."""
    optimizer = getattr(model, "camera_optimizer", None)
    return getattr(optimizer, "refiner", None) if getattr(optimizer, "enabled", True) else None


class StepWatch:
    """After every step (appended last, so after the model's own callbacks, a refresh of P included): the step's
    time, the camera errors when due, and the stop before ``stop_at``."""

    def __init__(self, trainer, spec: TrainSpec, stop_at: float | None, synchronize: bool) -> None:
        self.trainer, self.spec, self.stop_at, self.synchronize = trainer, spec, stop_at, synchronize
        device = torch.cuda.get_device_name() if synchronize else "cpu"
        method = trainer.config.method_name
        self.log = StepLog(Path(spec.steps_log), method, device, spec.log_every) if spec.steps_log else None
        self.steps, self.last, self.stopped_early = 0, None, False
        self.last_refresh = getattr(refiner_of(trainer.pipeline.model), "last_refresh", None)

    def begin(self, step: int) -> None:
        if self.last is None:
            self.last = self._stamp()

    def __call__(self, step: int) -> None:
        now = self._stamp()
        seconds = now - (self.last if self.last is not None else now)
        marker = getattr(refiner_of(self.trainer.pipeline.model), "last_refresh", None)
        refresh, self.last_refresh = marker != self.last_refresh, marker
        self.steps += 1
        if self.log is not None:
            self.log.add(step, seconds, refresh)
        done = step + 1
        if self.spec.errors_log and self.spec.errors_every and done % self.spec.errors_every == 0:
            log_camera_errors(Path(self.spec.errors_log), self.trainer.pipeline, REFINED, done)
        if done % 100 == 0:
            print(f"step {done}: {1e3 * seconds:.1f} ms", flush=True)
        if self.stop_at is not None and time.time() >= self.stop_at and not self.trainer.stop_training:
            self.trainer.stop_training = True  # nerfstudio's loop ends before the next step, as after its last
            self.stopped_early = done < self.trainer.config.max_num_iterations
            print(f"stopped after step {done} to end before the deadline", flush=True)
        self.last = self._stamp()  # the errors above are not the next step's time

    def _stamp(self) -> float:
        if self.synchronize:
            torch.cuda.synchronize()
        return time.perf_counter()


def time_refreshes(trainer, repeats: int, synchronize: bool) -> list[float]:
    """Seconds of ``repeats`` refreshes of P after training, through the refiner's own ``refresh`` with the camera
    optimizer's Adam state, as a scheduled refresh runs (none for other camera optimizers)."""
    refiner = refiner_of(trainer.pipeline.model)
    if repeats == 0 or refiner is None:
        return []
    adam = trainer.optimizers.optimizers.get("camera_opt")
    seconds = []
    for repeat in range(repeats):
        if synchronize:
            torch.cuda.synchronize()
        began = time.perf_counter()
        refiner.refresh(trainer.step + 1 + repeat, adam)
        if synchronize:
            torch.cuda.synchronize()
        seconds.append(time.perf_counter() - began)
    return seconds


def trainer_config(arguments: list[str]):
    """The ``TrainerConfig`` of ``ns-train <arguments>``, prepared as nerfstudio's ``main`` prepares it."""
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    config = tyro.cli(AnnotatedBaseConfigUnion, args=arguments)
    if config.machine.num_devices * config.machine.num_machines != 1:
        raise SystemExit("measured_train runs one process; use ns-train for several devices")
    if config.data:  # nerfstudio's main: --data is an alias of the data manager's data
        config.pipeline.datamanager.data = config.data
    config.set_timestamp()
    config.save_config()
    return config


def train(spec: TrainSpec, stop_at: float | None) -> None:
    """One run of the plan (module docstring)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed

    config = trainer_config(spec.arguments)
    on_cuda = config.machine.device_type == "cuda"
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    errors = Path(spec.errors_log) if spec.errors_log else None
    if errors is not None:
        errors.unlink(missing_ok=True)
        log_camera_errors(errors, trainer.pipeline, START, 0)
        log_camera_errors(errors, trainer.pipeline, REFINED, 0)
    if spec.setup_only:
        return
    watch = StepWatch(trainer, spec, stop_at, on_cuda)
    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], watch.begin))
    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], watch))
    trainer.train()
    if errors is not None and (not spec.errors_every or watch.steps % spec.errors_every):
        log_camera_errors(errors, trainer.pipeline, REFINED, watch.steps)
    if watch.log is not None:
        peak = torch.cuda.max_memory_allocated() if on_cuda else None
        refreshes = time_refreshes(trainer, spec.refresh_repeats, on_cuda)
        watch.log.end(RunEnd(watch.steps, peak, watch.stopped_early, refreshes))


def release() -> None:
    """Free what the last run held, so that the next one's peak memory is its own."""
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()  # each Trainer adds its own; the next one must not write to the last one's
    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()


def run_stop(plan: TrainPlan, runs_left: int) -> float | None:
    """When the next run must stop: ``plan.stop_at``, or with ``share`` the time left shared evenly among the runs
    left."""
    if plan.stop_at is None or not plan.share:
        return plan.stop_at
    now = time.time()
    return now + (plan.stop_at - now) / runs_left


def main(argv: list[str]) -> None:
    if len(argv) != 1:
        raise SystemExit(f"usage: python -m {__spec__.name} PLAN.json (a TrainPlan), got {argv}")
    plan = TrainPlan.read(Path(argv[0]))
    for index, spec in enumerate(plan.runs):
        reserve = 0.0 if spec.setup_only or plan.share else MINIMUM_RUN_S
        if plan.stop_at is not None and time.time() >= plan.stop_at - reserve:
            print(f"ns-train {spec.arguments[0]}: not started, too close to the deadline", flush=True)
            continue
        print(f">>> ns-train {' '.join(spec.arguments)}", flush=True)
        train(spec, run_stop(plan, len(plan.runs) - index))
        release()


if __name__ == "__main__":
    main(sys.argv[1:])
