"""``s2camp-bench train-time``: seconds per ``ns-train`` iteration of s2camp against nerfacto's stock optimizer.

Every method trains the same generated scene with the same batch, CPU-sized nerfacto (``s2camp_bench.demo``) and
perturbed cameras; the baseline is ``s2camp-so3xr3``, nerfstudio's SO3xR3 pose optimizer in the same pipeline, so
the difference is the camera optimizer alone (ray regeneration with intrinsics and distortion, P^-1, refreshes).
The methods run interleaved, ``rounds`` times each, so that drifts of a shared machine fall on all of them alike;
seconds per iteration come from nerfstudio's per-step tensorboard stamps (everything in the training loop,
P refreshes included, amortized over ``refresh_every``) after the first steps, and the median over rounds is
compared.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.report import markdown_table
from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import DATAPARSER_SUBCOMMAND, ns_train_arguments

from .common import DEFAULT_OUTPUT_DIR, generated_scene, in_work_folder, log, write_report
from .recovery_photometric import _run_ns_train, seconds_per_iteration

BASELINE = "s2camp-so3xr3"


@dataclass
class TrainTimeConfig:
    """Per-iteration time of ns-train s2camp / s2camp-camp relative to nerfacto's SO3xR3 optimizer (same run)."""

    methods: tuple[str, ...] = (BASELINE, "s2camp", "s2camp-camp")
    """ns-train methods; the first is the baseline of the ratios."""
    rounds: int = 3
    """Interleaved repetitions of every method."""
    iterations: int = 80
    """Training iterations per run (the first few are not timed)."""
    rays_per_batch: int = 1024
    """Training rays per iteration (as the demo and the recovery benchmark)."""
    refresh_every: int = 20
    """P refresh interval of s2camp, shorter than the default 1000 so that refreshes fall inside the timed window."""
    scene: MakeSceneConfig = field(
        default_factory=lambda: MakeSceneConfig(num_cameras=16, width=96, height=72, fov="narrow", seed=0)
    )
    """Generated scene (s2camp-make-scene settings)."""
    quick: bool = False
    """Small run for CI: one round of 8 iterations of the baseline and s2camp on a tiny scene; asserts only that it
    runs."""
    scene_dir: Path | None = None
    """Where the scene and the runs go (a temporary folder by default)."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False

    def effective(self) -> TrainTimeConfig:
        if not self.quick:
            return self
        scene = replace(self.scene, num_cameras=8, width=48, height=36)
        methods = self.methods[:2]  # the baseline and s2camp: each ns-train start-up has a fixed cost on CI's CPU
        return replace(self, methods=methods, rounds=1, iterations=8, rays_per_batch=256, refresh_every=2, scene=scene)


def _command(config: TrainTimeConfig, scene: Path, work: Path, method: str, round_index: int) -> list[str]:
    command = [
        *ns_train_arguments(
            method, scene, work, "train-time", f"round{round_index}", config.iterations, config.iterations,
            config.rays_per_batch,
        ),
        "--vis", "tensorboard",
    ]  # fmt: skip
    if method == "s2camp":  # CamP's protocol computes P once (s2camp-camp's default)
        command += ["--pipeline.model.camera-optimizer.refresh-every", str(config.refresh_every)]
    return [*command, DATAPARSER_SUBCOMMAND, "--perturbation.enabled", "True"]


def run(config: TrainTimeConfig) -> list[dict]:
    config = config.effective()
    if config.rounds < 1 or config.iterations < 2:
        raise ValueError(f"rounds must be >= 1 and iterations >= 2, got {config.rounds} and {config.iterations}")
    return in_work_folder(config.scene_dir, "s2camp-train-time-", lambda root: _run(config, root))


def _run(config: TrainTimeConfig, root: Path) -> list[dict]:
    scene = generated_scene(replace(config.scene, output_dir=root / "scene"))
    work = root / "runs"
    times: dict[str, list[float]] = {method: [] for method in config.methods}
    rows = []
    for round_index in range(config.rounds):
        for method in config.methods:
            _run_ns_train(
                _command(config, scene, work, method, round_index),
                root / f"{method}-round{round_index}.log",
                f"{method} round {round_index + 1}/{config.rounds}",
            )
            seconds = seconds_per_iteration(work / "train-time" / method / f"round{round_index}")
            times[method].append(seconds)
            rows.append({"kind": "run", "method": method, "round": round_index, "sec_per_iter": seconds})
            log(f"train-time {method:14s} round {round_index}: {seconds:.4f} s / iteration")
    baseline = statistics.median(times[config.methods[0]])
    for method in config.methods:
        median = statistics.median(times[method])
        ratios = [t / b for t, b in zip(times[method], times[config.methods[0]], strict=True)]
        rows.append(
            {
                "kind": "summary",
                "method": method,
                "rounds": config.rounds,
                "iterations": config.iterations,
                "rays_per_batch": config.rays_per_batch,
                "sec_per_iter": median,
                "min_sec_per_iter": min(times[method]),
                "max_sec_per_iter": max(times[method]),
                "ratio_to_baseline": median / baseline,
                "ratio_min": min(ratios),
                "ratio_max": max(ratios),
            }
        )
    return rows


def report(rows: list[dict], config: TrainTimeConfig) -> Path:
    config = config.effective()
    summary = [row for row in rows if row["kind"] == "summary"]
    runs = [row for row in rows if row["kind"] == "run"]
    s = config.scene
    setup = (
        f"`ns-train` on a generated {s.fov}-fov scene ({s.num_cameras} cameras, {s.width}x{s.height}), perturbed "
        f"cameras, CPU-sized nerfacto "
        f"(`s2camp_bench.train_commands.SMALL_MODEL`), {config.rays_per_batch} rays per step, "
        f"{config.iterations} iterations per run (the first steps untimed), {config.rounds} interleaved rounds; "
        f"P refreshed every {config.refresh_every} steps for s2camp, computed once for s2camp-camp. Baseline "
        f"`{config.methods[0]}`: nerfstudio's stock SO3xR3 pose optimizer in the same pipeline (data manager, "
        "model, logging). 'ratio' = median s/iter over the baseline's median; min/max = the per-round ratios."
    )
    return write_report(
        config.output_dir,
        "train-time",
        "Training time per iteration",
        "s2camp-bench train-time" + (" --quick" if config.quick else ""),
        [
            setup,
            markdown_table(
                summary,
                ["method", "sec_per_iter", "ratio_to_baseline", "ratio_min", "ratio_max"],
                ["method", "s / iter (median)", "ratio to baseline", "ratio min", "ratio max"],
            ),
            "## Every run",
            markdown_table(runs, ["method", "round", "sec_per_iter"], ["method", "round", "s / iter"]),
        ],
    )
