"""``s2camp-bench robustness --preset regime``: where does each evidence put the cameras in the real-training regime,
from accurate, SfM, perturbed and phone cameras?

Protocol (every run alike): one generated scene of 56 images (49 trained at 160x120, SfM on 320x240, 70 degrees),
3000 steps x 512 rays, so that each training pixel is seen 1.63 times, as in a nerfacto run (about once); starts
{accurate, perturbed, sfm, phone} (``grid``) x ``VARIANTS`` x seeds. Every run is one ``ns-train`` FROM SCRATCH with
the method's default options, except what a CPU run needs: a small nerfacto field (``train_commands.SMALL_MODEL``),
``--machine.device-type cpu``, the same ``--max-num-iterations`` for every run, no evaluation during training, no
camera-error logging during training (errors are computed afterwards, identically for every variant), tensorboard
instead of the viewer. No camera learning rate, schedule or sampling option is given: the camera schedule is the
method's default, whatever it is in this checkout. ``--machine.seed`` is the seed.

Metrics of the final checkpoint (``evaluation.evaluate_pipeline``): rotation (degrees), position (normalized scene
units: the data parser scales the camera centres into [-1, 1]^3) and focal (px, training resolution) errors, means
over the training cameras after a similarity alignment to the true cameras; the reprojection drift (``drift``): RMS
pixel displacement of the scene's 3D points between the true and the similarity-aligned refined cameras; PSNR / SSIM
of the held-out views (every 8th image) after test-time alignment (CamP's protocol). The same errors of the start
cameras are recorded. Up to ``workers`` runs train side by side, one thread each; each run is evaluated right after
it trains and its checkpoints are deleted. The report: ``robustness_report``.
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

from .common import DEFAULT_OUTPUT_DIR, changed_options, generated_scene, in_work_folder, log
from .grid import (
    ROWS_FILE,
    GridScene,
    RunSpec,
    focal_for_fov,
    read_rows,
    record_row,
    resume,
    run_side_by_side,
    run_specs,
    sfm_scene,
    start_arguments,
    train_logged,
)


def _scene(num_cameras: int, width: int, height: int, fov: float, ring_radius: float, seed: int) -> MakeSceneConfig:
    # Pinhole cameras (no distortion): the CamP perturbation zeroes distortion, so a distorted scene would give the
    # perturbed start an error that no variant refining pose and focal can remove, and the accurate start none.
    return MakeSceneConfig(
        num_cameras=num_cameras, width=width, height=height, focal=focal_for_fov(width, fov),
        ring_radius=ring_radius, k1=0.0, k2=0.0, seed=seed,
    )  # fmt: skip


REGIME_VARIES = (
    "the real-training regime: 49 training images trained at 160x120 (SfM on 320x240), 70 deg; 3000 steps x 512 rays "
    "see each training pixel 1.6 times (a nerfacto run about once)"
)
SCENES: dict[str, GridScene] = {
    "regime-wide": GridScene(_scene(56, 320, 240, 70.0, 4.0, seed=3), 70.0, 3, REGIME_VARIES, downscale=2),
    "small-narrow-far": GridScene(
        _scene(16, 48, 36, 40.0, 7.0, seed=0), 40.0, 0,
        "48x36 px, 40 deg, 16 images, cameras 7 units from the centre: distant objects, shallow depth range",
    ),
}  # fmt: skip
"""The runnable scenes: the regime's, and a tiny one for ``--quick``. The background sphere has radius 40
(``scene.procedural``); the foreground objects lie within 1.8 of the centre."""
RETIRED_SCENES: dict[str, GridScene] = {
    "regime-wide-full": GridScene(
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
VARIANTS = (
    "off", "s2camp-so3xr3", "s2camp-camp", "s2camp", "tracks", "s2camp-photometric", "s2camp-camp-prior",
    "s2camp-identity-prior",
)  # fmt: skip
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
"""Method options per variant beyond the CPU-sized run, each stating every candidate option so that a variant keeps
its meaning when a default changes. "s2camp" is the method's defaults; "off" disables camera refinement; "tracks"
every camera at its track prior's anchor, the images move none (``photometric`` False); "s2camp-photometric" the
defaults without the prior; "s2camp-camp-prior" the s2camp-camp method plus the defaults' prior and common-rotation
removal; "s2camp-identity-prior" the defaults with ``precondition`` False. Committed rows under other names were
recorded with settings that no longer run: the report lists them apart (docs/RESULTS.md, "Names that no longer
run")."""
METRICS = ("rot_err", "pos_err", "focal_err", "drift_px", "psnr", "ssim", "psnr_unaligned")
ERRORS = ("rot_err", "pos_err", "focal_err", "drift_px")
QUICK = {
    "scenes": ("small-narrow-far",), "starts": ("accurate", "perturbed"), "variants": ("off", "s2camp"),
    "iterations": 20, "seeds": 1,
}  # fmt: skip
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
    """Where scenes and runs go (a temporary /tmp/robust-* folder by default, removed afterwards). Each finished
    run's row is appended to ``rows.jsonl`` there as soon as it is evaluated; a run whose row is already there is not
    run again (its row is reused), so a grid continues in its folder across sessions."""
    rows_from: Path | None = None
    """Train nothing: report the rows of a ``rows.jsonl`` written by an earlier (possibly interrupted) run."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plot (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False
    trace_every: int = 0
    """Keep a checkpoint every this many steps and record the cameras' path (``regime_trace``). 0: none."""

    def effective(self) -> RobustnessConfig:
        if not self.quick:
            return self
        return replace(self, alignment=replace(self.alignment, steps=10, rays=64), **QUICK)

    def validate(self) -> None:
        check_choice("preset", self.preset, ("regime",))
        for name, allowed in (("scenes", tuple(SCENES)), ("starts", STARTS), ("variants", VARIANTS)):
            values = getattr(self, name)
            if not values:
                raise ValueError(f"{name} must name at least one of {', '.join(allowed)}, got none")
            for value in values:
                check_choice(name, value, allowed)
        for name in ("seeds", "iterations", "rays_per_batch", "workers"):
            check_positive_int(name, getattr(self, name))
        if self.first_seed < 0:
            raise ValueError(f"first_seed must be >= 0, got {self.first_seed}")
        if self.trace_every < 0:
            raise ValueError(f"trace_every must be >= 0 steps (0: no trace), got {self.trace_every}")
        self.alignment.validate()

    def command(self) -> str:
        """The ``s2camp-bench`` command line that regenerates this report."""
        if self.quick:
            return "s2camp-bench robustness --quick"
        names = ("scenes", "starts", "variants", "seeds", "first_seed", "iterations", "rays_per_batch", "workers")
        options = changed_options(self, RobustnessConfig(), (*names, "trace_every"))
        return " ".join(["s2camp-bench robustness --preset regime", *options])


def train_command(
    spec: RunSpec, scene_dir: Path, runs: Path, config: RobustnessConfig, truth: Path | None = None
) -> list[str]:
    """``ns-train`` of one run: the method's defaults plus the CPU-sized run (module docstring) and the start's data
    parser (``grid.start_arguments``). ``truth``: the generated scene, the reference cameras of an sfm start
    (``scene_dir`` is then SfM's)."""
    save_every = config.trace_every or config.iterations
    return [
        *ns_train_arguments(
            METHODS[spec.variant], scene_dir, runs, spec.experiment, spec.timestamp, config.iterations, save_every,
            config.rays_per_batch,
        ),
        "--machine.device-type", "cpu",
        "--machine.seed", str(spec.seed),
        "--vis", "tensorboard",
        "--pipeline.model.camera-error-every", "0",
        *(["--save-only-latest-checkpoint", "False"] if config.trace_every else []),
        *VARIANT_ARGUMENTS.get(spec.variant, []),
        *start_arguments(spec, SCENES[spec.scene], truth),
    ]  # fmt: skip


def run_folder(spec: RunSpec, runs: Path) -> Path:
    return runs / spec.experiment / METHODS[spec.variant] / spec.timestamp


def evaluate_run(run: Path, alignment: AlignmentConfig, trace: bool) -> dict:
    """``evaluation.evaluate_pipeline`` of a finished run's last checkpoint (``eval_seconds`` includes the loading),
    and with ``trace`` the cameras' path through its checkpoints (``regime_trace.trace_run``)."""
    from .evaluation import evaluate_pipeline, load_pipeline

    began = time.perf_counter()
    result = evaluate_pipeline(load_pipeline(run), alignment)
    result["eval_seconds"] = time.perf_counter() - began
    if trace:
        from .regime_trace import trace_run

        result["trace"] = trace_run(run)
    return result


def _run_one(spec: RunSpec, scene_dir: Path, root: Path, config: RobustnessConfig, pool) -> dict:
    """Train, evaluate and record one run; its row."""
    from .evaluation import seconds_per_iteration

    truth = None
    if spec.start == "sfm":
        truth, scene_dir = scene_dir, sfm_scene(spec.scene, scene_dir, root)
    log_path = root / "logs" / f"{spec.experiment}-{spec.timestamp}.log"
    train_seconds = train_logged(train_command(spec, scene_dir, root / "runs", config, truth), log_path, spec)
    folder = run_folder(spec, root / "runs")
    result = pool.submit(evaluate_run, folder, config.alignment, bool(config.trace_every)).result()
    row = {"scene": spec.scene, "start": spec.start, "variant": spec.variant, "seed": spec.seed}
    row["passes"] = config.iterations * config.rays_per_batch / SCENES[spec.scene].training_pixels
    row |= {key: result[key] for key in (*METRICS, "drift_behind")}
    row |= {f"start_{key}": result[f"start_{key}"] for key in (*ERRORS, "drift_behind")}
    row |= {"iterations": config.iterations, "eval_views": result["eval_views"], "train_seconds": train_seconds}
    row |= {"eval_seconds": result["eval_seconds"], "sec_per_iter": seconds_per_iteration(folder)}
    if result.get("trace"):
        row["trace"] = result["trace"]
    record_row(row, folder, root)
    log(
        f"robustness {spec.scene} {spec.start:9s} {spec.variant:13s} seed {spec.seed}: rot {row['rot_err']:.3f} deg "
        f"pos {row['pos_err']:.2e} focal {row['focal_err']:.3f} px drift {row['drift_px']:.3f} px "
        f"psnr {row['psnr']:.2f} ssim {row['ssim']:.3f} (start rot {row['start_rot_err']:.3f} drift "
        f"{row['start_drift_px']:.3f}; {train_seconds:.0f} s + {row['eval_seconds']:.0f} s)"
    )
    return row


def run(config: RobustnessConfig) -> list[dict]:
    config = config.effective()
    config.validate()
    if config.rows_from is not None:
        return read_rows(config.rows_from)
    return in_work_folder(config.work_dir, "robust-", lambda root: _run(config, root))


def _run(config: RobustnessConfig, root: Path) -> list[dict]:
    (root / "logs").mkdir(parents=True, exist_ok=True)
    scene_dirs = {
        name: generated_scene(replace(SCENES[name].scene, output_dir=root / "scenes" / name)) for name in config.scenes
    }
    done, specs = resume(run_specs(config), root)
    log(
        f"robustness: {len(specs)} runs of {config.iterations} iterations, {config.workers} at a time (work: {root})"
        + (f"; {len(done)} already in {ROWS_FILE}" if done else "")
    )
    run_one = lambda spec, pool: _run_one(spec, scene_dirs[spec.scene], root, config, pool)  # noqa: E731
    return done + run_side_by_side(specs, run_one, config.workers)


def report(rows: list[dict], config: RobustnessConfig) -> Path:
    """The report (``robustness_report.write``)."""
    from .robustness_report import write

    return write(rows, config.effective())
