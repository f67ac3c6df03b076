"""``s2camp-bench robustness --preset regime``: where does each evidence put the cameras in the real-training regime,
from accurate, SfM, perturbed and phone cameras?

Protocol (every run alike): one generated scene of 56 images (49 trained at 160x120, SfM on 320x240, 70 degrees),
3000 steps x 512 rays, so that each training pixel is seen 1.63 times, as in a nerfacto run (about once); starts
{accurate, perturbed, sfm, phone} (``grid``) x ``VARIANTS`` x seeds. Every run is one ``ns-train`` FROM SCRATCH with
the method's default options (its camera schedule included) and only what a CPU run needs: a small nerfacto field
(``train_commands.SMALL_MODEL``), ``--machine.device-type cpu``, no evaluation or camera-error logging during
training, tensorboard instead of the viewer; ``--machine.seed`` is the seed. Metrics of the final checkpoint
(``evaluation.evaluate_pipeline``, the same for every run): camera errors after a similarity alignment to the true
cameras, the reprojection drift, held-out PSNR / SSIM after test-time alignment; the start cameras' errors too. Up to
``workers`` runs train side by side, one thread each; each is evaluated right after it trains, then its checkpoints
are deleted. The report: ``robustness_report``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import ns_train_arguments
from s2camp_ns.core.validation import check_choice, check_positive_int
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

from . import grid
from .common import DEFAULT_OUTPUT_DIR, changed_options, generated_scene, in_work_folder, log


def _scene(num_cameras: int, width: int, height: int, fov: float, ring_radius: float, seed: int) -> MakeSceneConfig:
    """A pinhole scene (CamP's perturbation zeroes distortion: a distorted scene would keep an error no variant
    removes)."""
    focal, size = grid.focal_for_fov(width, fov), dict(num_cameras=num_cameras, width=width, height=height)
    return MakeSceneConfig(**size, focal=focal, ring_radius=ring_radius, k1=0.0, k2=0.0, seed=seed)


REGIME_VARIES = (
    "the real-training regime: 49 training images trained at 160x120 (SfM on 320x240), 70 deg; 3000 steps x 512 rays "
    "see each training pixel 1.6 times (a nerfacto run about once)"
)
SCENES: dict[str, grid.GridScene] = {
    "regime-wide": grid.GridScene(_scene(56, 320, 240, 70.0, 4.0, seed=3), 70.0, 3, REGIME_VARIES, downscale=2),
    "small-narrow-far": grid.GridScene(
        _scene(16, 48, 36, 40.0, 7.0, seed=0), 40.0, 0,
        "48x36 px, 40 deg, 16 images, cameras 7 units from the centre: distant objects, shallow depth range",
    ),
}  # fmt: skip
"""The runnable scenes: the regime's, and a tiny one for ``--quick``."""
RETIRED_SCENES: dict[str, grid.GridScene] = {
    "regime-wide-full": grid.GridScene(
        SCENES["regime-wide"].scene, 70.0, 3,
        "regime-wide trained at its full 320x240 (4x the pixels per image); 3000 steps x 512 rays see each training "
        "pixel 0.41 times: whether four times the pixels let the images gain on the keypoints",
    ),
}  # fmt: skip
"""Scenes of committed rows that no longer run (their question is answered), described for the report's table."""
STARTS = ("accurate", "perturbed", "sfm", "phone")
"""The starts (``grid``); committed rows of retired starts (accurate-untracked, phone-iid) are reported apart."""
OFF_REFERENCE_START = {"accurate-untracked": "accurate"}
"""Starts whose 'PSNR vs off' compares with refinement off from another start: off never reads the tracks, so the
true cameras with and without them train alike."""
RECOVERY_STARTS = ("perturbed", "phone", "phone-iid")
"""Starts that refinement must correct (the report gives the fraction of the start error removed); the others
(accurate, sfm) it must not make worse."""
VARIANTS = ("off", "s2camp-so3xr3", "s2camp-camp", "s2camp", "tracks", "s2camp-photometric", "s2camp-camp-prior",
            "s2camp-identity-prior")  # fmt: skip
"""What each evidence adds: refinement off, the two baselines, the default, the tracks alone, the images alone
(S2CamP without the prior), and the prior with CamP's P and with P = I, every row with a prior on the same tracks."""
METHODS = {
    "off": "s2camp", "s2camp-so3xr3": "s2camp-so3xr3", "s2camp-camp": "s2camp-camp", "s2camp": "s2camp",
    "tracks": "s2camp", "s2camp-photometric": "s2camp", "s2camp-camp-prior": "s2camp-camp",
    "s2camp-identity-prior": "s2camp",
}  # fmt: skip
_OPTIMIZER = "--pipeline.model.camera-optimizer"
_ROTATION, _PRIOR = f"{_OPTIMIZER}.fix-common-rotation", f"{_OPTIMIZER}.track-prior"
VARIANT_ARGUMENTS = {
    "off": [f"{_OPTIMIZER}.mode", "off"],
    "tracks": [f"{_OPTIMIZER}.photometric", "False", _ROTATION, "True", _PRIOR, "True"],
    "s2camp-photometric": [_ROTATION, "True", _PRIOR, "False"],
    "s2camp-camp-prior": [_ROTATION, "True", _PRIOR, "True"],
    "s2camp-identity-prior": [f"{_OPTIMIZER}.precondition", "False", _ROTATION, "True", _PRIOR, "True"],
}  # fmt: skip
"""Method options per variant, each stating every candidate option so that a variant keeps its meaning when a default
changes ("s2camp": the method's defaults). Committed rows under other names are reported apart (docs/RESULTS.md,
"Names that no longer run")."""
QUICK = {"scenes": ("small-narrow-far",), "starts": ("accurate", "perturbed"), "variants": ("off", "s2camp"),
         "iterations": 20, "seeds": 1}  # fmt: skip
"""``--quick``: a CI-sized run (under 5 minutes on 2 CPU cores), 10 test-time alignment steps of 64 rays."""


@dataclass
class RobustnessConfig:
    """The real-training regime from accurate, SfM, perturbed and phone cameras (module docstring)."""

    preset: Literal["regime"] = "regime"
    """The grid, and the report's name: the real-training regime (the defaults below)."""
    scenes: tuple[str, ...] = ("regime-wide",)
    starts: tuple[str, ...] = STARTS
    variants: tuple[str, ...] = VARIANTS
    seeds: int = 3
    """Runs per scene, start and variant, ``--machine.seed`` first_seed .. first_seed + seeds - 1."""
    first_seed: int = 0
    """The first seed: a grid that spans sessions adds seeds later without re-running the first ones."""
    iterations: int = 3000
    """``--max-num-iterations`` of every run."""
    rays_per_batch: int = 512
    """Training rays per step."""
    workers: int = 2
    """Runs training (then evaluating) side by side, one CPU thread each."""
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    """Test-time alignment of the held-out views (every run alike)."""
    quick: bool = False
    """Small run for CI (``QUICK``)."""
    work_dir: Path | None = None
    """Where scenes, runs and ``rows.jsonl`` go (``grid.resume``; a temporary folder by default, removed after)."""
    rows_from: Path | None = None
    """Train nothing: report the rows of a ``rows.jsonl`` written by an earlier (possibly interrupted) run."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    write: bool = True
    json: bool = False

    def effective(self) -> RobustnessConfig:
        if not self.quick:
            return self
        return replace(self, alignment=replace(self.alignment, steps=10, rays=64), **QUICK)

    def validate(self) -> None:
        check_choice("preset", self.preset, ("regime",))
        check_positive_int("rays_per_batch", self.rays_per_batch)
        grid.validate_grid(self, tuple(SCENES), STARTS, VARIANTS)

    def command(self) -> str:
        """The ``s2camp-bench`` command line that regenerates this report."""
        if self.quick:
            return "s2camp-bench robustness --quick"
        names = ("scenes", "starts", "variants", "seeds", "first_seed", "iterations", "rays_per_batch", "workers")
        options = changed_options(self, RobustnessConfig(), names)
        return " ".join(["s2camp-bench robustness --preset regime", *options])


def train_command(
    spec: grid.RunSpec, scene_dir: Path, runs: Path, config: RobustnessConfig, truth: Path | None = None
) -> list[str]:
    """``ns-train`` of one run: the method's defaults plus the CPU-sized run (module docstring) and the start's data
    parser (``grid.start_arguments``). ``truth``: the generated scene, the reference cameras of an sfm start
    (``scene_dir`` is then SfM's)."""
    return [
        *ns_train_arguments(
            METHODS[spec.variant], scene_dir, runs, spec.experiment, spec.timestamp, config.iterations,
            config.iterations, config.rays_per_batch,
        ),
        "--machine.device-type", "cpu",
        "--machine.seed", str(spec.seed),
        "--vis", "tensorboard",
        "--pipeline.model.camera-error-every", "0",
        *VARIANT_ARGUMENTS.get(spec.variant, []),
        *grid.start_arguments(spec, SCENES[spec.scene], truth),
    ]  # fmt: skip


def run_folder(spec: grid.RunSpec, runs: Path) -> Path:
    return runs / spec.experiment / METHODS[spec.variant] / spec.timestamp


def evaluate_run(run: Path, alignment: AlignmentConfig) -> dict:
    """``evaluation.evaluate_pipeline`` of a finished run's last checkpoint (``eval_seconds`` includes the loading)."""
    from .evaluation import evaluate_pipeline, load_pipeline

    began = time.perf_counter()
    result = evaluate_pipeline(load_pipeline(run), alignment)
    result["eval_seconds"] = time.perf_counter() - began
    return result


def _run_one(spec: grid.RunSpec, scene_dir: Path, root: Path, config: RobustnessConfig, pool) -> dict:
    """Train, evaluate and record one run; its row."""
    truth = None
    if spec.start == "sfm":
        truth, scene_dir = scene_dir, grid.sfm_scene(spec.scene, scene_dir, root)
    log_path = root / "logs" / f"{spec.experiment}-{spec.timestamp}.log"
    train_seconds = grid.train_logged(train_command(spec, scene_dir, root / "runs", config, truth), log_path, spec)
    folder = run_folder(spec, root / "runs")
    result = pool.submit(evaluate_run, folder, config.alignment).result()
    row = grid.evaluated_row(spec, result, config.iterations, train_seconds, folder)
    row["passes"] = config.iterations * config.rays_per_batch / SCENES[spec.scene].training_pixels
    grid.record_row(row, folder, root)
    return row


def run(config: RobustnessConfig) -> list[dict]:
    config = config.effective()
    config.validate()
    if config.rows_from is not None:
        return grid.read_rows(config.rows_from)
    return in_work_folder(config.work_dir, "robust-", lambda root: _run(config, root))


def _run(config: RobustnessConfig, root: Path) -> list[dict]:
    (root / "logs").mkdir(parents=True, exist_ok=True)
    scene_dirs = {
        name: generated_scene(replace(SCENES[name].scene, output_dir=root / "scenes" / name)) for name in config.scenes
    }
    done, specs = grid.resume(grid.run_specs(config), root)
    log(
        f"robustness: {len(specs)} runs of {config.iterations} iterations, {config.workers} at a time (work: {root})"
        + (f"; {len(done)} already in {grid.ROWS_FILE}" if done else "")
    )
    run_one = lambda spec, pool: _run_one(spec, scene_dirs[spec.scene], root, config, pool)  # noqa: E731
    return done + grid.run_side_by_side(specs, run_one, config.workers)


def report(rows: list[dict], config: RobustnessConfig) -> Path:
    """The report (``robustness_report.write``)."""
    from .robustness_report import write

    return write(rows, config.effective())
