"""Options of ``make gpu-check`` and the scene it trains on."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_ns.core.validation import check_choice, check_positive_int
from s2camp_ns.nerfstudio.test_time_alignment import AlignmentConfig
from s2camp_ns.scene.make_scene import MakeSceneConfig
from s2camp_ns.scene.make_scene import validate as validate_scene

METHODS = ("nerfacto", "s2camp-so3xr3", "s2camp", "s2camp-camp")
"""The ``ns-train`` methods trained side by side; nerfacto (stock nerfstudio) is the baseline of the time ratios."""
BASELINE = "nerfacto"
STAGES = ("tests", "train", "nccl")
"""``tests``: ``pytest -m cuda``; ``train``: the methods on the generated scene; ``nccl``: 2 processes (2 GPUs)."""

ROOM_IMAGES_4 = MakeSceneConfig(
    num_cameras=40,
    width=778,
    height=518,
    fov="narrow",
    k1=0.0,
    k2=0.0,
    supersample=1,
    points_per_image=200,
    seed=0,
)
"""A generated scene the size of mip-NeRF 360 room at images_4: 778x518 pixels (room's 3114x2075 photos divided by
4 and floored to even sizes, as the scene generator needs) and room's 52-degree horizontal field of view. 40 images
(room has 311): 35 train, every 8th held out. Pinhole, because the CamP perturbation zeroes distortion (a distorted
scene would leave an error no method can remove); one ray per pixel keeps the generation under a minute."""
DOCS_REPORT = Path("docs/benchmarks")
"""Where ``--write-docs`` also writes ``gpu-check.md``."""


@dataclass
class GpuCheckConfig:
    """Prove the CUDA path: the ``cuda`` tests, the four methods side by side on a room-sized scene, and NCCL."""

    output_dir: Path = Path("outputs/gpu-check")
    """Scene, runs, logs and the report ``gpu-check.md`` go here."""
    write_docs: bool = False
    """Also write the report to docs/benchmarks/gpu-check.md (for a committed result)."""
    stages: tuple[str, ...] = STAGES
    """Stages to run, in this order: tests, train, nccl."""
    methods: tuple[str, ...] = METHODS
    """Methods to train; nerfacto, when present, is the baseline of the time ratios."""
    iterations: int = 300
    """Training steps per method."""
    rays_per_batch: int = 4096
    """Training rays per step (nerfacto's default)."""
    warmup_steps: int = 30
    """Steps left out of the per-iteration time (CUDA kernels compile and caches fill in the first steps)."""
    refresh_every: int = 100
    """s2camp's P refresh interval for this check: ten times as often as its default (1000), so that refreshes fall
    inside the timed steps and the measured time bounds the default's from above."""
    scene: MakeSceneConfig = field(default_factory=lambda: replace(ROOM_IMAGES_4))
    """The generated scene (s2camp-make-scene options); its output_dir is replaced by <output_dir>/scene."""
    alignment: AlignmentConfig = field(default_factory=lambda: AlignmentConfig(chunk=1 << 15))
    """Test-time alignment of the held-out views before their PSNR (CamP's protocol, ``s2camp-eval``)."""
    nccl_iterations: int = 60
    """Steps of the 2-process NCCL run of s2camp (P refreshed every 20)."""
    run_timeout_minutes: float = 6.0
    """A training run, a pytest run or the NCCL run taking longer than this is stopped and counted as failed."""
    time_budget_minutes: float = 8.0
    """The whole check is meant to finish within this on one data-centre GPU; longer is reported (not a failure)."""
    tcnn_source: Path | None = None
    """A local tiny-cuda-nn checkout to build and install (needs nvcc; takes longer than the time budget). Without
    it, a missing tiny-cuda-nn is reported and nerfacto runs on nerfstudio's pure-torch fallback."""
    tests_dir: Path = Path("tests")
    """Where ``pytest -m cuda`` looks for the ``cuda`` tests."""
    report_from: Path | None = None
    """Run nothing: rebuild the report from the output folder of an earlier check (its ``environment.txt``,
    ``logs/cuda-tests.xml`` and ``runs/<method>.json``), for a check whose machine was lost or stopped before it wrote
    the report. Stages that left nothing there are left out of the report."""
    cpu_smoke: bool = False
    """Test this script itself without a GPU: the training stage only, on the CPU, on a tiny scene with a small
    nerfacto for a few steps. Its numbers mean nothing and its report says it is no GPU check."""

    def effective(self) -> GpuCheckConfig:
        """The configuration that runs: this one, or with ``cpu_smoke`` its tiny CPU version."""
        if not self.cpu_smoke:
            return self
        scene = replace(self.scene, num_cameras=9, width=48, height=36, points_per_image=100)
        alignment = replace(self.alignment, steps=2, rays=64, chunk=4096)
        return replace(
            self, stages=("train",), iterations=8, rays_per_batch=256, warmup_steps=2, refresh_every=3, scene=scene,
            alignment=alignment,
        )  # fmt: skip

    def validate(self) -> None:
        if self.cpu_smoke and self.write_docs:
            raise ValueError("write_docs must be False with cpu_smoke: a CPU smoke run is no GPU check for docs/")
        if not self.stages:
            raise ValueError(f"stages must name at least one of {', '.join(STAGES)}, got none")
        for stage in self.stages:
            check_choice("stages", stage, STAGES)
        if "train" in self.stages and not self.methods:
            raise ValueError(f"methods must name at least one of {', '.join(METHODS)}, got none")
        for method in self.methods:
            check_choice("methods", method, METHODS)
        if len(set(self.methods)) != len(self.methods):
            raise ValueError(f"methods must not repeat a method, got {' '.join(self.methods)}")
        for name in ("iterations", "rays_per_batch", "refresh_every", "nccl_iterations"):
            check_positive_int(name, getattr(self, name))
        if not (isinstance(self.warmup_steps, int) and 0 <= self.warmup_steps < self.iterations - 1):
            raise ValueError(
                f"warmup_steps must be an integer in [0, iterations - 1) = [0, {self.iterations - 1}) so that at "
                f"least two steps are timed, got {self.warmup_steps!r}"
            )
        for name in ("run_timeout_minutes", "time_budget_minutes"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        if self.tcnn_source is not None and not (self.tcnn_source / "bindings" / "torch").is_dir():
            raise ValueError(
                f"tcnn_source must be a tiny-cuda-nn checkout with bindings/torch/, got {str(self.tcnn_source)!r}"
            )
        if self.report_from is not None and not (self.report_from / "runs").is_dir():
            raise ValueError(
                f"report_from must be the output folder of an earlier check (with runs/), got {str(self.report_from)!r}"
            )
        validate_scene(self.scene)
        self.alignment.validate()

    @property
    def scene_dir(self) -> Path:
        return self.output_dir / "scene"

    @property
    def runs_dir(self) -> Path:
        return self.output_dir / "runs"

    @property
    def logs_dir(self) -> Path:
        return self.output_dir / "logs"

    @property
    def environment_path(self) -> Path:
        """The machine as the check found it (``environment.describe``), written first: ``--report-from`` reads it."""
        return self.output_dir / "environment.txt"

    @property
    def junit_path(self) -> Path:
        """pytest's JUnit file of the ``cuda`` tests."""
        return self.logs_dir / "cuda-tests.xml"

    def measurements_path(self, method: str) -> Path:
        """``measured_train``'s JSON of one method's run."""
        return self.runs_dir / f"{method}.json"

    @property
    def report_path(self) -> Path:
        return self.output_dir / "gpu-check.md"

    @property
    def baseline(self) -> str | None:
        return BASELINE if BASELINE in self.methods else None
