"""A grid of ``ns-train`` runs (scene x start x variant x seed) on generated scenes, shared by ``s2camp-bench
robustness`` and ``s2camp-bench splat``: the data parser's options of each start, runs side by side on one CPU thread
each, their rows, and the rows file a grid continues from across sessions.

Starts (none feeds the method anything made from the true cameras): "accurate" the true cameras; "perturbed" CamP's
perturbation (one seed per scene); "phone" ``PHONE_PROFILE``; "sfm" pycolmap SfM of the full-size images with
``SFM_FOCAL_PRIOR`` (once per work folder), measured against the true cameras (``--reference-model``). Every start but
sfm trains with tracks made from its images with its start cameras (``--image-tracks always``: the scene's own are
exact projections through the true cameras), sfm with SfM's.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import subprocess
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import DATAPARSER_SUBCOMMAND

from .common import log
from .data_parser import SUBCOMMAND as BENCH_DATAPARSER
from .data_parser import ns_train_environment

METRICS = ("rot_err", "pos_err", "focal_err", "drift_px", "psnr", "ssim", "psnr_unaligned")
ERRORS = ("rot_err", "pos_err", "focal_err", "drift_px")
"""A row's metrics of the final cameras and held-out views (``evaluation.evaluate_pipeline``; ``start_<error>``: of
the start cameras)."""
EVAL_INTERVAL = 8
"""The data parser's default held-out interval (every 8th image, the mip-NeRF 360 protocol)."""
SFM_FOCAL_PRIOR = 1.05
"""The sfm start's focal prior: the mapper starts at this factor times the true focal, as from a capture's EXIF."""
PHONE_PROFILE = {
    "perturbation.sigma_position": 0.0, "perturbation.sigma_look_at": 0.0, "perturbation.sigma_dolly_z": 0.0,
    "perturbation.sigma_focal_length": 0.0, "drift.enabled": True, "drift.position_drift": 0.01,
    "drift.yaw_drift_deg": 1.5, "drift.tilt_deg": 0.3, "drift.focal_error": 0.015,
}  # fmt: skip
"""The phone-pose start: a phone's visual-inertial odometry poses, the data parser's VIO drift with CamP's own steps
off (``phone_drift``; the sizes: docs/benchmarks/phone-drift.md). Run seed s of a scene with perturbation seed p draws
with seed p + s (the variants of one seed share the draw)."""


def focal_for_fov(width: int, fov_degrees: float) -> float:
    """Pinhole focal length (px) of a horizontal field of view ``fov_degrees`` over ``width`` pixels."""
    return 0.5 * width / math.tan(math.radians(fov_degrees) / 2.0)


@dataclass(frozen=True)
class GridScene:
    """A generated scene of a grid and the seed of its CamP perturbation."""

    scene: MakeSceneConfig
    fov_degrees: float
    perturbation_seed: int
    varies: str
    """What the scene stands for (the report's scene table)."""
    downscale: int = 1
    """Train on ``images_{downscale}`` (SfM runs on the full-size images, as a user's COLMAP does)."""

    @property
    def training_pixels(self) -> int:
        """Pixels of the training images: every image but each ``EVAL_INTERVAL``-th (the data parser's split)."""
        s = self.scene
        held_out = -(-s.num_cameras // EVAL_INTERVAL)
        return (s.num_cameras - held_out) * (s.width // self.downscale) * (s.height // self.downscale)


@dataclass(frozen=True)
class RunSpec:
    """One training run of a grid."""

    scene: str
    start: str
    variant: str
    seed: int

    @property
    def experiment(self) -> str:
        return f"{self.scene}-{self.start}"

    @property
    def timestamp(self) -> str:
        return f"{self.variant}-seed{self.seed}"


def run_specs(config) -> list[RunSpec]:
    """Every run of ``config`` (``scenes``, ``starts``, ``variants``, ``first_seed``, ``seeds``), seeds outermost: a
    grid cut short still leaves whole seeds of every scene, start and variant."""
    return [
        RunSpec(scene, start, variant, seed) for seed in range(config.first_seed, config.first_seed + config.seeds)
        for scene in config.scenes for start in config.starts for variant in config.variants
    ]


def validate_grid(config, scenes: tuple[str, ...], starts: tuple[str, ...], variants: tuple[str, ...]) -> None:
    """Raise ``ValueError`` naming the option unless ``config``'s scenes, starts and variants are non-empty choices of
    those given, its seeds, iterations and workers positive, its first seed >= 0 and its alignment valid."""
    from s2camp_ns.core.validation import check_choice, check_positive_int

    for name, allowed in (("scenes", scenes), ("starts", starts), ("variants", variants)):
        if not getattr(config, name):
            raise ValueError(f"{name} must name at least one of {', '.join(allowed)}, got none")
        for value in getattr(config, name):
            check_choice(name, value, allowed)
    for name in ("seeds", "iterations", "workers"):
        check_positive_int(name, getattr(config, name))
    if config.first_seed < 0:
        raise ValueError(f"first_seed must be >= 0, got {config.first_seed}")
    config.alignment.validate()


def start_arguments(spec: RunSpec, scene: GridScene, truth: Path | None) -> list[str]:
    """The data parser and its options for ``spec``'s start (module docstring); ``truth``: the generated scene, whose
    cameras an sfm start is measured against."""
    subcommand = BENCH_DATAPARSER if spec.start in ("phone", "sfm") else DATAPARSER_SUBCOMMAND
    arguments = [subcommand, "--downscale-factor", str(scene.downscale)]
    if spec.start in ("perturbed", "phone"):
        seed = scene.perturbation_seed + (spec.seed if spec.start == "phone" else 0)
        arguments += ["--perturbation.enabled", "True", "--perturbation.seed", str(seed)]
    if spec.start == "phone":
        for key, value in PHONE_PROFILE.items():
            arguments += [f"--{key.replace('_', '-')}", str(value)]
    if spec.start != "sfm":
        return [*arguments, "--image-tracks", "always"]
    if truth is None:
        raise ValueError("an sfm start needs the generated scene (truth) to measure against")
    return [*arguments, "--reference-model", str(truth / "sparse" / "0")]


def train_logged(command: list[str], log_path: Path, run: RunSpec) -> float:
    """Run one ``ns-train`` command on one CPU thread, its output in ``log_path``; return its wall-clock seconds
    (start-up included). A failed run raises with the log's last 30 lines."""
    environment = ns_train_environment() | {"OMP_NUM_THREADS": "1"}
    began = time.perf_counter()
    with open(log_path, "w", encoding="utf8") as output:
        result = subprocess.run(command, stdout=output, stderr=subprocess.STDOUT, env=environment)
    if result.returncode != 0:
        tail = "\n".join(log_path.read_text(encoding="utf8", errors="replace").splitlines()[-30:])
        raise RuntimeError(f"ns-train {run} failed with status {result.returncode}; log {log_path}:\n{tail}")
    return time.perf_counter() - began


ROWS_FILE = "rows.jsonl"
_ROWS_LOCK = threading.Lock()
_SFM_LOCK = threading.Lock()


def read_rows(path: Path) -> list[dict]:
    """Rows of a ``rows.jsonl`` (one JSON object per line), in the order the runs finished."""
    if not Path(path).is_file():
        raise ValueError(f"rows_from must be an existing rows.jsonl file, got {str(path)!r}")
    return [json.loads(line) for line in Path(path).read_text(encoding="utf8").splitlines() if line.strip()]


def evaluated_row(spec: RunSpec, result: dict, iterations: int, train_seconds: float, folder: Path) -> dict:
    """The row of a trained run evaluated as ``result`` (``evaluation.evaluate_pipeline`` and ``eval_seconds``): its
    spec, ``METRICS``, start errors, length, timings and seconds per step (``evaluation.seconds_per_iteration``)."""
    from .evaluation import seconds_per_iteration

    row = {"scene": spec.scene, "start": spec.start, "variant": spec.variant, "seed": spec.seed}
    row |= {key: result[key] for key in (*METRICS, "drift_behind")}
    row |= {f"start_{key}": result[f"start_{key}"] for key in (*ERRORS, "drift_behind")}
    row |= {"iterations": iterations, "eval_views": result["eval_views"], "train_seconds": train_seconds}
    return row | {"eval_seconds": result["eval_seconds"], "sec_per_iter": seconds_per_iteration(folder)}


def record_row(row: dict, folder: Path, root: Path) -> None:
    """A finished run's row appended to ``root``'s ``ROWS_FILE`` (so a grid can span sessions) and logged, after its
    checkpoints are removed (the trainer's atomic-save folder too): the row is all that is kept of an evaluated run."""
    import shutil

    for checkpoints in ("nerfstudio_models", "nerfstudio_models.partial"):
        shutil.rmtree(folder / checkpoints, ignore_errors=True)
    with _ROWS_LOCK, open(root / ROWS_FILE, "a", encoding="utf8") as rows_file:
        rows_file.write(json.dumps(row) + "\n")
    errors = " ".join(f"{key} {row[key]:.3g} (start {row[f'start_{key}']:.3g})" for key in ERRORS)
    log(f"{row['scene']} {row['start']} {row['variant']} seed {row['seed']}: {errors}, psnr {row['psnr']:.2f}")


def resume(specs: list[RunSpec], root: Path) -> tuple[list[dict], list[RunSpec]]:
    """The rows of ``specs`` already in ``root``'s ``ROWS_FILE`` (each finished run's row is appended there as soon as
    it is evaluated, so a grid continues in its work folder, possibly in another session) and the specs still to
    run. Rows of other runs stay in the file, untouched."""
    path = root / ROWS_FILE
    rows = read_rows(path) if path.exists() else []
    finished = {(row["scene"], row["start"], row["variant"], row["seed"]): row for row in rows}
    key = lambda spec: (spec.scene, spec.start, spec.variant, spec.seed)  # noqa: E731
    done = [finished[key(spec)] for spec in specs if key(spec) in finished]
    return done, [spec for spec in specs if key(spec) not in finished]


def _single_thread() -> None:
    import torch

    torch.set_num_threads(1)


def run_side_by_side(specs: list[RunSpec], run_one: Callable, workers: int) -> list[dict]:
    """``run_one(spec, pool)`` of every spec, ``workers`` at a time (threads that each wait on their ``ns-train``),
    with a pool of as many single-threaded spawned processes for the evaluations; the rows in the specs' order."""
    context = multiprocessing.get_context("spawn")  # a forked torch (threads, OpenMP state) is not safe
    with (
        ProcessPoolExecutor(workers, mp_context=context, initializer=_single_thread) as pool,
        ThreadPoolExecutor(workers) as threads,
    ):
        futures = [threads.submit(run_one, spec, pool) for spec in specs]
        return [future.result() for future in futures]


def sfm_scene(name: str, truth: Path, root: Path) -> Path:
    """SfM of the generated scene ``truth`` (once per scene and work folder, shared by its runs): pycolmap on the
    full-size images with ``SFM_FOCAL_PRIOR``; a reconstruction that fails ``sfm.run_sfm``'s checks stops the grid."""
    from .sfm import run_sfm

    output = root / "sfm" / name
    with _SFM_LOCK:
        if not (output / "sparse" / "0" / "images.bin").exists():
            result = run_sfm(truth, output, focal_prior=SFM_FOCAL_PRIOR)
            log(
                f"{name}: SfM registered {result.registered}/{result.images} images, rot {result.rot_err_mean:.2e} "
                f"rad, centre {result.centre_err_mean:.2e}, focal {result.focal:.1f} px (true {result.true_focal:.1f})"
                + (f"; FAILED: {result.failure}" if result.failure else "")
            )
            if result.failure:
                raise RuntimeError(f"SfM of scene {name} failed: {result.failure}")
    return output

