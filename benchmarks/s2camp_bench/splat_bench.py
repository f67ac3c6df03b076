"""``s2camp-bench splat``: S2CamP for Gaussian splatting (``ns-train s2camp-splat``) against splatfacto with
nerfstudio's SO3xR3 pose optimizer (``s2camp-splat-so3xr3``) and without camera refinement, from accurate cameras,
the CamP perturbation and an SfM start, on a generated scene (issue 20).

Protocol (every run alike): start {accurate, perturbed, sfm} x variant {splat-off, s2camp-splat-so3xr3,
s2camp-splat} x seeds. Every run is one ``ns-train`` FROM SCRATCH with the method's default options except:

- what a CPU run needs: ``--machine.device-type cpu`` (the model then picks the reference rasterizer, docs/SPLAT.md
  sec. 4), tensorboard instead of the viewer, no evaluation and no camera-error logging during training (errors are
  computed afterwards, identically for every variant), ``--machine.seed`` the seed. None of the nerfacto runs'
  options (``train_commands.SMALL_MODEL``, the ray batch): splatfacto renders whole images and has neither;
- the run length: ``--max-num-iterations`` ``iterations`` and, with ``compress_schedule`` (default), splatfacto's
  step-counted schedule (``SCHEDULE_STEPS``: warm-up, densification interval and stop, resolution doubling, SH
  degree interval, the means' and SO3xR3's learning-rate schedules) scaled by ``iterations`` / 30000, so that the
  run goes through the phases of a 30k-step splatfacto run. S2CamP's camera schedule is stated in fractions of the
  run already (``method_config.camera_schedule_for``) except its 2500-step warm-up floor, scaled likewise
  (``S2CAMP_SCHEDULE_STEPS``); SO3xR3's is splatfacto's absolute one (1000-step warm-up,
  decay over 30k) and is scaled with the rest. ``--compress-schedule False`` keeps every default;
- densification off unless ``--densify True`` (``--pipeline.model.stop-split-at 0``: gsplat's strategy then neither
  grows, prunes nor resets opacities): the Gaussians are those of the start's sparse points, trained in position,
  shape, colour and opacity. With it on (this scene, 1000 steps, refinement every 3 steps from step 17), at
  splatfacto's initial 1/4 resolution (16x12 px) nearly every Gaussian passes the gradient threshold at every
  refinement, so their number doubles each time and the reference rasterizer's step cost grows with it: beyond a CPU
  run (measured in docs/SPLAT.md sec. 6, "Densification off"). The same for every variant.

Variants: "splat-off" is ``ns-train s2camp-splat --pipeline.model.camera-optimizer.mode off``; the others are the
``ns-train`` methods of those names. Starts: robustness's (``benchmarks/s2camp_bench/robustness.py``): "accurate" the generated
scene's true cameras, "perturbed" the data parser's CamP perturbation (CamP's sigmas, the scene's perturbation
seed), "sfm" pycolmap SfM on the full-size images with robustness's focal prior, evaluated against the true cameras.

Regime: each splatfacto step renders one whole training image, so passes over each training pixel = steps /
training images. A real splatfacto run is 30k steps over ~300 images, ~100 passes; the default scene and
``iterations`` put a run in that range (``DEFAULT_ITERATIONS``). Every row records its passes.

Metrics (``s2camp_bench.evaluation.evaluate_pipeline``, as robustness's, identical for every variant):
rotation / position / focal errors of the final training cameras after a similarity alignment to the true ones,
drift, held-out PSNR / SSIM after test-time alignment (docs/SPLAT.md sec. 5) and before it (unaligned); the same
errors of the start cameras; the number of Gaussians at the end; training seconds per iteration from nerfstudio's
per-step timing, and its ratio to s2camp-splat-so3xr3's from the same start in the same invocation (runs train
``workers`` at a time on one thread each: the ratio compares runs that shared the machine alike).
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.report import markdown_table
from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import DATAPARSER_SUBCOMMAND, ns_train_base_arguments
from s2camp_ns.core.validation import check_choice, check_positive_int
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

from .common import (
    DEFAULT_OUTPUT_DIR,
    changed_options,
    generated_scene,
    in_report_order,
    in_work_folder,
    log,
    no_longer_run_section,
    split_runnable,
    write_report,
)
from .data_parser import SUBCOMMAND as BENCH_DATAPARSER
from .robustness import (
    ERRORS,
    METRICS,
    ROWS_FILE,
    SFM_FOCAL_PRIOR,
    RobustnessScene,
    RunSpec,
    Spread,
    _sfm_scene,
    focal_for_fov,
    plot,
    read_rows,
    record_row,
    resume,
    run_side_by_side,
    seeds_cell,
    train_logged,
)

SCENES: dict[str, RobustnessScene] = {
    "splat-ring": RobustnessScene(
        MakeSceneConfig(
            num_cameras=24, width=256, height=192, focal=focal_for_fov(256, 70.0), ring_radius=4.0, k1=0.0, k2=0.0,
            points_per_image=100, seed=4,
        ),
        70.0,
        4,
        "24 images (21 training, every 8th held out) trained at 64x48 (SfM on 256x192), 70 deg, pinhole, cameras 4 "
        "units from the centre; splatfacto starts from the start's sparse points (about 2.4k; SfM's own for sfm)",
        downscale=4,
    ),
}  # fmt: skip
"""The benchmark's scenes (``RobustnessScene``: generated, pinhole, SfM on the full-size images). Small enough for
the reference rasterizer on one CPU thread: 64x48 training images (``images_4``, ``add_quarter_images``). SfM needs
the larger full-size images: on this scene at 128x96 pycolmap registered a few of the 24 images, at 256x192 all of
them, with far fewer points than the generated scene's: the sfm start's runs train fewer Gaussians than the others
(compare PSNR between the variants of one start). The SfM start's errors are in the report's rows (``start_*``)."""
STARTS = ("accurate", "perturbed", "sfm")
RECOVERY_STARTS = ("perturbed",)
"""Starts that refinement must correct (the report gives the fraction of the start error removed); from the others
it must do no harm (the report gives final - start)."""
VARIANTS = ("splat-off", "s2camp-splat-so3xr3", "s2camp-splat")
"""The default grid's variants (issue 20's comparison)."""
EVIDENCE_VARIANTS = ("s2camp-splat-tracks", "s2camp-splat-photometric")
"""What each evidence gives alone, run by name (``--variants``): the tracks alone and the images alone."""
RUNNABLE_VARIANTS = VARIANTS + EVIDENCE_VARIANTS
"""Every variant this code runs; committed rows under other names are reported apart."""
METHODS = {
    "splat-off": "s2camp-splat", "s2camp-splat-so3xr3": "s2camp-splat-so3xr3", "s2camp-splat": "s2camp-splat",
    "s2camp-splat-tracks": "s2camp-splat", "s2camp-splat-photometric": "s2camp-splat",
}  # fmt: skip
_OPTIMIZER = "--pipeline.model.camera-optimizer"
VARIANT_ARGUMENTS = {
    "splat-off": [f"{_OPTIMIZER}.mode", "off"],
    "s2camp-splat-tracks": [f"{_OPTIMIZER}.photometric", "False", f"{_OPTIMIZER}.track-prior", "True"],
    "s2camp-splat-photometric": [f"{_OPTIMIZER}.track-prior", "False"],
}  # fmt: skip
"""Method options per variant: "splat-off" is s2camp-splat without camera refinement; "s2camp-splat" its defaults
(common rotation removed, track prior on: ``method_config.SPLAT_CAMERA_OPTIMIZER``); "s2camp-splat-tracks" the
tracks alone (every camera at its track prior's anchor, the images move none); "s2camp-splat-photometric" the images
alone (the defaults without the prior). Committed rows under other variant
names were recorded with settings that no longer run: the report lists them apart, and docs/RESULTS.md ("Names that
no longer run") says what each ran."""
BASELINE = "s2camp-splat-so3xr3"
"""The variant whose seconds per iteration the others are compared with."""
REFERENCE_STEPS = 30000
"""splatfacto's ``max_num_iterations``: the run length its step-counted schedule is written for."""
SCHEDULE_STEPS = {
    "--pipeline.model.warmup-length": 500,
    "--pipeline.model.refine-every": 100,
    "--pipeline.model.resolution-schedule": 3000,
    "--pipeline.model.sh-degree-interval": 1000,
    "--pipeline.model.stop-split-at": 15000,
    "--pipeline.model.stop-screen-size-at": 4000,
    "--optimizers.means.scheduler.max-steps": 30000,
}
"""splatfacto's (nerfstudio 1.1.5) step-counted options, scaled by iterations / ``REFERENCE_STEPS`` with
``compress_schedule``. ``reset_alpha_every`` counts refinements, so it follows ``refine_every``."""
SO3XR3_SCHEDULE_STEPS = {
    "--optimizers.camera-opt.scheduler.warmup-steps": 1000,
    "--optimizers.camera-opt.scheduler.max-steps": 30000,
}
"""The SO3xR3 baseline's camera schedule (splatfacto's own, ``method_config.make_splat_trainer_config``)."""
S2CAMP_SCHEDULE_STEPS = {"--optimizers.camera-opt.scheduler.min-warmup-steps": 2500}
"""S2CamP's camera schedule is in fractions of the run except its warm-up floor (``RunLengthScheduleConfig``), 2500
steps whatever the run length: uncompressed, a 1000-step run would stay inside the warm-up, at about a third of the
camera learning rate at its last step."""
DEFAULT_ITERATIONS = 1000
"""1000 steps over the default scene's 21 training images: 48 passes (a 30k-step splatfacto run over ~300 images
makes ~100)."""
QUICK = {"iterations": 30, "seeds": 1, "starts": ("perturbed",), "variants": VARIANTS}
"""``--quick``: a CI-sized run, the three variants from the perturbed start, 5 test-time alignment steps."""
QUICK_ALIGNMENT_STEPS = 5


@dataclass
class SplatBenchConfig:
    """s2camp-splat against splatfacto with SO3xR3 and without camera refinement (module docstring)."""

    scenes: tuple[str, ...] = ("splat-ring",)
    """Scenes (``SCENES``)."""
    starts: tuple[str, ...] = STARTS
    variants: tuple[str, ...] = VARIANTS
    seeds: int = 3
    """Runs per scene, start and variant, ``--machine.seed`` first_seed .. first_seed + seeds - 1."""
    first_seed: int = 0
    """The first seed: a grid that spans sessions adds seeds later without re-running the first ones."""
    iterations: int = DEFAULT_ITERATIONS
    """``--max-num-iterations`` of every run."""
    compress_schedule: bool = True
    """Scale splatfacto's step-counted schedule to ``iterations`` (module docstring); False: the defaults."""
    densify: bool = False
    """splatfacto's densification (gsplat's DefaultStrategy: growth, pruning, opacity resets). Off by default: the
    Gaussians stay those of the start's sparse points (module docstring)."""
    workers: int = 2
    """Runs training (then evaluating) side by side, one CPU thread each."""
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    """Test-time alignment of the held-out views (every run alike; splat runs render whole images, so ``rays`` and
    ``chunk`` do not apply)."""
    quick: bool = False
    """Small run for CI (``QUICK``, sized for CI's CPU cores)."""
    work_dir: Path | None = None
    """Where scenes and runs go (a temporary /tmp/splat-* folder by default, removed afterwards). Each finished run's
    row is appended to ``rows.jsonl`` there as soon as it is evaluated; a run whose row is already there is not run
    again (its row is reused), so a grid continues in its folder across sessions."""
    rows_from: Path | None = None
    """Train nothing: report the rows of a ``rows.jsonl`` written by an earlier (possibly interrupted) run."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plot (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False

    def effective(self) -> SplatBenchConfig:
        if not self.quick:
            return self
        alignment = replace(self.alignment, steps=QUICK_ALIGNMENT_STEPS)
        return replace(self, scenes=self.scenes[:1], alignment=alignment, **QUICK)

    def validate(self) -> None:
        for name, allowed in (("scenes", tuple(SCENES)), ("starts", STARTS), ("variants", RUNNABLE_VARIANTS)):
            values = getattr(self, name)
            if not values:
                raise ValueError(f"{name} must name at least one of {', '.join(allowed)}, got none")
            for value in values:
                check_choice(name, value, allowed)
        for name in ("seeds", "iterations", "workers"):
            check_positive_int(name, getattr(self, name))
        if self.first_seed < 0:
            raise ValueError(f"first_seed must be >= 0, got {self.first_seed}")
        self.alignment.validate()

    def command(self) -> str:
        """The ``s2camp-bench`` command line that regenerates this report."""
        parts = ["s2camp-bench splat"]
        if self.quick:
            return " ".join([*parts, "--quick"])
        default = SplatBenchConfig()
        names = ("scenes", "starts", "variants", "seeds", "first_seed", "iterations", "compress_schedule", "densify")
        return " ".join(parts + changed_options(self, default, (*names, "workers")))


def run_specs(config: SplatBenchConfig) -> list[RunSpec]:
    """Every run, seeds outermost, the variants of one start next to each other (their timings shared the machine
    alike)."""
    return [
        RunSpec(scene, start, variant, seed)
        for seed in range(config.first_seed, config.first_seed + config.seeds)
        for scene in config.scenes
        for start in config.starts
        for variant in config.variants
    ]


def passes(iterations: int, scene: str) -> float:
    """Passes over each training pixel: one whole training image per step."""
    preset = SCENES[scene]
    held_out = -(-preset.scene.num_cameras // 8)  # the data parser's every-8th split (robustness.EVAL_INTERVAL)
    return iterations / (preset.scene.num_cameras - held_out)


def schedule_arguments(variant: str, iterations: int, densify: bool) -> list[str]:
    """splatfacto's step-counted options (and SO3xR3's camera schedule) scaled by iterations / ``REFERENCE_STEPS``,
    each at least 1 step; without ``densify`` the strategy stops before it starts (``--pipeline.model.stop-split-at
    0``: no growth, pruning or opacity reset)."""
    scale = iterations / REFERENCE_STEPS
    steps = {option: max(1, round(value * scale)) for option, value in SCHEDULE_STEPS.items()}
    if METHODS[variant] == "s2camp-splat-so3xr3":
        steps |= {option: max(1, round(value * scale)) for option, value in SO3XR3_SCHEDULE_STEPS.items()}
    elif variant != "splat-off":  # S2CamP refines the cameras
        steps |= {option: max(1, round(value * scale)) for option, value in S2CAMP_SCHEDULE_STEPS.items()}
    if not densify:
        steps["--pipeline.model.stop-split-at"] = 0
    return [part for option, value in steps.items() for part in (option, str(value))]


def train_command(
    spec: RunSpec, scene_dir: Path, runs: Path, config: SplatBenchConfig, truth: Path | None = None
) -> list[str]:
    """``ns-train`` of one run (module docstring). ``truth``: the generated scene, the reference cameras of an sfm
    start (``scene_dir`` is then SfM's)."""
    command = [
        *ns_train_base_arguments(
            METHODS[spec.variant], scene_dir, runs, spec.experiment, spec.timestamp, config.iterations,
            config.iterations,
        ),
        "--machine.device-type", "cpu",
        "--machine.seed", str(spec.seed),
        "--vis", "tensorboard",
        "--pipeline.model.camera-error-every", "0",
        *(schedule_arguments(spec.variant, config.iterations, config.densify) if config.compress_schedule else []),
        *([] if config.densify or config.compress_schedule else ["--pipeline.model.stop-split-at", "0"]),
        *VARIANT_ARGUMENTS.get(spec.variant, []),
    ]  # fmt: skip
    preset = SCENES[spec.scene]
    subcommand = BENCH_DATAPARSER if spec.start == "sfm" else DATAPARSER_SUBCOMMAND
    dataparser = [subcommand, "--downscale-factor", str(preset.downscale)]
    if spec.start == "perturbed":
        dataparser += ["--perturbation.enabled", "True", "--perturbation.seed", str(preset.perturbation_seed)]
    if spec.start != "sfm":  # evidence that does not know the truth: the generated tracks are exact projections
        dataparser += ["--image-tracks", "always"]
    if spec.start == "sfm":
        if truth is None:
            raise ValueError("an sfm start needs the generated scene (truth) to measure against")
        dataparser += ["--reference-model", str(truth / "sparse" / "0")]
    return command + dataparser


def run_folder(spec: RunSpec, runs: Path) -> Path:
    return runs / spec.experiment / METHODS[spec.variant] / spec.timestamp


# ------------------------------------------------------------------------------------------------------------ run
def add_quarter_images(scene: Path) -> Path:
    """Write ``scene/images_4`` as the exact 2x2 box downsample of ``images_2`` (``make_scene`` writes ``images`` and
    ``images_2`` only); the data parser's ``--downscale-factor 4`` reads it."""
    import numpy as np
    from PIL import Image

    source, target = scene / "images_2", scene / "images_4"
    target.mkdir(exist_ok=True)
    for path in sorted(source.iterdir()):
        pixels = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)
        height, width = pixels.shape[0] // 2 * 2, pixels.shape[1] // 2 * 2
        if (height, width) != pixels.shape[:2]:
            raise ValueError(f"{path} is {pixels.shape[1]}x{pixels.shape[0]} px: images_2 must have even sizes")
        blocks = pixels.reshape(height // 2, 2, width // 2, 2, 3).mean(axis=(1, 3))
        Image.fromarray(np.clip(np.rint(blocks), 0, 255).astype(np.uint8)).save(target / path.name)
    return scene


def _scene_dir(name: str, root: Path) -> Path:
    """The generated scene ``name`` under ``root``, with the images_{k} folder its training resolution needs."""
    preset = SCENES[name]
    scene = generated_scene(replace(preset.scene, output_dir=root / "scenes" / name))
    if preset.downscale == 4:
        add_quarter_images(scene)
    elif preset.downscale not in (1, 2):
        message = f"scene {name}: downscale must be 1, 2 or 4 (images, images_2, images_4), got {preset.downscale}"
        raise ValueError(message)
    return scene


_SFM_FOLDER_LOCK = threading.Lock()


def _sfm_start(name: str, truth: Path, root: Path) -> Path:
    """robustness's SfM of the scene (once, shared by its runs), with the true scene's images_4 linked in."""
    output = _sfm_scene(name, truth, root)
    with _SFM_FOLDER_LOCK:
        link = output / "images_4"
        if (truth / "images_4").is_dir() and not link.exists():
            link.symlink_to((truth / "images_4").resolve(), target_is_directory=True)
    return output


def evaluate_splat_run(run: Path, alignment: AlignmentConfig) -> dict:
    """Robustness's evaluation of a finished run, plus its number of Gaussians."""
    import contextlib
    import sys

    from s2camp_bench.evaluation import evaluate_pipeline

    from .recovery_photometric import _load_pipeline

    began = time.perf_counter()
    pipeline = _load_pipeline(run)
    # splatfacto's data manager caches the held-out images on first use and says so on stdout: keep --json's clean.
    with contextlib.redirect_stdout(sys.stderr):
        result = evaluate_pipeline(pipeline, alignment)
    result["gaussians"] = int(pipeline.model.num_points)
    result["eval_seconds"] = time.perf_counter() - began
    return result


def _train(spec: RunSpec, scene_dir: Path, root: Path, config: SplatBenchConfig, truth: Path | None) -> float:
    """Train one run; return its wall-clock seconds (start-up included)."""
    command = train_command(spec, scene_dir, root / "runs", config, truth)
    return train_logged(command, root / "logs" / f"{spec.experiment}-{spec.timestamp}.log", spec)


def _run_one(
    spec: RunSpec, scene_dir: Path, root: Path, config: SplatBenchConfig, pool: ProcessPoolExecutor, invocation: str
) -> dict:
    from .recovery_photometric import seconds_per_iteration

    truth = None
    if spec.start == "sfm":
        truth, scene_dir = scene_dir, _sfm_start(spec.scene, scene_dir, root)
    train_seconds = _train(spec, scene_dir, root, config, truth)
    folder = run_folder(spec, root / "runs")
    result = pool.submit(evaluate_splat_run, folder, config.alignment).result()
    row = {"scene": spec.scene, "start": spec.start, "variant": spec.variant, "seed": spec.seed}
    row["passes"] = passes(config.iterations, spec.scene)
    row |= {key: result[key] for key in (*METRICS, "drift_behind", "gaussians")}
    row |= {f"start_{key}": result[f"start_{key}"] for key in (*ERRORS, "drift_behind")}
    row |= {
        "iterations": config.iterations,
        "compress_schedule": config.compress_schedule,
        "densify": config.densify,
        "workers": config.workers,
        "invocation": invocation,
        "eval_views": result["eval_views"],
        "train_seconds": train_seconds,
        "eval_seconds": result["eval_seconds"],
        "sec_per_iter": seconds_per_iteration(folder),
    }
    record_row(row, folder, root)
    log(
        f"splat {spec.scene} {spec.start:9s} {spec.variant:19s} seed {spec.seed}: rot {row['rot_err']:.3f} deg "
        f"pos {row['pos_err']:.2e} focal {row['focal_err']:.3f} px drift {row['drift_px']:.3f} px "
        f"psnr {row['psnr']:.2f} ssim {row['ssim']:.3f} (start rot {row['start_rot_err']:.3f} focal "
        f"{row['start_focal_err']:.3f}); {row['gaussians']} Gaussians; {train_seconds:.0f} s "
        f"({row['sec_per_iter']:.3f} s/step) + {row['eval_seconds']:.0f} s"
    )
    return row


def run(config: SplatBenchConfig) -> list[dict]:
    config = config.effective()
    config.validate()
    if config.rows_from is not None:
        return read_rows(config.rows_from)
    return in_work_folder(config.work_dir, "splat-", lambda root: _run(config, root))


def _run(config: SplatBenchConfig, root: Path) -> list[dict]:
    began = time.perf_counter()
    (root / "logs").mkdir(parents=True, exist_ok=True)
    scene_dirs = {name: _scene_dir(name, root) for name in config.scenes}
    done, specs = resume(run_specs(config), root)
    log(
        f"splat: {len(specs)} runs of {config.iterations} iterations ({passes(config.iterations, config.scenes[0]):.0f}"
        f" passes), {config.workers} at a time (work: {root})"
        + (f"; {len(done)} already in {ROWS_FILE}" if done else "")
    )
    invocation = time.strftime("%Y-%m-%dT%H:%M:%S")  # the rows of one invocation share the machine's load
    rows = run_side_by_side(
        specs, lambda spec, pool: _run_one(spec, scene_dirs[spec.scene], root, config, pool, invocation), config.workers
    )
    run.minutes = (time.perf_counter() - began) / 60.0  # type: ignore[attr-defined]
    return done + rows


# --------------------------------------------------------------------------------------------------------- report
SUMMARY_METRICS = (*METRICS, "sec_per_iter", "gaussians")


def summarize(rows: list[dict]) -> list[dict]:
    """One entry per scene, start and variant: the metrics over seeds (``Spread``); the start errors (equal for
    every seed); for a recovery start the fraction of each start error removed (1 - mean final / start), for the
    others the change final - start; the PSNR differences against SO3xR3 and splat-off; the ratio of the mean
    seconds per iteration to SO3xR3's from the same start and invocation (``_time_ratio``). Sorted by scene, start and
    variant in the order the benchmark lists them."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["scene"], row["start"], row["variant"]), []).append(row)
    summary = []
    for (scene, start, variant), chosen in groups.items():
        entry = {"scene": scene, "start": start, "variant": variant, "seeds": len(chosen)}
        entry["seed_list"] = sorted(row["seed"] for row in chosen)
        entry["passes"] = statistics.fmean(row["passes"] for row in chosen)
        for key in SUMMARY_METRICS:
            entry[key] = Spread.of([float(row[key]) for row in chosen])
        for key in ERRORS:
            start_value = statistics.fmean(row[f"start_{key}"] for row in chosen)
            entry[f"start_{key}"] = start_value
            entry[f"removed_{key}"] = (
                1.0 - entry[key].mean / start_value if start in RECOVERY_STARTS and start_value > 0 else math.nan
            )
            entry[f"change_{key}"] = entry[key].mean - start_value
        summary.append(entry)
    by_key = {(e["scene"], e["start"], e["variant"]): e for e in summary}
    for entry in summary:
        for other, label in ((BASELINE, "so3xr3"), ("splat-off", "off")):
            reference = by_key.get((entry["scene"], entry["start"], other))
            entry[f"psnr_vs_{label}"] = math.nan if reference is None else entry["psnr"].mean - reference["psnr"].mean
        entry["time_ratio"] = _time_ratio(groups[(entry["scene"], entry["start"], entry["variant"])],
                                          groups.get((entry["scene"], entry["start"], BASELINE), []))  # fmt: skip
    return in_report_order(summary, tuple(SCENES), STARTS, RUNNABLE_VARIANTS)


def _time_ratio(rows: list[dict], baseline: list[dict]) -> float:
    """Mean seconds per iteration over the baseline's, from the rows of the invocations both have runs in: the
    machine is shared, so seconds from different invocations are not comparable (the same settings ran several
    times faster on one day than on another). Rows from before invocations were recorded share the invocation ''."""
    shared = {row.get("invocation", "") for row in rows} & {row.get("invocation", "") for row in baseline}
    mine = [row["sec_per_iter"] for row in rows if row.get("invocation", "") in shared]
    theirs = [row["sec_per_iter"] for row in baseline if row.get("invocation", "") in shared]
    if not mine or not theirs:
        return math.nan
    return statistics.fmean(mine) / statistics.fmean(theirs)


def _errors_cell(entry: dict) -> str:
    if entry["start"] in RECOVERY_STARTS:
        return ", ".join(f"{key.split('_')[0]} {entry[f'removed_{key}']:.0%}" for key in ERRORS)
    return ", ".join(f"{key.split('_')[0]} {entry[f'change_{key}']:+.3g}" for key in ERRORS)


def _signed(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:+.2f}"


def _summary_rows(summary: list[dict]) -> list[dict]:
    table = []
    for entry in summary:
        row = {key: entry[key] for key in ("scene", "start", "variant")}
        row["seeds"] = seeds_cell(entry["seed_list"])
        row |= {key: entry[key].cell() for key in METRICS}
        gaussians = entry["gaussians"]
        row["gaussians"] = f"{gaussians.mean:.0f}" + (
            f" [{gaussians.low:.0f}, {gaussians.high:.0f}]" if gaussians.count > 1 else ""
        )
        row["sec_per_iter"] = entry["sec_per_iter"].cell(2)
        row["passes"] = f"{entry['passes']:.1f}"
        row["start_errors"] = " / ".join(f"{entry[f'start_{key}']:.3g}" for key in ERRORS)
        row["against_start"] = _errors_cell(entry)
        row["psnr_vs"] = " / ".join(_signed(entry[f"psnr_vs_{label}"]) for label in ("so3xr3", "off"))
        row["time_ratio"] = "" if math.isnan(entry["time_ratio"]) else f"{entry['time_ratio']:.2f}"
        table.append(row)
    return table


def _setup_text(rows: list[dict], config: SplatBenchConfig) -> str:
    """The report's paragraph on how every run trained and was measured, and what each column means."""
    seeds = ", ".join(str(value) for value in sorted({row["seed"] for row in rows}))
    setup = (
        f"Every run: `ns-train <method>` from scratch with the method's defaults and only what a CPU run needs "
        f"(`--machine.device-type cpu`: the reference rasterizer; no evaluation or camera-error logging during "
        f"training), `--machine.seed` {seeds}. 'splat-off' is `ns-train s2camp-splat "
        f"--pipeline.model.camera-optimizer.mode off`. Starts: 'accurate' the true cameras, 'perturbed' the data "
        f"parser's CamP perturbation, 'sfm' pycolmap SfM on the full-size images (focal prior {SFM_FOCAL_PRIOR} x the "
        f"true focal). Errors of the final cameras after a similarity alignment to the true ones: rotation (deg), "
        f"position (normalized scene units), focal (px at the training resolution); drift = RMS pixel displacement "
        f"of the scene's points between the true and the aligned refined cameras. PSNR / SSIM: held-out views "
        f"(every 8th image) after {config.alignment.steps} test-time alignment steps (docs/SPLAT.md sec. 5); "
        f"'unaligned' before them. Cells: mean [min, max] over seeds. 'against start': for the perturbed start the "
        f"fraction of each start error removed (1 - final / start; negative: the error grew), for the others "
        f"final - start (rot / pos / focal / drift; positive: worse). 'PSNR vs': difference of the mean PSNR "
        f"against s2camp-splat-so3xr3 / splat-off ('-': no such run). 'time ratio': mean seconds per iteration "
        f"over s2camp-splat-so3xr3's from the same start and the same invocation of the benchmark (empty where "
        f"none ran in one: the machine is shared, so seconds of different invocations are not comparable; runs "
        f"that trained side by side share the CPU: compare "
        f"ratios only between runs of the same `--workers`; `--workers 1` on an idle machine times cleanest)."
    )
    rebuilt = [row for row in rows if row.get("reconstructed")]
    if rebuilt:
        setup += (
            f" {len(rebuilt)} row(s) were rebuilt from their run's log line (their `reconstructed` field says why): "
            f"their unaligned PSNR was not logged, so it is nan and so is every mean that includes it."
        )
    return setup


def report(rows: list[dict], config: SplatBenchConfig) -> Path:
    config = config.effective()
    summary = summarize(rows)
    iterations = ", ".join(str(value) for value in sorted({row["iterations"] for row in rows}))
    run_passes = ", ".join(f"{value:.1f}" for value in sorted({row["passes"] for row in rows}))
    compressed = sorted({row.get("compress_schedule", True) for row in rows})
    densified = sorted({row.get("densify", False) for row in rows})
    workers = ", ".join(str(value) for value in sorted({row.get("workers", config.workers) for row in rows}))
    plot(summary, config.output_dir / "splat.png")
    scene_rows = [
        {
            "scene": name, "images": SCENES[name].scene.num_cameras,
            "size": f"{SCENES[name].scene.width // SCENES[name].downscale}x"
            f"{SCENES[name].scene.height // SCENES[name].downscale}",
            "fov": f"{SCENES[name].fov_degrees:g} deg", "what": SCENES[name].varies,
        }
        for name in dict.fromkeys(row["scene"] for row in rows)
    ]  # fmt: skip
    header = (
        f"**Regime: {iterations} steps = {run_passes} passes over each training pixel** (one whole training image per "
        f"step; a 30k-step splatfacto run over ~300 images makes ~100). splatfacto's step-counted schedule "
        + ("scaled to the run length (`SCHEDULE_STEPS`)" if compressed == [True] else "as in a 30k-step run")
        + "; densification "
        + {(False,): "off (the start's sparse points only)", (True,): "on"}.get(tuple(densified), "mixed")
        + "."
    )
    setup = _setup_text(rows, config)
    columns = [
        "start", "variant", "seeds", "passes", "start_errors", *METRICS, "against_start", "psnr_vs", "gaussians",
        "sec_per_iter", "time_ratio",
    ]  # fmt: skip
    headers = [
        "start", "variant", "seeds", "passes", "start rot / pos / focal / drift", "rot err (deg)", "pos err",
        "focal err (px)", "drift (px)", "PSNR", "SSIM", "PSNR unaligned", "against start", "PSNR vs so3xr3 / off",
        "Gaussians", "s / iteration", "time ratio vs so3xr3",
    ]  # fmt: skip

    def average(key: str) -> float:
        return statistics.fmean(row[key] for row in rows)

    timing = (
        f"{len(rows)} runs; per run on average: training {average('train_seconds'):.0f} s (start-up included), "
        f"evaluation {average('eval_seconds'):.0f} s; {workers} run(s) side by side, one thread each"
    )
    minutes = getattr(run, "minutes", None)
    if config.rows_from is not None:
        timing += f"; rows read from `{config.rows_from.name}` of an earlier run"
    elif minutes is not None:
        timing += f"; wall time of this run {minutes:.1f} minutes"
    current, old = split_runnable(_summary_rows(summary), RUNNABLE_VARIANTS, STARTS)
    sections = [
        "s2camp-splat against splatfacto with SO3xR3 and without camera refinement (issue 20). Protocol and "
        "metrics: `benchmarks/s2camp_bench/splat_bench.py`.",
        header,
        "## Scenes",
        markdown_table(scene_rows, ["scene", "images", "size", "fov", "what"]),
        "## Results",
        setup,
        markdown_table(current, columns, headers),
        "![PSNR and drift per variant](splat.png)",
        timing + ".",
        *(no_longer_run_section(markdown_table(old, columns, headers)) if old else []),
    ]
    return write_report(
        config.output_dir, "splat", "Splatting: s2camp-splat against splatfacto with SO3xR3 and without refinement",
        config.command(), sections,
    )  # fmt: skip
