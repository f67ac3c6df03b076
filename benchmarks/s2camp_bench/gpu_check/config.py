"""Options of the GPU check, the scene it trains on, and the layout of its output folder."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.scene.make_scene import validate as validate_scene
from s2camp_ns.core.validation import check_choice, check_positive_int
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

STAGES = ("timing", "tests", "rest", "nccl")
"""After the machine and the scene, in this order: ``timing`` the pairs at their defaults; ``tests`` ``pytest -m
cuda``; ``rest`` the four methods trained and evaluated side by side; ``nccl`` two processes on two GPUs."""
PAIRS = ("nerfacto/s2camp", "splatfacto/s2camp-splat")
"""``baseline/method``: each pair trains in one process, the baseline first; the report gives method / baseline."""
PAIR_METHODS = ("nerfacto", "s2camp", "s2camp-so3xr3", "s2camp-camp", "splatfacto", "s2camp-splat")
SPLAT_METHODS = ("splatfacto", "s2camp-splat", "s2camp-splat-so3xr3")
"""Methods that rasterize with gsplat's CUDA kernels (the check waits for their build before a pair with one)."""
REST_METHODS = ("nerfacto", "s2camp-so3xr3", "s2camp", "s2camp-camp")
"""The ``rest`` stage's methods, trained and evaluated one after the other; nerfacto is the baseline of its ratios."""
REST_BASELINE = "nerfacto"
CUDA_TEST_FILES = (
    "tests/test_cuda.py",
    "tests/test_device_audit.py",
    "tests/test_mixed_precision.py",
    "tests/test_splat_alignment.py",
    "tests/test_splat_identity.py",
)
"""The test modules that hold tests marked ``cuda``: ``pytest -m cuda`` is given these files, not the folder, so
that no other module is collected on the GPU machine."""
STAGE_MINIMUM_S = {"timing": 45.0, "tests": 60.0, "rest": 240.0, "nccl": 60.0}
"""The least time before the deadline at which a stage is started (enough for it to give a result); a stage that
would start with less is recorded as skipped."""
STOP_RESERVE_S = 15.0
"""Training stops this long before the deadline, to write its last records and exit."""

LEASE_SCENE = MakeSceneConfig(
    num_cameras=40,
    width=640,
    height=480,
    fov="narrow",
    k1=0.0,
    k2=0.0,
    supersample=1,
    points_per_image=200,
    seed=0,
)
"""The scene of the check and of the regime command: 40 images of 640x480 (35 train, every 8th held out) with
mip-NeRF 360 room's 52-degree horizontal field of view. Pinhole, because the CamP perturbation zeroes distortion (a
distorted scene would leave an error no method can remove); one ray per pixel."""
DOCS_REPORT = Path("docs/benchmarks")
"""Where ``--write-docs`` also writes ``gpu-check.md``."""


@dataclass(frozen=True)
class CheckFolder:
    """Where a check writes: everything the report is rebuilt from (``--report-from``) and the training outputs."""

    root: Path

    @property
    def environment_path(self) -> Path:
        """The machine as the check found it, written first."""
        return self.root / "environment.txt"

    @property
    def stages_path(self) -> Path:
        """One ``StageResult`` per line, appended as each stage ends."""
        return self.root / "stages.jsonl"

    @property
    def scene_dir(self) -> Path:
        return self.root / "scene"

    @property
    def logs_dir(self) -> Path:
        return self.root / "logs"

    @property
    def timing_dir(self) -> Path:
        return self.root / "timing"

    def steps_log(self, method: str) -> Path:
        """The timing stage's step log of ``method`` (``step_log``)."""
        return self.timing_dir / f"{method}.jsonl"

    @property
    def runs_dir(self) -> Path:
        """The ``rest`` stage's evaluated runs, ``<method>.json`` each."""
        return self.root / "runs"

    def measurements_path(self, method: str) -> Path:
        return self.runs_dir / f"{method}.json"

    @property
    def ns_train_dir(self) -> Path:
        """ns-train's own output folders (configs, tensorboard; checkpoints removed after each stage)."""
        return self.root / "ns-train"

    @property
    def junit_path(self) -> Path:
        """pytest's JUnit file of the ``cuda`` tests."""
        return self.logs_dir / "cuda-tests.xml"

    @property
    def report_path(self) -> Path:
        return self.root / "gpu-check.md"


@dataclass
class GpuCheckConfig:
    """Prove the CUDA path within a deadline: the machine, the time per step of the pairs at their defaults, the
    ``cuda`` tests, then the four methods evaluated side by side and NCCL while time remains."""

    output_dir: Path = Path("outputs/gpu-check")
    """Scene, measurements, logs and the report ``gpu-check.md`` go here."""
    deadline: float | None = None
    """Seconds from the start by which the check must be done: a stage that would start with too little time left
    is recorded as skipped, and a training run is stopped cleanly before it with what it measured kept. None: none."""
    stages: tuple[str, ...] = STAGES
    """Stages to run after the machine and the scene, in this order: timing, tests, rest, nccl."""
    pairs: tuple[str, ...] = PAIRS
    """The timing stage's pairs, ``baseline/method``, each in one process."""
    timing_steps: int = 200
    """Steps of each timing run (its other options are the method's defaults)."""
    warmup_steps: int = 30
    """Steps left out of the medians (CUDA kernels load and caches fill in the first steps)."""
    refresh_repeats: int = 3
    """Times P's refresh is timed after each S2CamP timing run (its default interval, 1000 steps, is longer than
    the run)."""
    log_every: int = 10
    """Steps between appends to a step log."""
    gsplat_jobs: int = 12
    """Compiler jobs (MAX_JOBS) of gsplat's kernel build in the background (at the lowest CPU priority; the rest of
    the cores stay for the check's own work)."""
    write_docs: bool = False
    """Also write the report to docs/benchmarks/gpu-check.md (for a committed result)."""
    rest_methods: tuple[str, ...] = REST_METHODS
    """The ``rest`` stage's methods; nerfacto, when present, is the baseline of its ratios."""
    rest_iterations: int = 300
    """Steps of each ``rest`` run."""
    rays_per_batch: int = 4096
    """Training rays per step of the ``rest`` and ``nccl`` runs."""
    refresh_every: int = 100
    """s2camp's P refresh interval in the ``rest`` stage: ten times as often as its default, so that refreshes fall
    inside its 300 steps."""
    scene: MakeSceneConfig = field(default_factory=lambda: replace(LEASE_SCENE))
    """The generated scene (s2camp-make-scene options); its output_dir is replaced by <output_dir>/scene."""
    alignment: AlignmentConfig = field(default_factory=lambda: AlignmentConfig(chunk=1 << 15))
    """Test-time alignment of the held-out views before their PSNR (CamP's protocol, ``s2camp-eval``)."""
    nccl_iterations: int = 60
    """Steps of the 2-process NCCL run of s2camp (P refreshed every 20)."""
    run_timeout_minutes: float = 6.0
    """Any one command (a process of training runs, pytest, a build) running longer than this is stopped and fails."""
    tcnn_source: Path | None = None
    """A local tiny-cuda-nn checkout to build and install (needs nvcc; takes minutes). Without it, a missing
    tiny-cuda-nn is reported and nerfacto runs on nerfstudio's pure-torch fallback."""
    report_from: Path | None = None
    """Run nothing: rebuild the report from the folder of an earlier check, finished or cut, into output_dir."""
    cpu_smoke: bool = False
    """Test this script itself without a GPU: the nerfacto/s2camp pair and the rest stage's nerfacto, on the CPU, on
    a tiny scene with a small field for a few steps. Its numbers mean nothing and its report says it is no GPU
    check."""

    def effective(self) -> GpuCheckConfig:
        """The configuration that runs: this one, or with ``cpu_smoke`` its tiny CPU version (the stages the CPU can
        run; the smoke sizes where the command line left the defaults)."""
        if not self.cpu_smoke:
            return self
        scene = replace(self.scene, num_cameras=16, width=320, height=240, points_per_image=100)  # tracks need 320x240
        smoke = dict(
            pairs=PAIRS[:1], timing_steps=8, warmup_steps=2, refresh_repeats=1, log_every=3, rest_methods=("nerfacto",),
            rest_iterations=8, rays_per_batch=256, refresh_every=3, scene=scene,
            alignment=replace(self.alignment, steps=2, rays=64, chunk=4096),
        )  # fmt: skip
        default = GpuCheckConfig()
        chosen = {key: value for key, value in smoke.items() if getattr(self, key) == getattr(default, key)}
        return replace(self, stages=tuple(s for s in self.stages if s in ("timing", "rest")), **chosen)

    def validate(self) -> None:
        if self.cpu_smoke and self.write_docs:
            raise ValueError("write_docs must be False with cpu_smoke: a CPU smoke run is no GPU check for docs/")
        if self.deadline is not None and not (isinstance(self.deadline, (int, float)) and self.deadline > 0):
            raise ValueError(f"deadline must be a number of seconds > 0 (or None: no deadline), got {self.deadline!r}")
        for stage in self.stages:
            check_choice("stages", stage, STAGES)
        for pair in self.pairs:
            parse_pair(pair)
        if "rest" in self.stages and not self.rest_methods:
            raise ValueError(f"rest_methods must name at least one of {', '.join(REST_METHODS)}, got none")
        for method in self.rest_methods:
            check_choice("rest_methods", method, REST_METHODS)
        if len(set(self.rest_methods)) != len(self.rest_methods):
            raise ValueError(f"rest_methods must not repeat a method, got {' '.join(self.rest_methods)}")
        for name in ("timing_steps", "rest_iterations", "log_every", "gsplat_jobs", "rays_per_batch"):
            check_positive_int(name, getattr(self, name))
        for name in ("refresh_every", "nccl_iterations"):
            check_positive_int(name, getattr(self, name))
        shortest = min(self.timing_steps, self.rest_iterations)
        if not (isinstance(self.warmup_steps, int) and 0 <= self.warmup_steps < shortest - 1):
            raise ValueError(
                f"warmup_steps must be an integer in [0, {shortest - 1}) (the shorter of timing_steps and "
                f"rest_iterations, minus one) so that at least two steps are timed, got {self.warmup_steps!r}"
            )
        repeats = self.refresh_repeats
        if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 0:
            raise ValueError(f"refresh_repeats must be an integer >= 0, got {self.refresh_repeats!r}")
        if not self.run_timeout_minutes > 0:
            raise ValueError(f"run_timeout_minutes must be > 0, got {self.run_timeout_minutes!r}")
        if self.tcnn_source is not None and not (self.tcnn_source / "bindings" / "torch").is_dir():
            raise ValueError(
                f"tcnn_source must be a tiny-cuda-nn checkout with bindings/torch/, got {str(self.tcnn_source)!r}"
            )
        if self.report_from is not None and not CheckFolder(self.report_from).environment_path.is_file():
            raise ValueError(
                f"report_from must be the folder of an earlier check (with environment.txt), got "
                f"{str(self.report_from)!r}"
            )
        validate_scene(self.scene)
        self.alignment.validate()

    @property
    def folder(self) -> CheckFolder:
        return CheckFolder(self.output_dir)

    @property
    def run_timeout_s(self) -> float:
        return 60.0 * self.run_timeout_minutes


def parse_pair(pair: str) -> tuple[str, str]:
    """``baseline/method`` as its two methods; a clear error for anything else."""
    parts = pair.split("/")
    if len(parts) != 2 or parts[0] == parts[1]:
        raise ValueError(f"pairs must be 'baseline/method' with two different methods, got {pair!r}")
    for method in parts:
        check_choice("pairs' methods", method, PAIR_METHODS)
    return parts[0], parts[1]
