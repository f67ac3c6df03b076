"""``s2camp-bench robustness``: does camera refinement with the methods' default options help, or hurt, from
accurate and from perturbed cameras, across scenes that differ in resolution, field of view, image count and depth?

Protocol (every run alike): scenes x start {accurate, perturbed} x variant {off, s2camp-so3xr3, s2camp-camp,
s2camp} x seeds. Every run is one ``ns-train`` FROM SCRATCH with the method's default options, except what a CPU
run needs: a small nerfacto field (``train_commands.SMALL_MODEL``), ``--machine.device-type cpu`` (``--device cuda``:
the method's own field on a CUDA device instead), the same ``--max-num-iterations`` for every run, no evaluation
during training, no camera-error logging during training (errors are computed afterwards, identically for every
variant), tensorboard instead of the viewer. No camera learning rate, schedule or sampling option is given: the
camera schedule is the method's default, whatever it is in this checkout. ``--machine.seed`` is the seed.

- start "accurate": the generated scene's true cameras; "perturbed": the data parser's CamP perturbation
  (``s2camp-data --perturbation.enabled True``, CamP's sigmas, one fixed perturbation seed per scene);
- variant "off": ``ns-train s2camp --pipeline.model.camera-optimizer.mode off`` (no camera refinement); the others
  are the ``ns-train`` methods of those names.

Metrics of the final checkpoint: rotation (degrees), position (normalized scene units: the data parser scales the
camera centres into [-1, 1]^3) and focal (px, training resolution) errors, means over the training cameras after a
similarity alignment to the true cameras (``core.alignment``); the reprojection drift (``core.drift``): RMS pixel
displacement of the scene's 3D points (the generated COLMAP model's points3D, in the data parser's frame) between
the true and the similarity-aligned refined cameras; PSNR / SSIM of the held-out views (every 8th image) after
test-time alignment (``s2camp_ns.scripts.test_time_alignment``, CamP's protocol). The same errors of the start
cameras (before refinement) are recorded. Up to ``workers`` runs train side by side, one thread each; each run is
evaluated right after it trains and its checkpoints are deleted.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import shutil
import statistics
import subprocess
import threading
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.report import markdown_table
from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.train_commands import (
    DATAPARSER_SUBCOMMAND,
    ns_train_arguments,
)
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
from .data_parser import ns_train_environment


def focal_for_fov(width: int, fov_degrees: float) -> float:
    """Pinhole focal length (px) of a horizontal field of view ``fov_degrees`` over ``width`` pixels."""
    return 0.5 * width / math.tan(math.radians(fov_degrees) / 2.0)


@dataclass(frozen=True)
class RobustnessScene:
    """A generated scene of the benchmark and the seed of its CamP perturbation."""

    scene: MakeSceneConfig
    fov_degrees: float
    perturbation_seed: int
    varies: str
    """What the scene stands for among the others (the report's scene table)."""
    downscale: int = 1
    """Train on ``images_{downscale}`` (SfM runs on the full-size images, as a user's COLMAP does)."""

    @property
    def training_pixels(self) -> int:
        """Pixels of the training images: every image but each ``EVAL_INTERVAL``-th (the data parser's split)."""
        s = self.scene
        held_out = -(-s.num_cameras // EVAL_INTERVAL)
        return (s.num_cameras - held_out) * (s.width // self.downscale) * (s.height // self.downscale)


EVAL_INTERVAL = 8
"""The data parser's default held-out interval (every 8th image, the mip-NeRF 360 protocol)."""


def _scene(num_cameras: int, width: int, height: int, fov: float, ring_radius: float, seed: int) -> MakeSceneConfig:
    # Pinhole cameras (no distortion): the CamP perturbation zeroes distortion, so a distorted scene would give the
    # perturbed start an error that no variant refining pose and focal can remove, and the accurate start none.
    return MakeSceneConfig(
        num_cameras=num_cameras, width=width, height=height, focal=focal_for_fov(width, fov),
        ring_radius=ring_radius, k1=0.0, k2=0.0, seed=seed,
    )  # fmt: skip


SCENES: dict[str, RobustnessScene] = {
    "small-narrow-far": RobustnessScene(
        _scene(16, 48, 36, 40.0, 7.0, seed=0),
        40.0,
        0,
        "48x36 px, 40 deg, 16 images, cameras 7 units from the centre: distant objects, shallow depth range",
    ),
    "large-wide": RobustnessScene(
        _scene(8, 192, 144, 100.0, 4.0, seed=1),
        100.0,
        1,
        "192x144 px (4x the width of small-narrow-far), 100 deg, 8 images, cameras 4 units out",
    ),
    "near-deep": RobustnessScene(
        _scene(12, 96, 72, 70.0, 2.6, seed=2),
        70.0,
        2,
        "96x72 px, 70 deg, 12 images, cameras 2.6 units out: objects 1 unit away, background 40: deepest range",
    ),
    "regime-wide": RobustnessScene(
        _scene(56, 320, 240, 70.0, 4.0, seed=3),
        70.0,
        3,
        "the real-training regime: 49 training images trained at 160x120 (SfM on 320x240), 70 deg; 3000 steps x "
        "512 rays see each training pixel 1.6 times (a nerfacto run about once)",
        downscale=2,
    ),
    "regime-wide-full": RobustnessScene(
        _scene(56, 320, 240, 70.0, 4.0, seed=3),
        70.0,
        3,
        "regime-wide trained at its full 320x240 (4x the pixels per image); 3000 steps x 512 rays see each training "
        "pixel 0.41 times: whether four times the pixels let the images gain on the keypoints",
    ),
}
"""The background sphere has radius 40 (``scene.procedural``); the foreground objects lie within 1.8 of the
centre, so the ring radius sets the depth range each camera sees. The cameras sit on a full ring, so the number
of images times the field of view is how often the background is covered: the narrow scene gets the most images
(with 8 images of 40 degrees a held-out view sees background no training view saw, and its PSNR stopped improving
early in training while the training PSNR kept rising), the wide one the fewest. The scenes and their start errors:
docs/benchmarks/robustness.md, "Scenes"."""
STARTS = ("accurate", "perturbed", "sfm", "phone", "accurate-untracked")
"""accurate: the true cameras; perturbed: CamP's perturbation; sfm: pycolmap SfM on the full-size images with an
EXIF-like focal prior (``benchmarks/s2camp_bench/sfm.py``); phone: ``PHONE_PROFILE`` (module docstring); accurate-untracked: the
true cameras as a scene without SfM tracks (a hand-made or exported transforms.json). Evidence that does not know the
truth: the generated scene's own tracks are exact projections through the true cameras, so every start but sfm
trains with tracks made from its images with its start cameras (``--image-tracks always``,
``s2camp_ns/tracks/image_tracks.py``), and the sfm start with SfM's tracks, made from the images too. accurate
and accurate-untracked therefore train alike now; the second is kept for its earlier rows."""
REGIME_STARTS = STARTS[:4]
OFF_REFERENCE_START = {"accurate-untracked": "accurate"}
"""Starts whose 'PSNR vs off' compares with refinement off from another start: off never reads the tracks, so the
true cameras with and without them train alike."""
DEFAULT_STARTS = ("accurate", "perturbed")
RECOVERY_STARTS = ("perturbed", "phone", "phone-iid")
"""Starts that refinement must correct (the report gives the fraction of the start error removed); the others
(accurate, sfm) it must not make worse. phone-iid names committed rows of a start that no longer runs (docs/RESULTS.md,
"Names that no longer run")."""
VARIANTS = (
    "off", "s2camp-so3xr3", "s2camp-camp", "s2camp", "tracks", "s2camp-photometric", "s2camp-camp-prior",
    "s2camp-identity-prior",
)  # fmt: skip
"""The ``--preset regime`` variants: what each evidence adds. Beside refinement off, the two baselines and the
default, the tracks alone, the images alone (S2CamP without the prior), and the prior with CamP's P and with P = I,
every row that uses a prior with the same tracks."""
FRONTIER_VARIANTS = ("s2camp-pose-exp0", "s2camp-pose-exp0.5")
"""The default with a looser hold on each pose (``pose-prior-exponent`` 0 and 0.5: radius r_i and r_i / (2 O_i)^0.25
instead of the standard error r_i / sqrt(2 O_i)): where cameras and renders go as the pose scale opens up."""
RUNNABLE_VARIANTS = VARIANTS + FRONTIER_VARIANTS
"""Every variant this code runs; committed rows under other names are reported apart."""
METHODS = {
    "off": "s2camp", "s2camp-so3xr3": "s2camp-so3xr3", "s2camp-camp": "s2camp-camp", "s2camp": "s2camp",
    "tracks": "s2camp", "s2camp-photometric": "s2camp", "s2camp-camp-prior": "s2camp-camp",
    "s2camp-identity-prior": "s2camp", **dict.fromkeys(FRONTIER_VARIANTS, "s2camp"),
}  # fmt: skip
_ROTATION = "--pipeline.model.camera-optimizer.fix-common-rotation"
_PRIOR = "--pipeline.model.camera-optimizer.track-prior"
_OPTIMIZER = "--pipeline.model.camera-optimizer"
VARIANT_ARGUMENTS = {
    "off": ["--pipeline.model.camera-optimizer.mode", "off"],
    "tracks": [f"{_OPTIMIZER}.photometric", "False", _ROTATION, "True", _PRIOR, "True"],
    "s2camp-photometric": [_ROTATION, "True", _PRIOR, "False"],
    "s2camp-camp-prior": [_ROTATION, "True", _PRIOR, "True"],
    "s2camp-identity-prior": [f"{_OPTIMIZER}.precondition", "False", _ROTATION, "True", _PRIOR, "True"],
    "s2camp-pose-exp0": [f"{_OPTIMIZER}.pose-prior-exponent", "0"],
    "s2camp-pose-exp0.5": [f"{_OPTIMIZER}.pose-prior-exponent", "0.5"],
}  # fmt: skip
"""Method options per variant beyond the CPU-sized run, each stating every candidate option so that a variant keeps
its meaning when a default changes. "s2camp" is the method's defaults (the common rotation removed and the track
prior on, ``S2CAMP_CAMERA_OPTIMIZER``); "off" disables camera refinement; "tracks" the tracks alone (every camera at
its track prior's anchor, the images move none: ``photometric`` False), what bundle adjustment gives without
refinement; "s2camp-photometric" the images alone (the defaults without the prior); "s2camp-camp-prior" the prior
with CamP's P (the s2camp-camp method plus the defaults' prior and common-rotation removal); "s2camp-identity-prior"
the prior with P = I (the defaults, ``precondition`` False); the looser poses of ``FRONTIER_VARIANTS``. Committed rows
under other variant names were recorded with settings that no longer run: the report lists them apart, and
docs/RESULTS.md ("Names that no longer run") says what each ran."""
PHONE_PROFILE = {
    "perturbation.sigma_position": 0.0, "perturbation.sigma_look_at": 0.0, "perturbation.sigma_dolly_z": 0.0,
    "perturbation.sigma_focal_length": 0.0, "drift.enabled": True, "drift.position_drift": 0.01,
    "drift.yaw_drift_deg": 1.5, "drift.tilt_deg": 0.3, "drift.focal_error": 0.015,
}  # fmt: skip
"""The phone-pose start: visual-inertial odometry poses (ARKit / ARCore, as Polycam or Record3D export them), the
benchmarks' data parser's VIO drift (``s2camp-bench-data``, ``benchmarks/s2camp_bench/phone_drift.py``, where each size's
source or assumption is stated) with CamP's own steps off. Along the capture (image order, the ring's order): the
centres a random walk from the first camera whose RMS grows to 1% of the distance travelled at the last (about 0.05 to
0.06 normalized units on these rings, which travel 4.6 to 6 units over the training cameras), the yaw (about +z, the
data parser's up) a random walk to 1.5 degrees RMS, roll and pitch within 0.3 degrees of gravity, and one focal length
for every image 1.5% off (a log-normal sigma; a single phone camera's factory calibration), no per-image focal error.
Each run seed draws its own drift: seed s of a scene with perturbation seed p uses perturbation seed p + s, so the seeds
of a grid are different draws (the variants of one seed share it), unlike the perturbed start's one draw per scene.
These exports carry no SfM tracks, so this start trains without the scene's (``--image-tracks always``: tracks made from
the images)."""
SFM_FOCAL_PRIOR = 1.05
"""The sfm start's focal prior (the EXIF focal of a real capture; ``benchmarks/s2camp_bench/sfm.py``)."""
METRICS = ("rot_err", "pos_err", "focal_err", "drift_px", "psnr", "ssim", "psnr_unaligned")
ERRORS = ("rot_err", "pos_err", "focal_err", "drift_px")
QUICK = {"iterations": 20, "seeds": 1, "variants": ("off", "s2camp")}
"""``--quick``: the first scene only, both starts, these settings, 10 test-time alignment steps of 64 rays."""
DEVICES = ("cpu", "cuda")
"""``--device``: where every run trains (``RobustnessConfig.device``)."""
REGIME = {"scenes": ("regime-wide",), "starts": REGIME_STARTS, "iterations": 3000, "variants": VARIANTS}
"""``--preset regime``: the regime real runs train in (the scene's ``varies``); passes per pixel in every row."""


@dataclass
class RobustnessConfig:
    """Camera refinement with default options from accurate and perturbed cameras (module docstring)."""

    scenes: tuple[str, ...] = ("small-narrow-far", "large-wide", "near-deep")
    """Scenes (``SCENES``); ``--preset regime`` picks the real-training regime."""
    starts: tuple[str, ...] = DEFAULT_STARTS
    variants: tuple[str, ...] = ("off", "s2camp-so3xr3", "s2camp-camp", "s2camp")
    seeds: int = 3
    """Runs per scene, start and variant, ``--machine.seed`` first_seed .. first_seed + seeds - 1."""
    first_seed: int = 0
    """The first seed: a grid that spans sessions adds seeds 1 and 2 later without re-running seed 0."""
    iterations: int = 200
    """``--max-num-iterations`` of every run."""
    rays_per_batch: int = 512
    """Training rays per step."""
    workers: int = 2
    """Runs training (then evaluating) side by side, one CPU thread each."""
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    """Test-time alignment of the held-out views (every run alike)."""
    quick: bool = False
    """Small run for CI (``QUICK``, under 5 minutes on 2 CPU cores)."""
    work_dir: Path | None = None
    """Where scenes and runs go (a temporary /tmp/robust-* folder by default, removed afterwards). Each finished
    run's row is appended to ``rows.jsonl`` there as soon as it is evaluated; a run whose row is already there is not
    run again (its row is reused), so a grid continues in its folder across sessions."""
    rows_from: Path | None = None
    """Train nothing: report the rows of a ``rows.jsonl`` written by an earlier (possibly interrupted) run."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False
    trace_every: int = 0
    """Keep a checkpoint every this many steps and record the cameras' path (``trace_run``): the mechanism of
    drift. 0: none."""
    preset: str = ""
    """"regime": the real-training regime (``REGIME``): scene regime-wide, all four starts, 3000 steps."""
    device: str = "cpu"
    """"cpu": the CPU-sized run (the small nerfacto field ``SMALL_MODEL``, one CPU thread per run); "cuda": the
    method's own nerfacto field on the CUDA device (``--machine.device-type cuda``), as ``ns-train s2camp`` trains on
    a GPU. Rows record the device; rows of the two devices are different rows of the report."""

    def effective(self) -> RobustnessConfig:
        if self.preset == "regime":  # the preset's values where the command line left the defaults
            default = RobustnessConfig()
            chosen = {key: value for key, value in REGIME.items() if getattr(self, key) == getattr(default, key)}
            return replace(self, **chosen)
        if not self.quick:
            return self
        alignment = replace(self.alignment, steps=10, rays=64)
        return replace(self, scenes=self.scenes[:1], alignment=alignment, **QUICK)

    def validate(self) -> None:
        for name, allowed in (("scenes", tuple(SCENES)), ("starts", STARTS), ("variants", RUNNABLE_VARIANTS)):
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
        check_choice("preset", self.preset, ("", "regime"))
        check_choice("device", self.device, DEVICES)
        self.alignment.validate()

    def command(self) -> str:
        """The ``s2camp-bench`` command line that regenerates this report."""
        parts = ["s2camp-bench robustness"]
        if self.quick:
            return " ".join([*parts, "--quick"])
        default = RobustnessConfig()
        if self.preset:
            parts.append(f"--preset {self.preset}")
            default = RobustnessConfig(preset=self.preset).effective()
        names = ("scenes", "starts", "variants", "seeds", "first_seed", "iterations", "rays_per_batch", "workers")
        return " ".join(parts + changed_options(self, default, (*names, "trace_every", "device")))


@dataclass(frozen=True)
class RunSpec:
    """One training run of the protocol."""

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


def run_specs(config: RobustnessConfig) -> list[RunSpec]:
    """Every run, seeds outermost: a run cut short still leaves whole seeds of every scene, start and variant."""
    return [
        RunSpec(scene, start, variant, seed)
        for seed in range(config.first_seed, config.first_seed + config.seeds)
        for scene in config.scenes
        for start in config.starts
        for variant in config.variants
    ]


def train_command(
    spec: RunSpec, scene_dir: Path, runs: Path, config: RobustnessConfig, truth: Path | None = None
) -> list[str]:
    """``ns-train`` of one run: the method's defaults plus the CPU-sized run (module docstring). ``truth``: the
    generated scene, the reference cameras of an sfm start (``scene_dir`` is then SfM's)."""
    save_every = config.trace_every or config.iterations
    command = [
        *ns_train_arguments(
            METHODS[spec.variant], scene_dir, runs, spec.experiment, spec.timestamp, config.iterations,
            save_every, config.rays_per_batch, small_model=config.device == "cpu",  # CUDA: the method's own field
        ),
        "--machine.device-type", config.device,
        "--machine.seed", str(spec.seed),
        "--vis", "tensorboard",
        "--pipeline.model.camera-error-every", "0",
        *(["--save-only-latest-checkpoint", "False"] if config.trace_every else []),
        *VARIANT_ARGUMENTS.get(spec.variant, []),
    ]  # fmt: skip
    preset = SCENES[spec.scene]
    subcommand = BENCH_DATAPARSER if spec.start in ("phone", "sfm") else DATAPARSER_SUBCOMMAND
    dataparser = [subcommand, "--downscale-factor", str(preset.downscale)]
    if spec.start == "perturbed":
        dataparser += ["--perturbation.enabled", "True", "--perturbation.seed", str(preset.perturbation_seed)]
    if spec.start == "phone":  # one VIO drift draw per run seed (PHONE_PROFILE)
        seed = preset.perturbation_seed + spec.seed
        dataparser += ["--perturbation.enabled", "True", "--perturbation.seed", str(seed)]
        for key, value in PHONE_PROFILE.items():
            dataparser += [f"--{key.replace('_', '-')}", str(value)]
    if spec.start != "sfm":  # evidence that does not know the truth: the generated tracks are exact projections
        dataparser += ["--image-tracks", "always"]
    if spec.start == "sfm":
        assert truth is not None, "an sfm start measures against the generated scene's cameras"
        dataparser += ["--reference-model", str(truth / "sparse" / "0")]
    return command + dataparser


def run_folder(spec: RunSpec, runs: Path) -> Path:
    return runs / spec.experiment / METHODS[spec.variant] / spec.timestamp


# ----------------------------------------------------------------------------------------------------- evaluation
def evaluate_run(run: Path, alignment: AlignmentConfig) -> dict:
    """Start and final camera metrics, held-out PSNR / SSIM after test-time alignment, of a finished run
    (``s2camp_bench.evaluation.evaluate_pipeline`` of its last checkpoint); ``eval_seconds`` includes the
    loading."""
    from s2camp_bench.evaluation import evaluate_pipeline

    from .recovery_photometric import _load_pipeline

    began = time.perf_counter()
    result = evaluate_pipeline(_load_pipeline(run), alignment)
    result["eval_seconds"] = time.perf_counter() - began
    return result


def _single_thread() -> None:
    import torch

    torch.set_num_threads(1)


# ------------------------------------------------------------------------------------------------------------ run
def _train(
    spec: RunSpec, scene_dir: Path, runs: Path, logs: Path, config: RobustnessConfig, truth: Path | None
) -> float:
    """Train one run; return its wall-clock seconds (start-up included)."""
    return train_logged(
        train_command(spec, scene_dir, runs, config, truth), logs / f"{spec.experiment}-{spec.timestamp}.log", spec
    )


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


def read_rows(path: Path) -> list[dict]:
    """Rows of a ``rows.jsonl`` (one JSON object per line), in the order the runs finished."""
    if not Path(path).is_file():
        raise ValueError(f"rows_from must be an existing rows.jsonl file, got {str(path)!r}")
    return [json.loads(line) for line in Path(path).read_text(encoding="utf8").splitlines() if line.strip()]


def _run_one(spec: RunSpec, scene_dir: Path, root: Path, config: RobustnessConfig, pool: ProcessPoolExecutor) -> dict:
    from .recovery_photometric import seconds_per_iteration

    runs, logs = root / "runs", root / "logs"
    truth = None
    if spec.start == "sfm":
        truth, scene_dir = scene_dir, _sfm_scene(spec.scene, scene_dir, root)
    train_seconds = _train(spec, scene_dir, runs, logs, config, truth)
    folder = run_folder(spec, runs)
    result = pool.submit(evaluate_run, folder, config.alignment).result()
    if config.trace_every:
        from .regime_trace import trace_run

        result["trace"] = pool.submit(trace_run, folder).result()
    row = {"scene": spec.scene, "start": spec.start, "variant": spec.variant, "seed": spec.seed}
    row["device"] = config.device
    row["passes"] = config.iterations * config.rays_per_batch / SCENES[spec.scene].training_pixels
    row |= {key: result[key] for key in (*METRICS, "drift_behind")}
    row |= {f"start_{key}": result[f"start_{key}"] for key in (*ERRORS, "drift_behind")}
    row |= {
        "iterations": config.iterations,
        "eval_views": result["eval_views"],
        "train_seconds": train_seconds,
        "eval_seconds": result["eval_seconds"],
        "sec_per_iter": seconds_per_iteration(folder),
    }
    if "trace" in result:
        row["trace"] = result["trace"]
    record_row(row, folder, root)
    log(
        f"robustness {spec.scene} {spec.start:9s} {spec.variant:13s} seed {spec.seed}: rot {row['rot_err']:.3f} deg "
        f"pos {row['pos_err']:.2e} focal {row['focal_err']:.3f} px drift {row['drift_px']:.3f} px "
        f"psnr {row['psnr']:.2f} ssim {row['ssim']:.3f} (start rot {row['start_rot_err']:.3f} drift "
        f"{row['start_drift_px']:.3f}; {train_seconds:.0f} s + {row['eval_seconds']:.0f} s)"
    )
    return row


def record_row(row: dict, folder: Path, root: Path) -> None:
    """A finished run's row appended to ``root``'s ``ROWS_FILE`` (so a grid can span sessions), after its checkpoints
    are removed (the trainer's atomic-save folder too): the row is all that is kept of an evaluated run."""
    for checkpoints in ("nerfstudio_models", "nerfstudio_models.partial"):
        shutil.rmtree(folder / checkpoints, ignore_errors=True)
    with _ROWS_LOCK, open(root / ROWS_FILE, "a", encoding="utf8") as rows_file:
        rows_file.write(json.dumps(row) + "\n")


_SFM_LOCK = threading.Lock()


def _sfm_scene(name: str, truth: Path, root: Path) -> Path:
    """SfM of the generated scene ``truth`` (once per scene, shared by its runs): pycolmap on the full-size images
    with ``SFM_FOCAL_PRIOR``; a reconstruction that fails ``benchmarks/s2camp_bench/sfm.py``'s checks stops the benchmark."""
    from .sfm import run_sfm

    output = root / "sfm" / name
    with _SFM_LOCK:
        if not (output / "sparse" / "0" / "images.bin").exists():
            result = run_sfm(truth, output, focal_prior=SFM_FOCAL_PRIOR)
            log(
                f"robustness {name}: SfM registered {result.registered}/{result.images} images, rot "
                f"{result.rot_err_mean:.2e} rad, centre {result.centre_err_mean:.2e}, focal {result.focal:.1f} px "
                f"(true {result.true_focal:.1f})" + (f"; FAILED: {result.failure}" if result.failure else "")
            )
            if result.failure:
                raise RuntimeError(f"SfM of scene {name} failed: {result.failure}")
    return output


def run(config: RobustnessConfig) -> list[dict]:
    config = config.effective()
    config.validate()
    if config.rows_from is not None:
        return read_rows(config.rows_from)
    return in_work_folder(config.work_dir, "robust-", lambda root: _run(config, root))


def _run(config: RobustnessConfig, root: Path) -> list[dict]:
    began = time.perf_counter()
    if config.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise ValueError("device must be 'cpu' on a machine without CUDA (torch.cuda.is_available() is False), "
                             "got 'cuda'")  # fmt: skip
    (root / "logs").mkdir(parents=True, exist_ok=True)
    scene_dirs = {
        name: generated_scene(replace(SCENES[name].scene, output_dir=root / "scenes" / name)) for name in config.scenes
    }
    done, specs = resume(run_specs(config), root, config.device)
    log(
        f"robustness: {len(specs)} runs of {config.iterations} iterations, {config.workers} at a time (work: {root})"
        + (f"; {len(done)} already in {ROWS_FILE}" if done else "")
    )
    rows = run_side_by_side(specs, lambda spec, pool: _run_one(spec, scene_dirs[spec.scene], root, config, pool),
                            config.workers)  # fmt: skip
    run.minutes = (time.perf_counter() - began) / 60.0  # type: ignore[attr-defined]
    return done + rows


def resume(specs: list[RunSpec], root: Path, device: str = "cpu") -> tuple[list[dict], list[RunSpec]]:
    """The rows of ``specs`` on ``device`` already in ``root``'s ``ROWS_FILE`` (a grid continued in its work folder,
    possibly by another session) and the specs still to run. Rows of other runs stay in the file, untouched."""
    path = root / ROWS_FILE
    rows = read_rows(path) if path.exists() else []
    finished = {(row["scene"], row["start"], row["variant"], row["seed"], row_device(row)): row for row in rows}
    key = lambda spec: (spec.scene, spec.start, spec.variant, spec.seed, device)  # noqa: E731
    done = [finished[key(spec)] for spec in specs if key(spec) in finished]
    return done, [spec for spec in specs if key(spec) not in finished]


def run_side_by_side(specs: list, run_one, workers: int) -> list[dict]:
    """``run_one(spec, pool)`` of every spec, ``workers`` at a time (threads that each wait on their ``ns-train``),
    with a pool of as many single-threaded spawned processes for the evaluations; the rows in the specs' order."""
    context = multiprocessing.get_context("spawn")  # a forked torch (threads, OpenMP state) is not safe
    with (
        ProcessPoolExecutor(workers, mp_context=context, initializer=_single_thread) as pool,
        ThreadPoolExecutor(workers) as threads,
    ):
        futures = [threads.submit(run_one, spec, pool) for spec in specs]
        return [future.result() for future in futures]


# --------------------------------------------------------------------------------------------------------- report
@dataclass(frozen=True)
class Spread:
    """Mean, min and max of one metric over seeds."""

    mean: float
    low: float
    high: float
    count: int

    @classmethod
    def of(cls, values: list[float]) -> Spread:
        return cls(statistics.fmean(values), min(values), max(values), len(values))

    @property
    def width(self) -> float:
        return self.high - self.low

    def cell(self, digits: int = 3) -> str:
        if self.count == 1:
            return f"{self.mean:.{digits}g}"
        return f"{self.mean:.{digits}g} [{self.low:.{digits}g}, {self.high:.{digits}g}]"


def summarize(rows: list[dict]) -> list[dict]:
    """One row per scene, start, variant and passes per pixel (``--rays-per-batch`` and ``--iterations`` change them):
    the metrics over seeds (``Spread``), the PSNR difference against "off" at the same passes (labelled "no difference"
    when smaller than the larger of the two seed ranges) and, for perturbed starts, the fraction of the start error
    removed (1 - mean final / start; the start is the same for every seed). In report order (``report_order``)."""
    groups: dict[tuple[str, str, str, str, str, str], list[dict]] = {}
    for row in rows:
        passes = f"{row.get('passes', math.nan):.3g}"
        key = (row["scene"], row["start"], row["variant"], _start_build(row), passes, row_device(row))
        groups.setdefault(key, []).append(row)
    summary = []
    for (scene, start, variant, build, passes, device), chosen in groups.items():
        entry = {"scene": scene, "start": start, "variant": variant, "build": build, "seeds": len(chosen)}
        entry["device"] = device
        entry["seed_list"] = sorted(row["seed"] for row in chosen)
        entry["passes_key"] = passes
        entry["passes"] = statistics.fmean(row.get("passes", math.nan) for row in chosen)
        for key in METRICS:
            entry[key] = Spread.of([row[key] for row in chosen])
        for key in ERRORS:
            entry[f"start_{key}"] = statistics.fmean(row[f"start_{key}"] for row in chosen)
            start_value = entry[f"start_{key}"]
            entry[f"removed_{key}"] = (
                1.0 - entry[key].mean / start_value if start in RECOVERY_STARTS and start_value > 0 else math.nan
            )
        summary.append(entry)
    for entry in summary:
        start = OFF_REFERENCE_START.get(entry["start"], entry["start"])
        reference = (entry["scene"], start, "off", entry["build"], entry["passes_key"], entry["device"])
        off = next((e for e in summary if _summary_key(e) == reference), None)
        entry["psnr_vs_off"] = math.nan if off is None else entry["psnr"].mean - off["psnr"].mean
        entry["psnr_vs_off_label"] = _difference_label(entry, off)
    return report_order(summary, then=("device", "passes_key", "build"))


def report_order(entries: list[dict], then: tuple[str, ...] = ()) -> list[dict]:
    """``entries`` by scene, start and variant in the order ``SCENES``, ``STARTS`` and ``RUNNABLE_VARIANTS`` list
    them (names no longer run after them), then by the keys ``then``."""
    return in_report_order(entries, tuple(SCENES), STARTS, RUNNABLE_VARIANTS, then)


def _summary_key(entry: dict) -> tuple[str, str, str, str, str, str]:
    return entry["scene"], entry["start"], entry["variant"], entry["build"], entry["passes_key"], entry["device"]


def row_device(row: dict) -> str:
    """The device a row trained on; rows written before ``--device`` existed trained on the CPU."""
    return row.get("device", "cpu")


def _start_build(row: dict) -> str:
    """Which SfM reconstruction an sfm row started from (its start rotation error; pycolmap's builds differ between
    work folders, and rows of different builds are different starts), "" for the other starts: their start is the
    scene's (accurate, perturbed) or each seed's own draw (phone)."""
    return f"{row['start_rot_err']:.4g}" if row["start"] == "sfm" else ""


def _difference_label(entry: dict, off: dict | None) -> str:
    if off is None or entry["variant"] == "off":
        return ""
    difference = entry["psnr"].mean - off["psnr"].mean
    spread = max(entry["psnr"].width, off["psnr"].width)
    text = f"{difference:+.2f} dB"
    if min(entry["seeds"], off["seeds"]) < 2:
        return f"{text} (1 seed, no spread)"
    return f"{text} (no difference)" if abs(difference) < spread else f"{text} (beyond the seed range {spread:.2f})"


def plot(summary: list[dict], path: Path) -> None:
    """PSNR and drift per variant and start, one column per scene, error bars from the seed range."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(entry["scene"] for entry in summary))
    variants = list(dict.fromkeys(entry["variant"] for entry in summary))
    starts = list(dict.fromkeys(entry["start"] for entry in summary))
    keys = (("psnr", "held-out PSNR (dB)"), ("drift_px", "drift (px RMS)"))
    figure, axes = plt.subplots(len(keys), len(scenes), figsize=(4.2 * len(scenes), 6.0), squeeze=False)
    width = 0.8 / len(starts)
    for column, scene in enumerate(scenes):
        for row_index, (key, label) in enumerate(keys):
            axis = axes[row_index][column]
            for offset, start in enumerate(starts):
                chosen = [
                    next((e[key] for e in summary if (e["scene"], e["start"], e["variant"]) == (scene, start, v)), None)
                    for v in variants
                ]
                xs = [i + (offset - (len(starts) - 1) / 2) * width for i in range(len(variants))]
                means = [s.mean if s else math.nan for s in chosen]
                # Clamped: the mean of equal values can differ from them in the last bit.
                errors = [
                    [max(s.mean - s.low, 0.0) if s else 0.0 for s in chosen],
                    [max(s.high - s.mean, 0.0) if s else 0.0 for s in chosen],
                ]
                axis.bar(xs, means, width, yerr=errors, capsize=3, label=start)
            axis.set_xticks(range(len(variants)), variants, rotation=20, fontsize=8)
            axis.set_title(f"{scene}: {label}", fontsize=9)
            axis.grid(True, axis="y", alpha=0.3)
            if key == "psnr":
                finite = [e["psnr"].low for e in summary if e["scene"] == scene]
                axis.set_ylim(bottom=max(0.0, min(finite) - 2.0))
        axes[0][column].legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)


def _scene_table(config: RobustnessConfig, summary: list[dict]) -> str:
    rows = []
    for name in dict.fromkeys(entry["scene"] for entry in summary):
        preset = SCENES[name]
        s = preset.scene
        starts = {e["start"]: e for e in summary if e["scene"] == name}
        perturbed = starts.get("perturbed")
        rows.append(
            {
                "scene": name,
                "images": s.num_cameras,
                "size": f"{s.width}x{s.height}",
                "fov": f"{preset.fov_degrees:g} deg (f {s.focal:.1f} px)",
                "ring": s.ring_radius,
                "seed": preset.perturbation_seed,
                "start": "" if perturbed is None else (
                    f"rot {perturbed['start_rot_err']:.3f} deg, pos {perturbed['start_pos_err']:.2e}, focal "
                    f"{perturbed['start_focal_err']:.3f} px, drift {perturbed['start_drift_px']:.3f} px"
                ),
                "varies": preset.varies,
            }
        )  # fmt: skip
    columns = ["scene", "images", "size", "fov", "ring", "seed", "start", "varies"]
    headers = ["scene", "images", "size", "fov", "ring radius", "perturbation seed", "perturbed start errors", "what"]
    return markdown_table(rows, columns, headers)


def seeds_cell(seeds: list[int]) -> str:
    """The number of runs; a seed run more than once (ns-train on a CPU is not bit-reproducible, so a repeat is
    another sample, not a copy) is named, so that the count is never read as that many distinct seeds."""
    repeated = sorted({seed for seed in seeds if seeds.count(seed) > 1})
    if not repeated:
        return str(len(seeds))
    names = ", ".join(f"{seed} x{seeds.count(seed)}" for seed in repeated)
    return f"{len(seeds)} runs, {len(set(seeds))} seeds (seed {names})"


def _summary_rows(summary: list[dict]) -> list[dict]:
    table = []
    for entry in summary:
        row = {key: entry[key] for key in ("scene", "start", "variant")}
        if entry["device"] == "cuda":
            row["scene"] += " (CUDA, nerfacto's field)"
        row["seeds"] = seeds_cell(entry["seed_list"])
        row |= {key: entry[key].cell() for key in METRICS}
        row["psnr_vs_off"] = entry["psnr_vs_off_label"]
        row["passes"] = f"{entry['passes']:.2f}"
        row["start_errors"] = (
            f"{entry['start_rot_err']:.3g} / {entry['start_pos_err']:.3g} / {entry['start_focal_err']:.3g} / "
            f"{entry['start_drift_px']:.3g}"
        )
        row["removed"] = (
            ", ".join(f"{key.replace('_err', '').replace('_px', '')} {entry[f'removed_{key}']:.0%}" for key in ERRORS)
            if entry["start"] in RECOVERY_STARTS
            else ""
        )
        table.append(row)
    return table


def report(rows: list[dict], config: RobustnessConfig) -> Path:
    config = config.effective()
    summary = summarize(rows)
    iterations = ", ".join(str(value) for value in sorted({row["iterations"] for row in rows}))
    seeds = ", ".join(str(value) for value in sorted({row["seed"] for row in rows}))
    plot(summary, config.output_dir / f"{config.preset or 'robustness'}.png")
    a = config.alignment
    setup = (
        f"Every run: `ns-train <method>` from scratch with the method's default options (camera learning rate and "
        f"schedule included) and only what a CPU run needs: the small nerfacto field "
        f"(`s2camp_bench.train_commands.SMALL_MODEL`), `--machine.device-type cpu`, `--max-num-iterations "
        f"{iterations}`, {config.rays_per_batch} rays per step, no evaluation or camera-error logging during "
        f"training; `--machine.seed` {seeds}. 'off' is `ns-train s2camp --pipeline.model.camera-optimizer.mode off`. "
        f"'perturbed' is the data parser's CamP perturbation (CamP's sigmas, the scene's perturbation seed), "
        f"'accurate' the true cameras, 'sfm' pycolmap SfM on the full-size images (focal prior {SFM_FOCAL_PRIOR} x "
        f"the true focal; built once per work folder; builds in different work folders differ, so the start "
        f"column gives each row's SfM errors and rows of different builds are different rows; the prior's anchor "
        f"is fitted to SfM's "
        f"points re-adjusted with its robust loss, `s2camp_ns/tracks/robust_adjustment.py`), 'phone' "
        f"`PHONE_PROFILE` without SfM tracks, 'accurate-untracked' "
        f"the true cameras without SfM tracks (`benchmarks/s2camp_bench/robustness.py`); both train with tracks made from their "
        f"images (`--image-tracks always`, `s2camp_ns/tracks/image_tracks.py`). Errors of the final checkpoint "
        f"after a similarity alignment to the true cameras: rotation in degrees, position in normalized scene units "
        f"(the cameras fit in [-1, 1]^3), focal in px; drift = RMS pixel displacement of the scene's 3D points "
        f"between the true and the aligned refined cameras (`s2camp_bench.drift`). PSNR / SSIM: held-out views "
        f"(every 8th image) after {a.steps} test-time alignment steps of {a.rays} rays. Cells: mean [min, max] over "
        f"the runs, one per seed unless the seeds cell names a seed run twice. 'PSNR vs off': difference of the "
        f"means, 'no difference' when smaller than the larger seed range of the two. 'removed': 1 - final / start "
        f"error for perturbed and phone starts. Rows whose scene says 'CUDA, nerfacto's field' trained with "
        f"`--device cuda`: nerfacto's own field (no `SMALL_MODEL`) on a CUDA device (the machine in the timing line "
        f"of their run), everything else alike."
    )
    columns = ["scene", "start", "variant", "seeds", "passes", "start_errors", *METRICS, "psnr_vs_off", "removed"]
    headers = [
        "scene", "start", "variant", "seeds", "passes", "start rot / pos / focal / drift", "rot err (deg)",
        "pos err", "focal err (px)", "drift (px)", "PSNR", "SSIM", "PSNR unaligned", "PSNR vs off",
        "start error removed",
    ]  # fmt: skip

    def average(key: str) -> float:
        return statistics.fmean(row[key] for row in rows)

    timing = (
        f"{len(rows)} runs; per run on average: training {average('train_seconds'):.0f} s (start-up included, "
        f"{average('sec_per_iter'):.3f} s / iteration), evaluation {average('eval_seconds'):.0f} s; "
        f"{config.workers} runs side by side"
    )
    minutes = getattr(run, "minutes", None)
    if config.rows_from is not None:
        seed_count = len({row["seed"] for row in rows})
        timing += f"; rows read from `{config.rows_from.name}` of an earlier run ({seed_count} seed(s)"
        stopped = f"; the command runs {config.seeds}: that run was stopped early"
        timing += ")" if seed_count >= config.seeds else stopped + ")"
    elif minutes is not None:
        timing += f"; wall time of this run {minutes:.1f} minutes"
    name = config.preset or "robustness"
    current, old = split_runnable(_summary_rows(summary), RUNNABLE_VARIANTS, STARTS)
    sections = [
        "Does camera refinement with each method's default options help or hurt, from accurate and from perturbed "
        "cameras? Protocol and metrics: `benchmarks/s2camp_bench/robustness.py`. passes = steps x rays / training pixels.",
        "## Scenes",
        _scene_table(config, summary),
        "## Results",
        setup,
        markdown_table(current, columns, headers),
        f"![PSNR and drift per variant]({name}.png)",
        timing + ".",
        *(no_longer_run_section(markdown_table(old, columns, headers)) if old else []),
        *trace_sections(rows),
    ]
    return write_report(
        config.output_dir, name, "Robustness: default camera refinement from accurate and perturbed cameras",
        config.command(), sections,
    )  # fmt: skip


TRACE_COLUMNS = (
    "step", "train_loss", "rot_err", "moved_rot", "moved_pos", "moved_focal", "gauge_scale", "gauge_rot",
    "forward_shift", "focal_forward_corr", "rot_err_common", "pitch_y_corr", "yaw_x_corr", "pose_consistency",
    "intrinsics_consistency",
)  # fmt: skip


def trace_sections(rows: list[dict]) -> list[str]:
    """One table per traced run: the cameras' path through training (``benchmarks/s2camp_bench/regime_trace.py``)."""
    sections = []
    for row in report_order(rows, then=("seed",)):
        trace = row.get("trace")
        if not trace:
            continue
        title = f"### Camera path: {row['scene']}, {row['start']} start, {row['variant']}, seed {row['seed']}"
        cells = [{key: f"{point.get(key, math.nan):.4g}" for key in TRACE_COLUMNS} for point in trace]
        sections += [title, markdown_table(cells, list(TRACE_COLUMNS), list(TRACE_COLUMNS))]
    if sections:
        sections.insert(0, "## The mechanism: camera paths (`--trace-every`; columns: `benchmarks/s2camp_bench/regime_trace.py`)")
    return sections
