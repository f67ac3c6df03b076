"""``make demo``: generate a scene, perturb its cameras (CamP protocol), train ``s2camp``, print camera errors.

Offline, on the CPU, in minutes, on a small procedural scene in the mip-NeRF 360 layout. Recipe ``default``: ``ns-train
s2camp`` with its default options, from scratch (the track prior gets tracks made from the images with the perturbed
cameras, not the scene's). Recipe ``warm-start``: the photometric refinement alone (``PHOTOMETRIC_ONLY``), nerfacto
fitted to the accurate cameras, then resumed on the perturbed ones with a raised camera learning rate and no warm-up.
The errors of the start, the tracks alone and the refined cameras against the true ones, after a similarity
alignment, are read from the final checkpoint and printed.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import shutil
import subprocess
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from s2camp_bench import train_commands
from s2camp_bench.common import generated_scene
from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_ns.core.validation import check_positive_int, check_range

CONSOLE = Console()

EXPERIMENT = "demo"
WARM_START_TIMESTAMP = "warm-start"
REFINE_TIMESTAMP = "refine"


@dataclass
class DemoConfig:
    """Camera refinement from perturbed cameras (CamP protocol) with S2CamP on a generated scene."""

    scene_dir: Path = Path("demo_scene")
    """Where the generated scene is written (reused when it already exists with the same size)."""
    output_dir: Path = Path("outputs/demo")
    """nerfstudio output folder (its demo/<method>/{warm-start,refine} runs are replaced)."""
    num_cameras: int = 32
    """Cameras of the generated scene (every 8th is held out for evaluation)."""
    width: int = 256
    """Image width of the generated scene (even)."""
    height: int = 192
    """Image height of the generated scene (even)."""
    recipe: Literal["default", "warm-start"] = "default"
    """"default": the method's defaults from scratch; "warm-start": the photometric refinement alone, from a field
    fitted to the accurate cameras (module docstring)."""
    warm_start: int = 250
    """Recipe "warm-start": iterations on the accurate cameras (camera learning rate zero); 0 skips it."""
    iterations: int = 200
    """Iterations of the run on the perturbed cameras."""
    rays_per_batch: int = 1024
    """Training rays per iteration."""
    camera_lr: float = 1e-3
    """Recipe "warm-start": camera learning rate (whitened units) at the start of the refinement run."""
    camera_lr_final: float = 3e-4
    """Recipe "warm-start": camera learning rate at the end of the refinement run."""
    sigma_position: float = 0.05
    """Perturbation: camera centres move this far (normalized scene units; CamP 0.005)."""
    sigma_look_at: float = 0.02
    """Perturbation: look-at points move this far (normalized scene units; CamP 0.005)."""
    sigma_focal_length: float = 0.02
    """Perturbation: per-camera relative focal-length change (CamP 0.02)."""
    sigma_dolly_z: float = 0.05
    """Perturbation: shared dolly zoom, relative (CamP 0.05)."""
    perturbation_seed: int = 0
    """Seed of the perturbation."""
    method: Literal["s2camp", "s2camp-camp"] = "s2camp"
    """nerfstudio method: s2camp (deterministic lattice preconditioner) or s2camp-camp (CamP's random points)."""
    viewer: bool = False
    """Also serve the viser viewer during the refinement run (ns-train --vis viewer+tensorboard)."""
    verbose: bool = False
    """Stream ns-train's full output instead of a progress bar (always in <output_dir>/{warm-start,refine}.log)."""


WARM_START_RECIPE_OPTIONS = ("warm_start", "camera_lr", "camera_lr_final")


def check_config(config: DemoConfig) -> None:
    """Reject settings that would only fail inside ns-train, with the parameter's name."""
    for name in ("iterations", "rays_per_batch", "num_cameras", "width", "height"):
        check_positive_int(name, getattr(config, name))
    for name in ("warm_start", "perturbation_seed"):
        check_range(name, getattr(config, name), low=0)
    for name in ("camera_lr", "camera_lr_final", "sigma_position", "sigma_look_at", "sigma_focal_length"):
        check_range(name, getattr(config, name), low=0.0, low_inclusive=name.startswith("sigma"))
    check_range("sigma_dolly_z", config.sigma_dolly_z, low=0.0)
    if config.recipe == "default":  # the default recipe uses the method's own schedule: these would do nothing
        for name in WARM_START_RECIPE_OPTIONS:
            value, default = getattr(config, name), getattr(DemoConfig, name)
            if value != default:
                raise ValueError(
                    f"{name} applies to recipe 'warm-start' only, got {value!r} with recipe 'default' (which trains "
                    "with the method's own camera schedule); add --recipe warm-start"
                )


def ensure_scene(config: DemoConfig) -> Path:
    """Generate the scene, or reuse the one in ``scene_dir`` generated with the same settings."""
    CONSOLE.print(f"[dim]the {config.num_cameras}-camera {config.width}x{config.height} scene in {config.scene_dir}")
    size = {"num_cameras": config.num_cameras, "width": config.width, "height": config.height}
    return generated_scene(MakeSceneConfig(output_dir=config.scene_dir, **size))


def _common_arguments(config: DemoConfig, scene: Path, timestamp: str, iterations: int) -> list[str]:
    """Options of both runs (the refinement run loads the warm start: the models must match)."""
    return [
        *train_commands.ns_train_arguments(
            config.method, scene, config.output_dir, EXPERIMENT, timestamp, iterations, iterations,
            config.rays_per_batch,
        ),
        "--pipeline.model.camera-error-every", "10",
    ]  # fmt: skip


def run_dir(config: DemoConfig, timestamp: str) -> Path:
    return config.output_dir / EXPERIMENT / config.method / timestamp


def uses_warm_start(config: DemoConfig) -> bool:
    return config.recipe == "warm-start" and config.warm_start > 0


def warm_start_command(config: DemoConfig, scene: Path) -> list[str]:
    """nerfacto on the accurate cameras; the camera optimizer exists (the checkpoints must match) but does not move."""
    return [
        *_common_arguments(config, scene, WARM_START_TIMESTAMP, config.warm_start),
        "--vis", "tensorboard",
        *train_commands.camera_schedule_arguments(train_commands.FROZEN_LR, train_commands.FROZEN_LR),
        *train_commands.PHOTOMETRIC_ONLY,  # the photometric loss alone
    ]  # fmt: skip


def refine_command(config: DemoConfig, scene: Path) -> list[str]:
    """The run on the perturbed cameras: the method's own camera options ("default"), or the warm start resumed
    (if any) with a fresh camera schedule and the photometric loss alone ("warm-start")."""
    command = [
        *_common_arguments(config, scene, REFINE_TIMESTAMP, config.iterations),
        "--vis", "viewer+tensorboard" if config.viewer else "tensorboard",
        "--viewer.quit-on-train-completion", "True",
    ]  # fmt: skip
    if config.recipe == "default":
        return [*command, *train_commands.perturbation_arguments(config)]
    command += [
        *train_commands.camera_schedule_arguments(config.camera_lr, config.camera_lr_final, config.iterations),
        "--pipeline.model.camera-optimizer.refresh-every", str(max(config.iterations // 4, 1)),
        *train_commands.PHOTOMETRIC_ONLY,  # the photometric loss alone
    ]  # fmt: skip
    if config.warm_start > 0:
        command += [
            "--load-dir", str(run_dir(config, WARM_START_TIMESTAMP) / "nerfstudio_models"),
            "--load-scheduler", "False",
        ]  # fmt: skip
    return [*command, *train_commands.perturbation_arguments(config)]


_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
_STEP = re.compile(r"^(\d+) \(\d+(?:\.\d+)?%\)")
_SHOWN = ("CUDA is not available: training on the CPU", "Viewer running", "Viewer at")
"""ns-train lines echoed on the terminal in quiet mode (the rest goes to the run's log file)."""


def run(command: list[str], what: str, log_path: Path, iterations: int, verbose: bool = False) -> float:
    """Run one ns-train command and return its wall time; exit with its status if it fails. Its output goes to
    ``log_path`` behind a progress bar, or to the terminal with ``verbose``."""
    CONSOLE.rule(what)
    CONSOLE.print("[bold]running:[/bold] " + " ".join(command), soft_wrap=True, highlight=False)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    began = time.perf_counter()
    with open(log_path, "w", encoding="utf8") as log:
        piped = {} if verbose else {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT, "text": True}
        process = subprocess.Popen(command, env=train_commands.training_environment(), **piped)
        try:
            if not verbose:
                _follow(process, log, iterations)
            returncode = process.wait()
        except KeyboardInterrupt:
            process.terminate()
            process.wait()
            raise
    if returncode != 0:
        if not verbose:
            tail = log_path.read_text(encoding="utf8", errors="replace").splitlines()[-40:]
            CONSOLE.print("\n".join(_ANSI.sub("", line) for line in tail), highlight=False, markup=False)
        CONSOLE.print(f"[bold red]{what}: ns-train exited with status {returncode}; full output in {log_path}")
        raise SystemExit(returncode)
    CONSOLE.print(f"[dim]done in {time.perf_counter() - began:.0f} s; ns-train output in {log_path}")
    return time.perf_counter() - began


def _follow(process: subprocess.Popen, log, iterations: int) -> None:
    """Copy ns-train's output to the log, echo the few lines that matter and advance a progress bar."""
    assert process.stdout is not None
    first_step = None
    with Progress(
        TextColumn("training"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=CONSOLE
    ) as progress:
        task = progress.add_task("training", total=iterations)
        for line in process.stdout:
            log.write(line)
            text = _ANSI.sub("", line).strip()
            match = _STEP.match(text)
            if match:
                step = int(match.group(1))
                first_step = step if first_step is None else first_step
                # Resumed runs count on from the checkpoint's step; steps are printed every few iterations.
                progress.update(task, completed=min(step - first_step + 1, iterations))
            elif text.startswith(_SHOWN):
                progress.console.print(text, highlight=False, markup=False)
        progress.update(task, completed=iterations)


@torch.no_grad()
def camera_error_table(config_path: Path) -> dict[str, dict[str, float]]:
    """``camera_errors`` of the start, tracks-alone (with a track prior) and refined cameras, by row label."""
    from s2camp_ns.core.alignment import camera_errors

    captured = io.StringIO()
    try:
        # eval_setup prints nerfstudio's start-up chatter (tcnn fallback, LPIPS, checkpoint); keep it off the table.
        with contextlib.redirect_stdout(captured), contextlib.redirect_stderr(captured), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from nerfstudio.utils.eval_utils import eval_setup

            _, pipeline, _, _ = eval_setup(config_path, test_mode="inference")
    except Exception:
        CONSOLE.print(captured.getvalue(), highlight=False, markup=False)
        raise
    model = pipeline.model
    reference = model.reference_cameras()
    if reference is None:
        raise RuntimeError(f"the run {config_path} has no reference cameras: was the perturbation enabled?")
    reference_c2w = reference.camera_to_worlds.to(torch.float64).cpu()
    reference_fx = reference.fx.reshape(-1).to(torch.float64).cpu()
    refiner = model.camera_optimizer.refiner
    zeros = torch.zeros_like(refiner.deltas())
    start = (refiner.refined_c2w(zeros, opengl=True), refiner.refined_intrinsics(zeros).fx)
    refined = (refiner.refined_c2w(opengl=True), refiner.refined_intrinsics().fx)
    rows = [("perturbed start", start)]
    if refiner.has_track_prior:  # where the tracks alone put the cameras (no prior: the given camera)
        anchor = refiner.layout.expand(refiner.prior_anchor).to(zeros)
        rows.append(("tracks alone (where the run starts)", (refiner.refined_c2w(anchor, opengl=True),
                                                             refiner.refined_intrinsics(anchor).fx)))  # fmt: skip
    rows.append(("after refinement", refined))
    return {
        label: camera_errors(c2w.cpu(), reference_c2w, fx.cpu(), reference_fx, align=True) for label, (c2w, fx) in rows
    }


def change(before: float, after: float) -> str:
    """``after`` against ``before`` as "N.Nx smaller" (green) or "N.Nx larger" (red), "same" within 1%."""
    if before <= 0 or after <= 0:
        return "n/a"
    ratio = before / after
    if abs(ratio - 1.0) < 0.01:
        return "same"
    if ratio > 1.0:
        return f"[green]{ratio:.1f}x smaller[/green]"
    return f"[red]{1.0 / ratio:.2f}x larger[/red]"


def print_table(results: dict[str, dict[str, float]], title: str) -> None:
    """``camera_error_table``'s rows (mean / max), then each later row's means against the start's and the last
    row's against the tracks alone's."""
    table = Table(title=title, title_justify="left")
    table.add_column("training cameras")
    table.add_column("rotation (deg)\nmean / max", justify="right")
    table.add_column("position (scene units)\nmean / max", justify="right")
    table.add_column("focal length (px)\nmean / max", justify="right")
    keys = ("rot_err", "pos_err", "focal_err")
    for label, errors in results.items():
        table.add_row(
            label,
            f"{math.degrees(errors['rot_err_mean']):.3f} / {math.degrees(errors['rot_err_max']):.3f}",
            f"{errors['pos_err_mean']:.4f} / {errors['pos_err_max']:.4f}",
            f"{errors['focal_err_mean']:.3f} / {errors['focal_err_max']:.3f}",
            end_section=label == list(results)[-1],
        )
    labels = list(results)
    comparisons = [(label, labels[0]) for label in labels[1:]]
    if len(labels) > 2:
        comparisons.append((labels[-1], labels[1]))
    for label, reference in comparisons:
        cells = [change(results[reference][f"{key}_mean"], results[label][f"{key}_mean"]) for key in keys]
        table.add_row(f"{label.split(' (')[0]} vs {reference.split(' (')[0]}", *cells)
    CONSOLE.print(table)
    CONSOLE.print(
        "[dim]Errors against the unperturbed cameras after a similarity alignment of the camera centres; position in "
        "the normalized scene units of nerfstudio (cameras within [-1, 1]^3), focal length in pixels.",
        soft_wrap=False,
    )


def protocol_notice(config: DemoConfig) -> str:
    """What this demo's run is, against a user's ``ns-train s2camp`` run."""
    if config.recipe == "default" and config.method == "s2camp-camp":
        return (
            "s2camp-camp with its default options, from scratch, on perturbed cameras. CamP has no track prior: its "
            "cameras move by the photometric loss alone, after a warm-up of at least 2500 steps, longer than this "
            "demo. `--recipe warm-start` shows its photometric refinement."
        )
    if config.recipe == "default":
        return (
            "s2camp with its default options, from scratch, on perturbed cameras. The scene's own tracks were made "
            "with the true cameras and are not used: the default gets tracks made from the images with the perturbed "
            "cameras (SIFT, bundle-adjusted), starts each camera where they put it and lets the images move it by "
            "what the tracks leave uncertain. Real-regime runs: docs/benchmarks/regime.md. `--recipe warm-start` "
            "shows the photometric refinement alone."
        )
    overrides = ["the track prior and the common-rotation removal are off: the photometric loss alone moves cameras"]
    if config.warm_start > 0:
        overrides.append(
            f"the field is first fitted for {config.warm_start} iterations to the ACCURATE cameras (a warm start no "
            "real capture has), then the cameras are perturbed"
        )
    overrides.append(
        f"the camera learning rate is overridden: {config.camera_lr:g} decaying to {config.camera_lr_final:g} over "
        f"{config.iterations} iterations with no warm-up (the default starts at 1e-8, warms up over at least 2500 "
        "steps and peaks at 1e-4)"
    )
    return (
        "This recipe shows that the optimizer can correct cameras, not the default recipe: "
        + "; ".join(overrides)
        + ". Real-regime runs with the default options: docs/benchmarks/regime.md."
    )


def main(config: DemoConfig) -> dict[str, dict[str, float]]:
    check_config(config)
    notice = protocol_notice(config)
    CONSOLE.print(f"[bold yellow]{notice}", soft_wrap=False)
    scene = ensure_scene(config)
    for timestamp in (WARM_START_TIMESTAMP, REFINE_TIMESTAMP):
        shutil.rmtree(run_dir(config, timestamp), ignore_errors=True)
    seconds = 0.0
    if uses_warm_start(config):
        what = f"1/2 warm start: nerfacto on the accurate cameras, {config.warm_start} iterations"
        log_path = config.output_dir / f"{WARM_START_TIMESTAMP}.log"
        seconds += run(warm_start_command(config, scene), what, log_path, config.warm_start, config.verbose)
    step = "2/2 " if uses_warm_start(config) else ""
    what = "default options, from scratch" if config.recipe == "default" else "photometric refinement"
    what = f"{step}{config.method} on perturbed cameras (CamP protocol): {what}, {config.iterations} iterations"
    log_path = config.output_dir / f"{REFINE_TIMESTAMP}.log"
    seconds += run(refine_command(config, scene), what, log_path, config.iterations, config.verbose)
    config_path = run_dir(config, REFINE_TIMESTAMP) / "config.yml"
    CONSOLE.rule("camera errors")
    results = camera_error_table(config_path)
    if config.recipe == "default":
        title = f"{config.method}, default options from scratch: {config.iterations} iterations"
    else:
        warm = f"{config.warm_start} warm-start + " if config.warm_start > 0 else ""
        title = f"{config.method}, photometric refinement: {warm}{config.iterations} refinement iterations"
    print_table(results, f"{title}, {seconds:.0f} s of training")
    summary = config.output_dir / "camera_errors.json"
    payload = {"config": _jsonable(config), "protocol": notice, "training_seconds": seconds, **results}
    summary.write_text(json.dumps(payload, indent=2))
    CONSOLE.print(f"[yellow]{notice}", soft_wrap=False)
    CONSOLE.print(f"[dim]errors written to {summary}; trained model: {config_path}")
    return results


def _jsonable(config: DemoConfig) -> dict:
    return {key: str(value) if isinstance(value, Path) else value for key, value in vars(config).items()}


def entrypoint() -> None:
    config = tyro.cli(DemoConfig, description=__doc__)
    try:
        main(config)
    except ValueError as error:
        CONSOLE.print(f"[bold red]s2camp demo: {error}")
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        CONSOLE.print("[bold red]interrupted")
        raise SystemExit(130) from None


if __name__ == "__main__":
    entrypoint()
