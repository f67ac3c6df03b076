"""Tier 2 of ``s2camp-bench recovery``: photometric joint optimisation with ``ns-train``, every variant alike.

Per generated scene (narrow and wide field of view):

1. warm start: one ``ns-train s2camp`` run on the accurate cameras with the camera learning rate at zero (the demo's
   protocol, see ``s2camp_bench.demo``: from scratch on a CPU budget the NeRF absorbs the camera errors first);
2. its checkpoint, stripped of the camera optimizer's parameters and Adam state, is the common start of every
   variant: ``ns-train <method> --load-dir`` with the training cameras perturbed (CamP protocol, fixed seed);
3. each variant trains the same number of iterations with the same camera learning-rate schedule, saving a
   checkpoint every ``checkpoint_every`` steps;
4. once every run of every scene has trained (so evaluation never overlaps a timed training run), identically for
   every variant and in ``eval_workers`` processes: camera errors of each checkpoint after a similarity alignment
   (``core.alignment``), and PSNR / SSIM (LPIPS where its weights are cached) of the held-out views after
   test-time camera alignment (``s2camp_ns.scripts.test_time_alignment``, CamP's 100 camera-only steps).

Variants: none (camera optimizer off), so3xr3 (``s2camp-so3xr3``: nerfstudio's stock optimizer in the same
pipeline), raw (S2CamP's 12 parameters without preconditioning), camp (``s2camp-camp``, 5000 random points, P once,
one run per seed), s2camp (500 lattice points, P refreshed), s2camp-once (P computed once), all with intrinsics per
image, and s2camp-per-camera (as s2camp with one set of intrinsics per physical camera, the method's default).
Seconds per iteration come from the wall-clock stamps of nerfstudio's per-step tensorboard events (everything in
the training loop, checkpoint saves and P refreshes included), skipping the first steps.
"""

from __future__ import annotations

import contextlib
import io
import math
import multiprocessing
import shutil
import subprocess
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from itertools import repeat
from pathlib import Path

import torch

from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene
from s2camp_bench.train_commands import (
    FROZEN_LR,
    PHOTOMETRIC_ONLY,
    camera_schedule_arguments,
    ns_train_arguments,
    perturbation_arguments,
)
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

from .common import log
from .data_parser import ns_train_environment

SCENES = {
    "narrow": MakeSceneConfig(num_cameras=16, width=96, height=72, fov="narrow", seed=0),
    "wide": MakeSceneConfig(num_cameras=16, width=96, height=72, fov="wide", seed=1),
}
QUICK_SCENE_SIZE = {"num_cameras": 8, "width": 48, "height": 36}
METHODS = {
    "none": "s2camp",
    "so3xr3": "s2camp-so3xr3",
    "raw": "s2camp",
    "camp": "s2camp-camp",
    "s2camp": "s2camp",
    "s2camp-once": "s2camp",
    "s2camp-per-camera": "s2camp",
}
PER_CAMERA = ("s2camp-per-camera",)
"""Variants that share intrinsics per physical camera; every other S2CamP variant refines them per image, as
CamP does (rows carry ``intrinsics``)."""
NERFSTUDIO_SEED = 42
"""nerfstudio's default ``--machine.seed``."""
SKIPPED_TIMING_STEPS = 5
"""Steps excluded from the seconds-per-iteration (start-up, first allocations)."""


@dataclass
class PhotometricConfig:
    """ns-train joint optimisation from a shared warm start (module docstring)."""

    warm_start: int = 250
    """Iterations of the shared warm start on the accurate cameras."""
    iterations: int = 200
    """Iterations of every variant on the perturbed cameras."""
    rays_per_batch: int = 1024
    """Training rays per iteration."""
    camera_lr: float = 1e-3
    """Camera learning rate at the start (every variant; whitened units for camp/s2camp, raw for the others)."""
    camera_lr_final: float = 3e-4
    """Camera learning rate at the end (exponential decay)."""
    refresh_every: int = 50
    """P refresh interval of the s2camp variant."""
    checkpoint_every: int = 20
    """Checkpoint interval: the camera-error curves are evaluated on these checkpoints."""
    sigma_position: float = 0.05
    """Perturbation of the camera centres (normalized scene units; the demo's value)."""
    sigma_look_at: float = 0.02
    """Perturbation of the look-at points (normalized scene units)."""
    sigma_focal_length: float = 0.02
    """Per-camera relative focal-length perturbation (CamP)."""
    sigma_dolly_z: float = 0.05
    """Shared dolly zoom (CamP)."""
    perturbation_seed: int = 0
    camp_seeds: tuple[int, ...] = (0, 1, 2)
    """nerfstudio's ``--machine.seed`` of CamP's runs, one run each, errors and metrics averaged (its random proxy
    points are the method's own; rows filed before they became an internal setting varied their seed instead)."""
    training_seeds: tuple[int, ...] = (NERFSTUDIO_SEED,)
    """nerfstudio's ``--machine.seed`` (which rays each step trains on) of every variant but CamP, one run each,
    errors and metrics averaged and their range reported; CamP varies ``camp_seeds`` instead. Several seeds measure
    the run-to-run spread of a variant."""
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    """Test-time alignment of the held-out cameras (every variant alike)."""
    eval_workers: int = 2
    """Processes (one torch thread each) evaluating the finished runs; 1 evaluates in this process."""

    def quick(self) -> PhotometricConfig:
        return replace(
            self,
            warm_start=10,
            iterations=4,
            rays_per_batch=256,
            refresh_every=2,
            checkpoint_every=2,
            camp_seeds=self.camp_seeds[:1],
            training_seeds=self.training_seeds[:1],
            alignment=replace(self.alignment, steps=3, rays=64),
        )


def _arguments(
    method: str, scene: Path, work: Path, experiment: str, timestamp: str, iterations: int, every: int, rays: int
) -> list[str]:
    """The demo's shared ns-train options, plus: every checkpoint kept (the error curves), no camera-error logging
    during training (errors are computed afterwards, the same way for every variant, and time is not spent on it);
    for ``s2camp`` runs the track prior and the common-rotation removal off (``PHOTOMETRIC_ONLY``), so the tiers
    compare the preconditioners alone, as they did before both became s2camp's defaults."""
    return [
        *ns_train_arguments(method, scene, work, experiment, timestamp, iterations, every, rays),
        "--save-only-latest-checkpoint", "False",
        "--vis", "tensorboard",
        "--pipeline.model.camera-error-every", "0",
        *(PHOTOMETRIC_ONLY if method == "s2camp" else []),
    ]  # fmt: skip


def run_seeds(variant: str, config: PhotometricConfig) -> tuple[int, ...]:
    """The seeds ``variant`` runs with, one run each: ``camp_seeds`` for CamP, ``training_seeds`` for the others."""
    return config.camp_seeds if variant == "camp" else config.training_seeds


def run_timestamp(variant: str, seed: int, config: PhotometricConfig) -> str:
    """The run folder's name: the variant, with its seed where the variant runs more than once or is CamP."""
    if variant == "camp":
        return f"camp-seed{seed}"
    return variant if len(config.training_seeds) == 1 else f"{variant}-seed{seed}"


def seed_arguments(variant: str, seed: int) -> list[str]:
    """Every variant's seed seeds nerfstudio (the field's initialisation and the rays each step trains on)."""
    return ["--machine.seed", str(seed)]


def _variant_arguments(variant: str, seed: int, config: PhotometricConfig) -> list[str]:
    prefix = "--pipeline.model.camera-optimizer."
    per_image = [prefix + "intrinsics", "per-image"]
    options = {
        "none": [prefix + "mode", "off"],
        "so3xr3": [],
        "raw": [prefix + "precondition", "False", prefix + "refresh-every", "0", *per_image],
        "camp": [prefix + "refresh-every", "0"],
        "s2camp": [prefix + "refresh-every", str(config.refresh_every), *per_image],
        "s2camp-once": [prefix + "refresh-every", "0", *per_image],
        "s2camp-per-camera": [prefix + "refresh-every", str(config.refresh_every), prefix + "intrinsics", "per-camera"],
    }[variant]
    return seed_arguments(variant, seed) + options


def _run_ns_train(command: list[str], log_path: Path, what: str) -> None:
    log(f"  ns-train {what}: " + " ".join(command[1:3]) + f" ... (log: {log_path})")
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w", encoding="utf8") as output:
        result = subprocess.run(command, stdout=output, stderr=subprocess.STDOUT, env=ns_train_environment())
    if result.returncode != 0:
        tail = "\n".join(log_path.read_text(encoding="utf8", errors="replace").splitlines()[-30:])
        raise RuntimeError(f"ns-train {what} failed with status {result.returncode}; log {log_path}:\n{tail}")


def _checkpoints(run: Path) -> list[Path]:
    return sorted((run / "nerfstudio_models").glob("step-*.ckpt"))


def warm_start(
    scene: Path, work: Path, scene_name: str, config: PhotometricConfig, dataparser_arguments: tuple[str, ...] = ()
) -> Path:
    """Train on the input cameras (camera learning rate frozen); return a checkpoint folder without camera-optimizer
    state. ``dataparser_arguments`` start with the dataparser subcommand."""
    command = [
        *_arguments(
            "s2camp", scene, work, scene_name, "warm-start", config.warm_start, config.warm_start,
            config.rays_per_batch,
        ),
        *camera_schedule_arguments(FROZEN_LR, FROZEN_LR),
        *dataparser_arguments,
    ]  # fmt: skip
    run = work / scene_name / "s2camp" / "warm-start"
    _run_ns_train(command, work / f"{scene_name}-warm-start.log", f"{scene_name} warm start")
    state = torch.load(_checkpoints(run)[-1], map_location="cpu", weights_only=True)
    # Every variant starts from the same field; the camera parameters (whose shapes differ between camera
    # optimizers) and their Adam state start fresh. nerfstudio loads the pipeline non-strictly.
    stripped = {
        "step": state["step"],
        "pipeline": {key: value for key, value in state["pipeline"].items() if ".camera_optimizer." not in key},
        "optimizers": {key: value for key, value in state["optimizers"].items() if key != "camera_opt"},
        "scalers": state["scalers"],
    }
    folder = work / f"{scene_name}-warm-start-fields"
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(stripped, folder / f"step-{state['step']:09d}.ckpt")
    return folder


def train_variant(
    scene: Path, work: Path, scene_name: str, warm: Path | None, variant: str, seed: int, config: PhotometricConfig
) -> Path:
    method, timestamp = METHODS[variant], run_timestamp(variant, seed, config)
    command = variant_command(
        scene, work, scene_name, warm, method, timestamp, _variant_arguments(variant, seed, config),
        perturbation_arguments(config), config,
    )  # fmt: skip
    return train_from_warm_start(command, work, scene_name, method, timestamp)


def train_from_warm_start(command: list[str], work: Path, scene_name: str, method: str, timestamp: str) -> Path:
    """Run one ``variant_command``; returns the run folder."""
    _run_ns_train(command, work / f"{scene_name}-{timestamp}.log", f"{scene_name} {timestamp}")
    return work / scene_name / method / timestamp


def variant_command(
    scene: Path,
    work: Path,
    scene_name: str,
    warm: Path | None,
    method: str,
    timestamp: str,
    method_arguments: list[str],
    dataparser_arguments: list[str],
    config: PhotometricConfig,
) -> list[str]:
    """One ``ns-train <method>`` run of ``config.iterations`` from the warm start (every variant's camera schedule);
    ``dataparser_arguments`` start with the dataparser subcommand."""
    command = [
        *_arguments(
            method, scene, work, scene_name, timestamp, config.iterations, config.checkpoint_every,
            config.rays_per_batch,
        ),
        *camera_schedule_arguments(config.camera_lr, config.camera_lr_final, config.iterations),
        *method_arguments,
    ]  # fmt: skip
    if warm is not None:
        command += ["--load-dir", str(warm), "--load-scheduler", "False"]
    return command + list(dataparser_arguments)


def seconds_per_iteration(run: Path) -> float:
    """Mean wall-clock seconds per training step from nerfstudio's per-step tensorboard events."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = sorted(run.glob("events.out.tfevents.*"))
    if not events:
        return math.nan
    accumulator = EventAccumulator(str(events[-1]), size_guidance={"scalars": 0})
    accumulator.Reload()
    stamps = accumulator.Scalars("Train Iter (time)")
    stamps = stamps[SKIPPED_TIMING_STEPS:] if len(stamps) > SKIPPED_TIMING_STEPS + 1 else stamps
    if len(stamps) < 2:
        return math.nan
    return (stamps[-1].wall_time - stamps[0].wall_time) / (stamps[-1].step - stamps[0].step)


def _load_pipeline(run: Path):
    """The run's pipeline (nerfstudio's eval_setup, latest checkpoint), start-up chatter kept off the terminal."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured), contextlib.redirect_stderr(captured), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from nerfstudio.utils.eval_utils import eval_setup

            _, pipeline, _, _ = eval_setup(run / "config.yml", test_mode="test")
    except Exception:
        log(captured.getvalue())
        raise
    return pipeline


def _errors(model) -> dict[str, float]:
    """Mean errors of the training cameras as the model sees them, after similarity alignment (its own logging)."""
    errors = model.update_camera_errors()
    return {key: errors[f"camera_errors/{key}_mean"] for key in ("rot_err", "pos_err", "focal_err")}


def evaluate_run(run: Path, warm_step: int, config: PhotometricConfig) -> dict:
    """Camera errors of every checkpoint (the curve), then held-out metrics after test-time alignment."""
    from s2camp_ns.scripts.test_time_alignment import evaluate_held_out_views

    pipeline = _load_pipeline(run)
    model = pipeline.model
    history = []
    for checkpoint in _checkpoints(run):
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
        pipeline.load_pipeline(state["pipeline"], state["step"])
        history.append({"iteration": state["step"] - warm_step, **_errors(model)})
    views = evaluate_held_out_views(pipeline, config.alignment)
    result = {
        "start": _start_errors(model),
        "history": history,
        "final": history[-1],
        "psnr": sum(v.psnr for v in views) / len(views),
        "ssim": sum(v.ssim for v in views) / len(views),
        "lpips": sum(v.lpips for v in views) / len(views),
        "psnr_unaligned": sum(v.psnr_unaligned for v in views) / len(views),
        "eval_views": len(views),
        "sec_per_iter": seconds_per_iteration(run),
    }
    return result


def _start_errors(model) -> dict[str, float]:
    """Errors of the perturbed start (identical for every variant: same cameras, zero corrections)."""
    from s2camp_ns.core.alignment import camera_errors

    cameras, reference = model._train_cameras, model.reference_cameras()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        errors = camera_errors(
            cameras.camera_to_worlds.to(torch.float64),
            reference.camera_to_worlds.to(torch.float64).cpu(),
            cameras.fx.reshape(-1).to(torch.float64),
            reference.fx.reshape(-1).to(torch.float64).cpu(),
            align=True,
        )
    return {key: errors[f"{key}_mean"] for key in ("rot_err", "pos_err", "focal_err")}


def iterations_to_fraction(history: list[dict], start: dict[str, float], key: str, fraction: float) -> float:
    """First evaluated iteration at which ``key`` is at most ``fraction`` of its start value (NaN if never)."""
    for entry in history:
        if entry[key] <= fraction * start[key]:
            return float(entry["iteration"])
    return math.nan


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


@dataclass(frozen=True)
class TrainedRun:
    """A finished ``ns-train`` run of one variant (one of CamP's seeds) on one scene, waiting for evaluation."""

    scene: str
    variant: str
    path: Path


def train_scene(
    scene_name: str, variants: tuple[str, ...], config: PhotometricConfig, root: Path, quick: bool
) -> list[TrainedRun]:
    """Generate the scene, train the shared warm start, then every variant (once per seed), one at a time."""
    scene_config = replace(SCENES[scene_name], output_dir=root / "scenes" / scene_name)
    if quick:
        scene_config = replace(scene_config, **QUICK_SCENE_SIZE)
    scene = make_scene(scene_config)
    work = root / "runs"
    shutil.rmtree(work / scene_name, ignore_errors=True)
    warm = warm_start(scene, work, scene_name, config) if config.warm_start > 0 else None
    return [
        TrainedRun(scene_name, variant, train_variant(scene, work, scene_name, warm, variant, seed, config))
        for variant in variants
        for seed in run_seeds(variant, config)
    ]


def _single_thread() -> None:
    # Two evaluations side by side on two cores: one thread each, idle OpenMP threads not spinning.
    torch.set_num_threads(1)


def evaluate_runs(runs: list[TrainedRun], config: PhotometricConfig) -> list[dict]:
    """``evaluate_run`` for every run, in ``config.eval_workers`` processes (results in the order of ``runs``)."""
    paths = [run.path for run in runs]
    if config.eval_workers <= 1 or len(runs) <= 1:
        return [evaluate_run(path, config.warm_start, config) for path in paths]
    context = multiprocessing.get_context("spawn")  # a forked torch (threads, OpenMP state) is not safe
    with ProcessPoolExecutor(config.eval_workers, mp_context=context, initializer=_single_thread) as pool:
        return list(pool.map(evaluate_run, paths, repeat(config.warm_start), repeat(config)))


def summarize_scene(scene_name: str, results: list[tuple[TrainedRun, dict]], tier: int = 2) -> tuple[list[dict], dict]:
    """One row per variant (the mean over its seeds, and each error's range) and the mean error curve, for one
    scene."""
    rows, histories = [], {}
    variants = list(dict.fromkeys(run.variant for run, _ in results if run.scene == scene_name))
    for variant in variants:
        chosen = [result for run, result in results if run.scene == scene_name and run.variant == variant]
        start = chosen[0]["start"]
        # mean curve over the seeds (same checkpoint steps)
        history = [{"iteration": 0, **start}] + [
            {"iteration": entries[0]["iteration"]}
            | {key: _mean([e[key] for e in entries]) for key in ("rot_err", "pos_err", "focal_err")}
            for entries in zip(*[r["history"] for r in chosen], strict=True)
        ]
        histories[(scene_name, variant)] = history
        row = {"tier": tier, "scene": scene_name, "variant": variant, "seeds": len(chosen)}
        row["intrinsics"] = "per-camera" if variant in PER_CAMERA else "per-image"
        for key in ("rot_err", "pos_err", "focal_err"):
            row[f"start_{key}"] = start[key]
            row[key] = _mean([r["final"][key] for r in chosen])
            row[f"{key}_min"] = min(r["final"][key] for r in chosen)
            row[f"{key}_max"] = max(r["final"][key] for r in chosen)
            row[f"iters_to_half_{key}"] = iterations_to_fraction(history, start, key, 0.5)
        for key in ("psnr", "ssim", "lpips", "psnr_unaligned", "sec_per_iter"):
            row[key] = _mean([r[key] for r in chosen])
        row["eval_views"] = chosen[0]["eval_views"]
        rows.append(row)
        log(
            f"recovery tier {tier} {scene_name:6s} {variant:12s} rot {row['rot_err']:.2e} pos {row['pos_err']:.2e} "
            f"focal {row['focal_err']:.3f} psnr {row['psnr']:.2f} ssim {row['ssim']:.3f} "
            f"s/iter {row['sec_per_iter']:.3f}"
        )
    baseline = next((row["sec_per_iter"] for row in rows if row["variant"] == "so3xr3"), None)
    for row in rows:
        row["time_vs_so3xr3"] = row["sec_per_iter"] / baseline if baseline else math.nan
    return rows, histories


def run_photometric(
    scenes: tuple[str, ...], variants: tuple[str, ...], config: PhotometricConfig, root: Path, quick: bool
) -> tuple[list[dict], dict]:
    if quick:  # CI: every variant runs, on the first scene only (each ns-train start-up has a fixed cost)
        config, scenes = config.quick(), scenes[:1]
    runs = [run for scene_name in scenes for run in train_scene(scene_name, variants, config, root, quick)]
    log(f"  evaluating {len(runs)} runs ({config.eval_workers} processes)")
    results = list(zip(runs, evaluate_runs(runs, config), strict=True))
    rows, histories = [], {}
    for scene_name in scenes:
        scene_rows, scene_histories = summarize_scene(scene_name, results)
        rows.extend(scene_rows)
        histories.update(scene_histories)
    return rows, histories
