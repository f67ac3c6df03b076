"""The ``ns-train`` arguments of the check's runs: what every run shares, and each stage's additions."""

from __future__ import annotations

from pathlib import Path

from s2camp_bench.train_commands import DATAPARSER_SUBCOMMAND, SMALL_MODEL

from .config import GpuCheckConfig

PERTURBED = [DATAPARSER_SUBCOMMAND, "--perturbation.enabled", "True"]
"""The data parser with CamP's perturbation of the training cameras (its default seed and sigmas): the tracks of the
perturbed start are made from the images (the parser's ``image_tracks`` "auto")."""
NCCL_REFRESH_EVERY = 20


def run_arguments(scene: Path, output_dir: Path, experiment: str, timestamp: str, iterations: int) -> list[str]:
    """What every run shares: its data and output places, its length (one checkpoint, at the end), no evaluation
    during training, tensorboard instead of the viewer."""
    return [
        "--data", str(scene),
        "--output-dir", str(output_dir),
        "--experiment-name", experiment,
        "--timestamp", timestamp,
        "--max-num-iterations", str(iterations),
        "--steps-per-save", str(iterations),
        "--steps-per-eval-batch", "0",
        "--steps-per-eval-image", "0",
        "--steps-per-eval-all-images", "0",
        "--vis", "tensorboard",
    ]  # fmt: skip


def cpu_arguments(config: GpuCheckConfig) -> list[str]:
    """``--cpu-smoke``: the CPU and the small nerfacto field (``train_commands.SMALL_MODEL``); nothing otherwise."""
    return ["--machine.device-type", "cpu", *SMALL_MODEL] if config.cpu_smoke else []


def timing_arguments(config: GpuCheckConfig, method: str, scene: Path) -> list[str]:
    """A timing run: the method's defaults (its ray batch and P's refresh interval included) for ``timing_steps``,
    on the perturbed scene."""
    folder = config.folder
    return [
        method,
        *run_arguments(scene, folder.ns_train_dir, "timing", method, config.timing_steps),
        *cpu_arguments(config),
        *PERTURBED,
    ]


def rest_arguments(config: GpuCheckConfig, method: str, scene: Path) -> list[str]:
    """A ``rest`` run: the method's defaults with the ray batch of ``rays_per_batch`` and s2camp's P refreshed every
    ``refresh_every`` steps, on the perturbed scene."""
    arguments = [
        method,
        *run_arguments(scene, config.folder.ns_train_dir, "rest", method, config.rest_iterations),
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.rays_per_batch),
    ]  # fmt: skip
    if method == "s2camp":
        arguments += ["--pipeline.model.camera-optimizer.refresh-every", str(config.refresh_every)]
    return [*arguments, *cpu_arguments(config), *PERTURBED]


def nccl_arguments(config: GpuCheckConfig, scene: Path, ns_train: str) -> list[str]:
    """``ns-train s2camp`` on two GPUs with nerfstudio's own launcher (one process per GPU, NCCL)."""
    return [
        ns_train, "s2camp",
        *run_arguments(scene, config.folder.ns_train_dir, "nccl", "s2camp", config.nccl_iterations),
        "--machine.num-devices", "2",
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.rays_per_batch),
        "--pipeline.model.camera-optimizer.refresh-every", str(NCCL_REFRESH_EVERY),
        *PERTURBED,
    ]  # fmt: skip
