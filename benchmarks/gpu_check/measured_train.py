"""One training run of the GPU check, measured and evaluated in the training process.

    python -m s2camp_ns.benchmarks.gpu_check.measured_train --result RUN.json [--alignment JSON] -- <ns-train arguments>

The run is nerfstudio's own ``ns-train`` path: its ``main`` (the ``--data`` alias, timestamp, saved config.yml,
``launch``) and its ``train_loop`` (seed, ``Trainer`` setup and training), with three additions:

- the wall time of every training step, stamped after ``torch.cuda.synchronize()`` (CUDA queues kernels
  asynchronously: without the synchronization a step's stamp is when its work was queued, not done);
- the peak CUDA memory of the run, ``torch.cuda.max_memory_allocated()`` right after the last step (before the
  evaluation allocates its own);
- the evaluation of the trained pipeline while it is still in memory: camera errors of the perturbed start and of the
  refined cameras, and held-out PSNR after test-time alignment (``s2camp-eval``'s protocol), as
  ``s2camp-bench robustness`` computes them. Evaluating here spares loading the checkpoint, which nerfstudio 1.1.5
  cannot do for a stock ``nerfacto`` run under torch >= 2.6 (numpy learning rates in its scheduler state).

Everything is written to ``--result`` as JSON: first after training (so a failed evaluation keeps the timing), then
with the evaluation. Stock ``nerfacto`` builds LPIPS from torchvision's AlexNet weights, which an offline machine
lacks; there its LPIPS is left out (nerfacto uses it for evaluation images only, never in training) and the result
says so.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch


@dataclass
class StepClock:
    """Wall-clock stamps after every training step, taken once the device has finished the step's work."""

    synchronize: bool
    stamps: list[float] = field(default_factory=list)

    def __call__(self, step: int) -> None:
        if self.synchronize:
            torch.cuda.synchronize()
        self.stamps.append(time.perf_counter())

    def step_seconds(self) -> list[float]:
        """Seconds of each step after the first (the first has no previous stamp)."""
        return [later - earlier for earlier, later in zip(self.stamps[:-1], self.stamps[1:], strict=True)]


def lpips_loadable() -> bool:
    """Whether torchmetrics' LPIPS can be built here (its AlexNet weights cached or downloadable)."""
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    try:
        LearnedPerceptualImagePatchSimilarity(normalize=True)
    except (OSError, RuntimeError):
        return False
    return True


def leave_out_stock_lpips() -> None:
    """Let stock nerfacto build without LPIPS (its model then holds ``lpips = None``, which the evaluation reads as
    unavailable); S2CamP's model has this fallback itself. nerfacto imports the class from torchmetrics when it
    builds its modules, so the stand-in goes there."""
    import torchmetrics.image.lpip as lpip_module

    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: None


def evaluate(pipeline, alignment) -> dict:
    """Camera errors (start and final) and held-out PSNR of a trained pipeline, S2CamP's or stock nerfacto's."""
    from s2camp_ns.nerfstudio.evaluation import evaluate_pipeline
    from s2camp_ns.nerfstudio.model import S2CampModel

    from .stock_nerfacto import StockNerfactoPipeline

    if not isinstance(pipeline.model, S2CampModel):
        pipeline = StockNerfactoPipeline(pipeline)
    return evaluate_pipeline(pipeline, alignment)


def train_measure_evaluate(config, result_path: Path, alignment, lpips_left_out: bool) -> None:
    """nerfstudio's ``train_loop`` for one process, plus the step clock, the peak memory and the evaluation."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed

    on_cuda = config.machine.device_type == "cuda"
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    clock = StepClock(synchronize=on_cuda)
    # Appended last: the stamp follows the step's other callbacks (a refresh of P included).
    after_step = [TrainingCallbackLocation.AFTER_TRAIN_ITERATION]
    trainer.callbacks.append(TrainingCallback(where_to_run=after_step, func=clock))
    trainer.train()
    result = {
        "method": config.method_name,
        "device": torch.cuda.get_device_name() if on_cuda else "cpu",
        "step_seconds": clock.step_seconds(),
        "peak_memory_bytes": torch.cuda.max_memory_allocated() if on_cuda else None,
        "lpips_left_out": lpips_left_out,
        "config": str(config.get_base_dir() / "config.yml"),
    }
    _write(result_path, result)
    result["evaluation"] = evaluate(trainer.pipeline, alignment)
    _write(result_path, result)


def _write(path: Path, result: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp")
    temporary.write_text(json.dumps(result, indent=2).replace("NaN", "null"))
    temporary.replace(path)


def main(argv: list[str]) -> None:
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from s2camp_ns.nerfstudio.test_time_alignment import AlignmentConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--result", type=Path, required=True, help="JSON file for the measurements")
    parser.add_argument("--alignment", default="{}", help="AlignmentConfig fields as a JSON object")
    if "--" not in argv:
        parser.error("the ns-train arguments must follow a lone --")
    separator = argv.index("--")
    options = parser.parse_args(argv[:separator])
    alignment = AlignmentConfig(**json.loads(options.alignment))
    alignment.validate()
    config = tyro.cli(AnnotatedBaseConfigUnion, args=argv[separator + 1 :])
    if config.machine.num_devices * config.machine.num_machines != 1:
        raise SystemExit("measured_train runs one process; use ns-train for several devices")
    lpips_left_out = config.method_name == "nerfacto" and not lpips_loadable()
    if lpips_left_out:
        print("LPIPS weights unavailable (offline): stock nerfacto is built without LPIPS", flush=True)
        leave_out_stock_lpips()
    if config.data:  # nerfstudio's main: --data is an alias of the data manager's data
        config.pipeline.datamanager.data = config.data
    config.set_timestamp()
    config.print_to_terminal()
    config.save_config()
    train_measure_evaluate(config, options.result, alignment, lpips_left_out)


if __name__ == "__main__":
    main(sys.argv[1:])
