"""``s2camp-bench splat``: S2CamP for Gaussian splatting (``ns-train s2camp-splat``) against splatfacto with
nerfstudio's SO3xR3 pose optimizer (``s2camp-splat-so3xr3``) and without camera refinement, from accurate cameras,
the CamP perturbation and an SfM start (``grid``), on a generated scene.

Every run is one ``ns-train`` FROM SCRATCH with the method's default options and only what a CPU run needs
(``--machine.device-type cpu``: the reference rasterizer, docs/SPLAT.md sec. 4; tensorboard, no evaluation or
camera-error logging during training; ``--machine.seed`` the seed), plus the run length: ``iterations`` steps with
splatfacto's step-counted schedule (``SCHEDULE_STEPS``, SO3xR3's and S2CamP's camera schedules) scaled by
``iterations`` / 30000, so that a run goes through the phases of a 30k-step splatfacto run, and densification off
(``--pipeline.model.stop-split-at 0``: the Gaussians stay those of the start's sparse points; with it on their number
doubles at every refinement at this resolution, beyond a CPU run: docs/SPLAT.md sec. 6). Each step renders one whole
training image: passes over each training pixel = steps / training images (a 30k-step run over ~300 images makes
~100). Metrics (``evaluation.evaluate_pipeline``, as robustness's): camera errors after a similarity alignment,
drift, held-out PSNR / SSIM after test-time alignment (docs/SPLAT.md sec. 5) and before it, the start cameras'
errors, the number of Gaussians, and seconds per iteration from nerfstudio's per-step timing. The report:
``splat_report``.
"""


from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import ns_train_base_arguments
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

from . import grid
from .common import DEFAULT_OUTPUT_DIR, changed_options, generated_scene, in_work_folder, log

SCENES: dict[str, grid.GridScene] = {
    "splat-ring": grid.GridScene(
        MakeSceneConfig(num_cameras=24, width=256, height=192, focal=grid.focal_for_fov(256, 70.0), ring_radius=4.0,
                        k1=0.0, k2=0.0, points_per_image=100, seed=4), 70.0, 4,
        "24 images (21 training, every 8th held out) trained at 64x48 (SfM on 256x192), 70 deg, pinhole, cameras 4 "
        "units from the centre; splatfacto starts from the start's sparse points (about 2.4k; SfM's own for sfm)",
        downscale=4,
    ),
}  # fmt: skip
"""Small enough for the reference rasterizer on one CPU thread: 64x48 training images (``images_4``); SfM on the
full-size images makes fewer points than the generated scene (compare PSNR within a start)."""
STARTS = ("accurate", "perturbed", "sfm")
RECOVERY_STARTS = ("perturbed",)
"""Starts that refinement must correct (the report gives the fraction of the start error removed); from the others
it must do no harm (the report gives final - start)."""
VARIANTS = ("splat-off", "s2camp-splat-so3xr3", "s2camp-splat")
"""The default grid's variants."""
RUNNABLE_VARIANTS = (*VARIANTS, "s2camp-splat-tracks", "s2camp-splat-photometric")
"""Every variant this code runs: with the tracks alone and the images alone, by name (``--variants``)."""
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
"""Method options per variant beyond s2camp-splat's defaults. Committed rows under other names are reported apart
(docs/RESULTS.md, "Names that no longer run")."""
BASELINE = "s2camp-splat-so3xr3"
"""The variant whose seconds per iteration the others are compared with."""
REFERENCE_STEPS = 30000
"""splatfacto's ``max_num_iterations``: the run length its step-counted schedule is written for."""
SCHEDULE_STEPS = {
    "--pipeline.model.warmup-length": 500, "--pipeline.model.refine-every": 100,
    "--pipeline.model.resolution-schedule": 3000, "--pipeline.model.sh-degree-interval": 1000,
    "--pipeline.model.stop-split-at": 15000, "--pipeline.model.stop-screen-size-at": 4000,
    "--optimizers.means.scheduler.max-steps": 30000,
}  # fmt: skip
"""splatfacto's (nerfstudio 1.1.5) step-counted options (``reset_alpha_every`` counts refinements)."""
SO3XR3_SCHEDULE_STEPS = {
    "--optimizers.camera-opt.scheduler.warmup-steps": 1000,
    "--optimizers.camera-opt.scheduler.max-steps": 30000,
}
"""The SO3xR3 baseline's camera schedule (splatfacto's own)."""
S2CAMP_SCHEDULE_STEPS = {"--optimizers.camera-opt.scheduler.min-warmup-steps": 2500}
"""S2CamP's camera schedule is in fractions of the run but for its warm-up floor (``RunLengthScheduleConfig``)."""
DEFAULT_ITERATIONS = 1000
"""48 passes over the default scene's 21 training images."""
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
    iterations: int = DEFAULT_ITERATIONS
    workers: int = 2
    """Runs training (then evaluating) side by side, one CPU thread each."""
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    """Test-time alignment of the held-out views (splat runs render whole images: ``rays`` and ``chunk`` unused)."""
    quick: bool = False
    """Small run for CI (``QUICK``)."""
    work_dir: Path | None = None
    """Where scenes, runs and ``rows.jsonl`` go (``grid.resume``; a temporary folder by default, removed after)."""
    rows_from: Path | None = None
    """Train nothing: report the rows of a ``rows.jsonl`` written by an earlier (possibly interrupted) run."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    write: bool = True
    json: bool = False

    def effective(self) -> SplatBenchConfig:
        if not self.quick:
            return self
        alignment = replace(self.alignment, steps=QUICK_ALIGNMENT_STEPS)
        return replace(self, scenes=self.scenes[:1], alignment=alignment, **QUICK)

    def validate(self) -> None:
        grid.validate_grid(self, tuple(SCENES), STARTS, RUNNABLE_VARIANTS)

    def command(self) -> str:
        """The ``s2camp-bench`` command line that regenerates this report."""
        if self.quick:
            return "s2camp-bench splat --quick"
        names = ("scenes", "starts", "variants", "seeds", "first_seed", "iterations", "workers")
        return " ".join(["s2camp-bench splat", *changed_options(self, SplatBenchConfig(), names)])


def passes(iterations: int, scene: str) -> float:
    """Passes over each training pixel: one whole training image per step."""
    preset = SCENES[scene]
    held_out = -(-preset.scene.num_cameras // grid.EVAL_INTERVAL)
    return iterations / (preset.scene.num_cameras - held_out)


def schedule_arguments(variant: str, iterations: int) -> list[str]:
    """splatfacto's step-counted options (and the variant's camera schedule) scaled by iterations /
    ``REFERENCE_STEPS``, each at least 1 step; densification off (``--pipeline.model.stop-split-at 0``)."""
    scale = iterations / REFERENCE_STEPS
    steps = dict(SCHEDULE_STEPS)
    if METHODS[variant] == "s2camp-splat-so3xr3":
        steps |= SO3XR3_SCHEDULE_STEPS
    elif variant != "splat-off":  # S2CamP refines the cameras
        steps |= S2CAMP_SCHEDULE_STEPS
    scaled = {option: max(1, round(value * scale)) for option, value in steps.items()}
    scaled["--pipeline.model.stop-split-at"] = 0
    return [part for option, value in scaled.items() for part in (option, str(value))]


def train_command(
    spec: grid.RunSpec, scene_dir: Path, runs: Path, config: SplatBenchConfig, truth: Path | None = None
) -> list[str]:
    """``ns-train`` of one run (module docstring) and the start's data parser (``grid.start_arguments``). ``truth``:
    the generated scene, the reference cameras of an sfm start (``scene_dir`` is then SfM's)."""
    return [
        *ns_train_base_arguments(
            METHODS[spec.variant], scene_dir, runs, spec.experiment, spec.timestamp, config.iterations,
            config.iterations,
        ),
        "--machine.device-type", "cpu",
        "--machine.seed", str(spec.seed),
        "--vis", "tensorboard",
        "--pipeline.model.camera-error-every", "0",
        *schedule_arguments(spec.variant, config.iterations),
        *VARIANT_ARGUMENTS.get(spec.variant, []),
        *grid.start_arguments(spec, SCENES[spec.scene], truth),
    ]  # fmt: skip


def run_folder(spec: grid.RunSpec, runs: Path) -> Path:
    return runs / spec.experiment / METHODS[spec.variant] / spec.timestamp


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


_SFM_FOLDER_LOCK = threading.Lock()


def _sfm_start(name: str, truth: Path, root: Path) -> Path:
    """The grid's SfM of the scene (once, shared by its runs), with the true scene's images_4 linked in."""
    output = grid.sfm_scene(name, truth, root)
    with _SFM_FOLDER_LOCK:
        link = output / "images_4"
        if (truth / "images_4").is_dir() and not link.exists():
            link.symlink_to((truth / "images_4").resolve(), target_is_directory=True)
    return output


def evaluate_splat_run(run: Path, alignment: AlignmentConfig) -> dict:
    """Robustness's evaluation of a finished run, plus its number of Gaussians."""
    import contextlib
    import sys

    from .evaluation import evaluate_pipeline, load_pipeline

    began = time.perf_counter()
    pipeline = load_pipeline(run)
    # splatfacto's data manager caches the held-out images on first use and says so on stdout: keep --json's clean.
    with contextlib.redirect_stdout(sys.stderr):
        result = evaluate_pipeline(pipeline, alignment)
    result["gaussians"] = int(pipeline.model.num_points)
    result["eval_seconds"] = time.perf_counter() - began
    return result


def _run_one(spec: grid.RunSpec, scene_dir: Path, root: Path, config: SplatBenchConfig, pool, invocation: str) -> dict:
    """Train, evaluate and record one run; its row."""
    truth = None
    if spec.start == "sfm":
        truth, scene_dir = scene_dir, _sfm_start(spec.scene, scene_dir, root)
    log_path = root / "logs" / f"{spec.experiment}-{spec.timestamp}.log"
    train_seconds = grid.train_logged(train_command(spec, scene_dir, root / "runs", config, truth), log_path, spec)
    folder = run_folder(spec, root / "runs")
    result = pool.submit(evaluate_splat_run, folder, config.alignment).result()
    row = grid.evaluated_row(spec, result, config.iterations, train_seconds, folder)
    row |= {"passes": passes(config.iterations, spec.scene), "gaussians": result["gaussians"]}
    row |= {"workers": config.workers, "invocation": invocation}
    grid.record_row(row, folder, root)
    return row


def run(config: SplatBenchConfig) -> list[dict]:
    config = config.effective()
    config.validate()
    if config.rows_from is not None:
        return grid.read_rows(config.rows_from)
    return in_work_folder(config.work_dir, "splat-", lambda root: _run(config, root))


def _run(config: SplatBenchConfig, root: Path) -> list[dict]:
    (root / "logs").mkdir(parents=True, exist_ok=True)
    scene_dirs = {}
    for name in config.scenes:
        scene_dirs[name] = generated_scene(replace(SCENES[name].scene, output_dir=root / "scenes" / name))
        if SCENES[name].downscale == 4:  # make_scene writes images and images_2
            add_quarter_images(scene_dirs[name])
    done, specs = grid.resume(grid.run_specs(config), root)
    already = f"; {len(done)} already in {grid.ROWS_FILE}" if done else ""
    log(
        f"splat: {len(specs)} runs of {config.iterations} iterations ({passes(config.iterations, config.scenes[0]):.0f}"
        f" passes), {config.workers} at a time (work: {root}){already}"
    )
    invocation = time.strftime("%Y-%m-%dT%H:%M:%S")  # the rows of one invocation share the machine's load
    run_one = lambda spec, pool: _run_one(spec, scene_dirs[spec.scene], root, config, pool, invocation)  # noqa: E731
    return done + grid.run_side_by_side(specs, run_one, config.workers)


def report(rows: list[dict], config: SplatBenchConfig) -> Path:
    """The report (``splat_report.write``)."""
    from .splat_report import write

    return write(rows, config.effective())
