"""Training runs of the GPU check, one after the other in one process, measured while they train.

    python -m s2camp_bench.gpu_check.measured_train PLAN.json

``PLAN.json`` is a ``TrainPlan``. Each run is nerfstudio's own ``ns-train`` path (its ``main``: the ``--data`` alias,
timestamp, saved config.yml; its ``train_loop``: seed, ``Trainer`` setup and training) with these additions, each
asked for by the run's ``TrainSpec``:

- the time of every step, stamped after ``torch.cuda.synchronize()`` (CUDA queues work asynchronously: without it a
  stamp says when a step's work was queued, not done), appended to a step log every few steps (``step_log``), the
  steps in which S2CamP refreshed P marked; the run's peak CUDA memory; P's refresh timed apart after training;
- the camera errors against the true cameras every ``errors_every`` steps (``camera_error_log``); ``setup_only``:
  those of the cameras as set up, without training (the tracks-alone placement);
- a clean stop before the plan's ``stop_at`` (the time left shared evenly among the runs not yet started):
  nerfstudio's loop stops after the current step (``stop_training``) and ends as after its last step, with
  everything measured so far written;
- the evaluation of the trained pipeline while it is in memory (camera errors, held-out PSNR after test-time
  alignment), which spares loading a checkpoint nerfstudio 1.1.5 cannot load for a stock ``nerfacto`` run under
  torch >= 2.6. Stock ``nerfacto`` and ``splatfacto`` build LPIPS from torchvision's AlexNet weights, which an
  offline machine lacks; there LPIPS is left out (they use it for evaluation images only) and the result says so.
"""

from __future__ import annotations

import gc
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from .camera_error_log import REFINED, START, log_camera_errors
from .records import as_record
from .step_log import RunEnd, StepLog

STOCK_METHODS = ("nerfacto", "splatfacto")
"""nerfstudio's own methods: they build LPIPS unconditionally."""


@dataclass
class TrainSpec:
    """One run: its ``ns-train`` arguments (method first) and what to measure."""

    arguments: list[str]
    steps_log: str | None = None
    """Step log file (``step_log``); None: none."""
    log_every: int = 10
    """Steps between appends to the step log."""
    errors_log: str | None = None
    """Camera-error log file (``camera_error_log``); None: none."""
    errors_every: int = 0
    """Steps between camera errors (0: at the start and the end only)."""
    refresh_repeats: int = 0
    """Times P's refresh is timed after training (S2CamP methods)."""
    setup_only: bool = False
    """Set up, log the camera errors, train nothing."""
    result: str | None = None
    """JSON file of the evaluated run (step seconds, peak memory, evaluation); None: no evaluation."""
    alignment: dict = field(default_factory=dict)
    """``AlignmentConfig`` fields of the evaluation."""


@dataclass
class TrainPlan:
    runs: list[TrainSpec]
    stop_at: float | None = None
    """``time.time()`` by which training stops; a run not started by then is left out."""

    def write(self, path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(asdict(self), indent=1))
        return path

    @classmethod
    def read(cls, path: Path) -> TrainPlan:
        values = json.loads(path.read_text())
        return cls([as_record(TrainSpec, run) for run in values["runs"]], values.get("stop_at"))


class StepWatch:
    """After every step (appended last, so after the model's own callbacks, a refresh of P included): the step's
    time, the camera errors when due, and the stop before ``stop_at``."""

    def __init__(self, trainer, spec: TrainSpec, stop_at: float | None, synchronize: bool) -> None:
        self.trainer, self.spec, self.stop_at, self.synchronize = trainer, spec, stop_at, synchronize
        device = torch.cuda.get_device_name() if synchronize else "cpu"
        method = trainer.config.method_name
        self.log = StepLog(Path(spec.steps_log), method, device, spec.log_every) if spec.steps_log else None
        self.seconds: list[float] = []
        self.last: float | None = None
        self.last_refresh = refresh_marker(trainer.pipeline.model)
        self.stopped_early = False

    def begin(self, step: int) -> None:
        if self.last is None:
            self.last = self._stamp()

    def __call__(self, step: int) -> None:
        now = self._stamp()
        seconds = now - (self.last if self.last is not None else now)
        marker = refresh_marker(self.trainer.pipeline.model)
        refresh, self.last_refresh = marker != self.last_refresh, marker
        self.seconds.append(seconds)
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


def refresh_marker(model) -> int | None:
    """The step of S2CamP's last refresh of P (None for other camera optimizers): it changes when P is refreshed."""
    refiner = getattr(getattr(model, "camera_optimizer", None), "refiner", None)
    return getattr(refiner, "last_refresh", None)


def time_refreshes(trainer, repeats: int, synchronize: bool) -> list[float]:
    """Seconds of ``repeats`` refreshes of P after training, through the optimizer's own ``refresh`` with the camera
    optimizer's Adam state, as a scheduled refresh runs (none for other camera optimizers)."""
    refiner = getattr(getattr(trainer.pipeline.model, "camera_optimizer", None), "refiner", None)
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


def lpips_loadable() -> bool:
    """Whether torchmetrics' LPIPS can be built here (its AlexNet weights cached or downloadable)."""
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    try:
        LearnedPerceptualImagePatchSimilarity(normalize=True)
    except (OSError, RuntimeError):
        return False
    return True


def leave_out_stock_lpips() -> None:
    """Let stock nerfacto and splatfacto build without LPIPS (their model then holds ``lpips = None``, which the
    evaluation reads as unavailable); S2CamP's models have this fallback themselves. They import the class from
    torchmetrics when they build their modules, so the stand-in goes there."""
    import torchmetrics.image.lpip as lpip_module

    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: None


def evaluate(pipeline, alignment) -> dict:
    """Camera errors (start and final) and held-out PSNR of a trained pipeline, S2CamP's or stock nerfacto's."""
    from s2camp_ns.method.model import S2CampModel
    from s2camp_bench.evaluation import evaluate_pipeline

    from .stock_nerfacto import StockNerfactoPipeline

    if not isinstance(pipeline.model, S2CampModel):
        pipeline = StockNerfactoPipeline(pipeline)
    return evaluate_pipeline(pipeline, alignment)


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
    lpips_left_out = config.method_name in STOCK_METHODS and not lpips_loadable()
    if lpips_left_out:
        print("LPIPS weights unavailable (offline): stock methods are built without LPIPS", flush=True)
        leave_out_stock_lpips()
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
    steps = len(watch.seconds)
    peak = torch.cuda.max_memory_allocated() if on_cuda else None
    if errors is not None and (not spec.errors_every or steps % spec.errors_every):
        log_camera_errors(errors, trainer.pipeline, REFINED, steps)
    if watch.log is not None:
        refreshes = time_refreshes(trainer, spec.refresh_repeats, on_cuda)
        watch.log.end(RunEnd(steps, peak, watch.stopped_early, refreshes))
    if spec.result:
        result = {
            "method": config.method_name, "device": torch.cuda.get_device_name() if on_cuda else "cpu",
            "step_seconds": watch.seconds[1:], "peak_memory_bytes": peak, "lpips_left_out": lpips_left_out,
            "stopped_early": watch.stopped_early, "config": str(config.get_base_dir() / "config.yml"),
        }  # fmt: skip
        write_json(Path(spec.result), result)  # first without the evaluation: a failed one keeps the timing
        result["evaluation"] = evaluate(trainer.pipeline, _alignment(spec.alignment))
        write_json(Path(spec.result), result)


def _alignment(fields: dict):
    from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

    alignment = AlignmentConfig(**fields)
    alignment.validate()
    return alignment


def write_json(path: Path, value: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp")
    temporary.write_text(json.dumps(value, indent=2).replace("NaN", "null"))
    temporary.replace(path)


def release() -> None:
    """Free what the last run held, so that the next one's peak memory is its own."""
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()  # each Trainer adds its own; the next one must not write to the last one's
    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()


def main(argv: list[str]) -> None:
    if len(argv) != 1:
        raise SystemExit(f"usage: python -m {__spec__.name} PLAN.json (a TrainPlan), got {argv}")
    plan = TrainPlan.read(Path(argv[0]))
    for index, spec in enumerate(plan.runs):
        if plan.stop_at is not None and time.time() >= plan.stop_at:
            print(f"ns-train {spec.arguments[0]}: not started, the deadline is reached", flush=True)
            continue
        print(f">>> ns-train {' '.join(spec.arguments)}", flush=True)
        train(spec, share_of_time(plan.stop_at, len(plan.runs) - index))
        release()


def share_of_time(stop_at: float | None, runs_left: int) -> float | None:
    """When the next run must stop: the time left before ``stop_at`` shared evenly among the runs left, so that a
    deadline cuts every run of a pair, not the second one away."""
    if stop_at is None:
        return None
    now = time.time()
    return now + (stop_at - now) / runs_left


if __name__ == "__main__":
    main(sys.argv[1:])
