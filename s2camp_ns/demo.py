"""``make demo``: generate a scene, perturb its cameras (CamP protocol), train ``s2camp``, print camera errors.

Everything runs offline on the CPU in minutes: a small procedural scene in the mip-NeRF 360 layout, a short
``ns-train s2camp`` run with a CPU-sized batch and a camera learning-rate schedule compressed to the run's length,
then the camera errors of the starting (perturbed) and the refined training cameras against the unperturbed ones,
after a similarity alignment.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro
from rich.console import Console
from rich.table import Table

from s2camp_ns.scene.make_scene import MakeSceneConfig, make_scene

CONSOLE = Console()


@dataclass
class DemoConfig:
    """Joint NeRF + camera refinement from perturbed cameras on a generated scene."""

    scene_dir: Path = Path("demo_scene")
    """Where the generated scene is written (reused when it already exists)."""
    output_dir: Path = Path("outputs/demo")
    """nerfstudio output folder of the demo run."""
    iterations: int = 400
    """Training iterations."""
    rays_per_batch: int = 512
    """Training rays per iteration."""
    camera_lr: float = 1e-3
    """Final learning rate of the whitened camera parameters; it grows exponentially from a hundredth of it, so the
    cameras wait for the NeRF to learn something before they move (moving them against a blurry NeRF adds noise)."""
    sigma_focal_length: float = 0.1
    """Per-camera focal perturbation (CamP uses 0.02 and a shared dolly zoom; a run of minutes on the CPU resolves
    a 10% focal error, while pose errors of CamP's size sit below its gradient noise; see tests/test_e2e.py)."""
    num_cameras: int = 24
    width: int = 160
    height: int = 120
    method: str = "s2camp"
    """nerfstudio method: s2camp or s2camp-camp."""
    perturbation_seed: int = 0
    viewer: bool = False
    """Also serve the viser viewer while training (ns-train --vis viewer+tensorboard)."""


def ensure_scene(config: DemoConfig) -> Path:
    info = config.scene_dir / "scene_info.json"
    if info.exists():
        CONSOLE.print(f"[dim]reusing the generated scene in {config.scene_dir}")
        return config.scene_dir
    if config.scene_dir.exists():
        shutil.rmtree(config.scene_dir)
    CONSOLE.print(f"generating a {config.num_cameras}-camera scene in {config.scene_dir} ...")
    scene = MakeSceneConfig(
        output_dir=config.scene_dir, num_cameras=config.num_cameras, width=config.width, height=config.height
    )
    return make_scene(scene)


def train_command(config: DemoConfig, scene: Path) -> list[str]:
    ns_train = Path(sys.executable).with_name("ns-train")
    return [
        str(ns_train) if ns_train.exists() else "ns-train",
        config.method,
        "--data", str(scene),
        "--output-dir", str(config.output_dir),
        "--timestamp", "demo",
        "--max-num-iterations", str(config.iterations),
        "--steps-per-save", str(config.iterations),
        "--steps-per-eval-batch", "0",
        "--steps-per-eval-image", "0",
        "--steps-per-eval-all-images", "0",
        "--mixed-precision", "False",
        "--vis", "viewer+tensorboard" if config.viewer else "tensorboard",
        "--viewer.quit-on-train-completion", "True",
        "--pipeline.datamanager.train-num-rays-per-batch", str(config.rays_per_batch),
        # A smaller nerfacto (same code paths) so that a CPU step takes a fraction of a second.
        "--pipeline.model.log2-hashmap-size", "15",
        "--pipeline.model.num-levels", "8",
        "--pipeline.model.max-res", "128",
        "--pipeline.model.num-nerf-samples-per-ray", "32",
        "--pipeline.model.num-proposal-samples-per-ray", "64", "32",
        "--optimizers.camera-opt.optimizer.lr", str(config.camera_lr / 100),
        "--optimizers.camera-opt.scheduler.warmup-steps", "0",
        "--optimizers.camera-opt.scheduler.lr-final", str(config.camera_lr),
        "--optimizers.camera-opt.scheduler.max-steps", str(config.iterations),
        "--pipeline.model.camera-optimizer.refresh-every", str(max(config.iterations // 4, 1)),
        # nerfstudio takes dataparser options only after the dataparser's subcommand, at the end.
        "s2camp-data",
        "--perturbation.enabled", "True",
        "--perturbation.seed", str(config.perturbation_seed),
        "--perturbation.sigma-focal-length", str(config.sigma_focal_length),
        "--perturbation.sigma-dolly-z", "0",
    ]


@torch.no_grad()
def camera_error_table(config_path: Path) -> dict[str, dict[str, float]]:
    """Errors of the perturbed start and of the refined cameras, read from the final checkpoint."""
    from nerfstudio.utils.eval_utils import eval_setup

    from s2camp_ns.core.alignment import camera_errors

    _, pipeline, _, _ = eval_setup(config_path, test_mode="inference")
    model = pipeline.model
    optimizer = model.camera_optimizer
    reference = model.reference_cameras()
    if reference is None:
        raise RuntimeError("the demo run has no reference cameras: was the perturbation enabled?")
    reference_c2w = reference.camera_to_worlds.to(torch.float64)
    reference_fx = reference.fx.reshape(-1).to(torch.float64)
    zeros = optimizer.camera_deltas().zero_()
    start = (optimizer.refined_c2w(zeros, opengl=True), optimizer.refined_intrinsics(zeros).fx)
    refined = (optimizer.refined_c2w(opengl=True), optimizer.refined_intrinsics().fx)
    results = {}
    for label, (c2w, fx) in (("perturbed start", start), ("after refinement", refined)):
        results[label] = camera_errors(c2w.cpu(), reference_c2w.cpu(), fx.cpu(), reference_fx.cpu(), align=True)
    return results


def print_table(results: dict[str, dict[str, float]], seconds: float, iterations: int) -> None:
    table = Table(title=f"Training-camera errors vs the unperturbed cameras ({iterations} iterations, {seconds:.0f} s)")
    table.add_column("cameras")
    for header in ("rotation (rad)", "position (scene units)", "focal (px)"):
        table.add_column(header + " mean / max", justify="right")
    for label, errors in results.items():
        table.add_row(
            label,
            f"{errors['rot_err_mean']:.2e} / {errors['rot_err_max']:.2e}",
            f"{errors['pos_err_mean']:.2e} / {errors['pos_err_max']:.2e}",
            f"{errors['focal_err_mean']:.3f} / {errors['focal_err_max']:.3f}",
        )
    CONSOLE.print(table)


def main(config: DemoConfig) -> dict[str, dict[str, float]]:
    scene = ensure_scene(config)
    command = train_command(config, scene)
    CONSOLE.print("[bold]running:[/bold] " + " ".join(command))
    began = time.perf_counter()
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
    subprocess.run(command, check=True, env=environment)
    seconds = time.perf_counter() - began
    config_path = config.output_dir / scene.name / config.method / "demo" / "config.yml"
    results = camera_error_table(config_path)
    print_table(results, seconds, config.iterations)
    summary = config.output_dir / "camera_errors.json"
    summary.write_text(json.dumps(results, indent=2))
    CONSOLE.print(f"[dim]errors written to {summary}; trained model config: {config_path}")
    return results


def entrypoint() -> None:
    main(tyro.cli(DemoConfig, description=__doc__))


if __name__ == "__main__":
    entrypoint()
