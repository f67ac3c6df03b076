"""``ns-train`` command lines shared by every CPU-sized run (the demo, the end-to-end tests, the benchmarks)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

DATAPARSER_SUBCOMMAND = "s2camp-data"
"""nerfstudio takes the dataparser's options only after its subcommand (registered as an entry point)."""
FROZEN_LR = 1e-12
"""Camera learning rate of the warm start: effectively zero (the exponential schedule cannot start at 0)."""
SMALL_MODEL = [
    "--pipeline.model.log2-hashmap-size", "15",
    "--pipeline.model.num-levels", "8",
    "--pipeline.model.max-res", "128",
    "--pipeline.model.num-nerf-samples-per-ray", "32",
    "--pipeline.model.num-proposal-samples-per-ray", "64", "32",
]  # fmt: skip
"""A smaller nerfacto than the default (16 levels of 2^19 hash entries): the same code paths, cheap CPU steps."""

PHOTOMETRIC_ONLY = [
    "--pipeline.model.camera-optimizer.fix-common-rotation", "False",
    "--pipeline.model.camera-optimizer.track-prior", "False",
]  # fmt: skip
"""``ns-train s2camp`` options that leave the cameras to the photometric loss alone: no track prior and no removal
of the common rotation (both on by default; CamP's code has neither)."""


def ns_train_executable() -> str:
    """The ns-train next to this Python (the same environment), else the one on PATH."""
    ns_train = Path(sys.executable).with_name("ns-train")
    return str(ns_train) if ns_train.exists() else "ns-train"


def ns_train_base_arguments(
    method: str, scene: Path, output_dir: Path, experiment: str, timestamp: str, iterations: int, steps_per_save: int
) -> list[str]:
    """``ns-train <method>`` with what every CPU-sized run shares: data and output folders, run length, no
    evaluation during training, a log every 10 steps."""
    return [
        ns_train_executable(), method,
        "--data", str(scene),
        "--output-dir", str(output_dir),
        "--experiment-name", experiment,
        "--timestamp", timestamp,
        "--max-num-iterations", str(iterations),
        "--steps-per-save", str(steps_per_save),
        "--steps-per-eval-batch", "0",
        "--steps-per-eval-image", "0",
        "--steps-per-eval-all-images", "0",
        "--logging.steps-per-log", "10",
    ]  # fmt: skip


def ns_train_arguments(
    method: str, scene: Path, output_dir: Path, experiment: str, timestamp: str, iterations: int, steps_per_save: int,
    rays_per_batch: int, small_model: bool = True,
) -> list[str]:
    """``ns_train_base_arguments`` of a nerfacto method, its ray batch and (``small_model``) ``SMALL_MODEL``."""
    return [
        *ns_train_base_arguments(method, scene, output_dir, experiment, timestamp, iterations, steps_per_save),
        "--pipeline.datamanager.train-num-rays-per-batch", str(rays_per_batch),
        *(SMALL_MODEL if small_model else []),
    ]  # fmt: skip


def camera_schedule_arguments(lr: float, lr_final: float, max_steps: int | None = None) -> list[str]:
    """Camera learning rate ``lr`` decaying exponentially to ``lr_final`` (over ``max_steps``), no warm-up."""
    arguments = [
        "--optimizers.camera-opt.optimizer.lr", str(lr),
        "--optimizers.camera-opt.scheduler.warmup-steps", "0",
        "--optimizers.camera-opt.scheduler.lr-final", str(lr_final),
    ]  # fmt: skip
    if max_steps is not None:
        arguments += ["--optimizers.camera-opt.scheduler.max-steps", str(max_steps)]
    return arguments


def perturbation_arguments(config) -> list[str]:
    """The dataparser subcommand with CamP's perturbation on, seed and sigmas from ``config`` (``perturbation_seed``
    and ``sigma_*`` fields, as ``DemoConfig``)."""
    names = ("seed", "sigma_position", "sigma_look_at", "sigma_focal_length", "sigma_dolly_z")
    values = {name: getattr(config, name if name != "seed" else "perturbation_seed") for name in names}
    options = [part for key, v in values.items() for part in (f"--perturbation.{key}".replace("_", "-"), str(v))]
    return [DATAPARSER_SUBCOMMAND, "--perturbation.enabled", "True", *options]


def training_environment() -> dict[str, str]:
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # Idle OpenMP threads must not spin (on a busy machine that slows each step down several times).
    environment.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return environment
