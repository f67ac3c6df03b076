"""Options of the GPU check, the scene it trains on, and the layout of its output folder."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.scene.make_scene import validate as validate_scene
from s2camp_ns.core.validation import check_choice, check_positive_int

STAGES = ("timing", "regime", "tests")
"""After the machine, in this order (``timing``, ``regime``, ``tests_stage``; the scene before one that trains)."""
_OFF = ["--pipeline.model.camera-optimizer.mode", "off"]
METHODS: dict[str, tuple[str, list[str]]] = {
    "off": ("s2camp", _OFF), "s2camp-so3xr3": ("s2camp-so3xr3", []), "s2camp": ("s2camp", []),
    "splat-off": ("s2camp-splat", _OFF), "s2camp-splat-so3xr3": ("s2camp-splat-so3xr3", []),
    "s2camp-splat": ("s2camp-splat", []),
}  # fmt: skip
"""A timed method: its ``ns-train`` method and options ("off": s2camp's field and data path, refinement off)."""
GROUPS = ("off/s2camp-so3xr3/s2camp", "splat-off/s2camp-splat-so3xr3/s2camp-splat")
"""``baseline/method/...``: each group trains in one process, the baseline first (its time per step the reference)."""
REGIME_VARIANTS = ("tracks-alone", "s2camp", "images-alone")
"""The regime's runs, in the order they run (``regime``)."""
CUDA_TEST_FILES = (
    "tests/test_cuda.py", "tests/test_device_audit.py", "tests/test_mixed_precision.py",
    "tests/test_splat_alignment.py", "tests/test_splat_identity.py",
)  # fmt: skip
"""The test modules with tests marked ``cuda``: ``pytest -m cuda`` gets these files, so nothing else is collected."""
STAGE_MINIMUM_S = {"timing": 45.0, "regime": 90.0, "tests": 60.0}
"""The least time before the deadline a stage starts with; with less it is recorded as skipped."""
STOP_RESERVE_S = 15.0
"""Training stops this long before the deadline, to write its last records and exit."""
LEASE_SCENE = MakeSceneConfig(
    num_cameras=40, width=640, height=480, fov="narrow", k1=0.0, k2=0.0, supersample=1, points_per_image=200, seed=0
)
"""40 images of 640x480 (35 train) with mip-NeRF 360 room's 52-degree field of view; pinhole, because the CamP
perturbation zeroes distortion (a distorted scene would leave an error no method can remove)."""
SMOKE = dict(groups=GROUPS[:1], timing_steps=8, warmup_steps=2, refresh_repeats=1, log_every=3, regime_passes=0.02,
             regime_rays=256, errors_every=3)  # fmt: skip
"""``--cpu-smoke``'s settings, and a scene of 16 images of 320x240 (image tracks need about that size)."""


@dataclass(frozen=True)
class CheckFolder:
    """Where a check writes: the machine (written first), one ``StageResult`` a line as each stage ends, the timing's
    step logs, the regime's camera errors (``run_logs``): all its report is rebuilt from (``--report-from``)."""

    root: Path

    @property
    def environment_path(self) -> Path:
        return self.root / "environment.txt"

    @property
    def stages_path(self) -> Path:
        return self.root / "stages.jsonl"

    def steps_log(self, method: str) -> Path:
        return self.root / "timing" / f"{method}.jsonl"

    def errors_log(self, variant: str) -> Path:
        return self.root / "errors" / f"{variant}.jsonl"


@dataclass
class GpuCheckConfig:
    """The CUDA path within a deadline: the machine, each group's time per step at the defaults, the regime at real
    resolution, the ``cuda`` tests."""

    output_dir: Path = Path("outputs/gpu-check")
    """Scene, records, logs and the report ``gpu-check.md`` go here."""
    deadline: float | None = None
    """Seconds from the start by which the check must be done (stages skipped, training stopped cleanly before)."""
    stages: tuple[str, ...] = STAGES
    """Stages to run after the machine, in this order."""
    groups: tuple[str, ...] = GROUPS
    """The timing stage's groups, ``baseline/method/...``, each in one process."""
    timing_steps: int = 200
    """Steps of each timing run (its other options are the method's defaults)."""
    warmup_steps: int = 30
    """Steps left out of the medians (CUDA kernels load and caches fill in the first steps)."""
    refresh_repeats: int = 3
    """Times P's refresh is timed after each S2CamP run (its default interval, 1000 steps, exceeds the run)."""
    log_every: int = 10
    """Steps between appends to a step log."""
    regime_variants: tuple[str, ...] = REGIME_VARIANTS
    regime_passes: float = 1.0
    """The regime's passes over the training pixels: steps = ceil(passes x training pixels / regime_rays)."""
    regime_rays: int = 4096
    """The regime's training rays per step (nerfacto's default)."""
    errors_every: int = 250
    """Steps between the regime's camera errors."""
    scene: MakeSceneConfig = field(default_factory=lambda: replace(LEASE_SCENE))
    """The generated scene (s2camp-make-scene options); written to <output_dir>/scene, reused when unchanged."""
    run_timeout_minutes: float = 10.0
    """Any one command (a training process, pytest) running longer than this is stopped and fails."""
    report_from: Path | None = None
    """Run nothing: rebuild the report from the folder of an earlier check, finished or cut, into output_dir."""
    cpu_smoke: bool = False
    """Test this command itself on the CPU: a small scene and field, a few steps, no ``cuda`` tests."""

    def effective(self) -> GpuCheckConfig:
        """This configuration, or with ``cpu_smoke`` its CPU version (``SMOKE`` where the command line left the
        defaults)."""
        if not self.cpu_smoke:
            return self
        smoke = {**SMOKE, "scene": replace(self.scene, num_cameras=16, width=320, height=240, points_per_image=100)}
        chosen = {key: value for key, value in smoke.items() if getattr(self, key) == getattr(GpuCheckConfig(), key)}
        return replace(self, stages=tuple(s for s in self.stages if s != "tests"), **chosen)

    def validate(self) -> None:
        for stage in self.stages:
            check_choice("stages", stage, STAGES)
        for group in self.groups:
            parse_group(group)
        for variant in self.regime_variants:
            check_choice("regime_variants", variant, REGIME_VARIANTS)
        for name in ("timing_steps", "log_every", "regime_rays", "errors_every"):
            check_positive_int(name, getattr(self, name))
        if not (isinstance(self.warmup_steps, int) and 0 <= self.warmup_steps < self.timing_steps - 1):
            raise ValueError(f"warmup_steps must be an integer in [0, {self.timing_steps - 1}) (timing_steps - 1, so "
                             f"that at least two steps are timed), got {self.warmup_steps!r}")  # fmt: skip
        repeats = self.refresh_repeats
        if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 0:
            raise ValueError(f"refresh_repeats must be an integer >= 0, got {repeats!r}")
        for name in ("regime_passes", "run_timeout_minutes", *(("deadline",) if self.deadline is not None else ())):
            if not (isinstance(getattr(self, name), (int, float)) and 0 < getattr(self, name) < math.inf):
                raise ValueError(f"{name} must be a number > 0, got {getattr(self, name)!r}")
        if self.report_from is not None and not CheckFolder(self.report_from).environment_path.is_file():
            raise ValueError(f"report_from must be the folder of an earlier check (with environment.txt), got "
                             f"{str(self.report_from)!r}")  # fmt: skip
        validate_scene(self.scene)

    @property
    def folder(self) -> CheckFolder:
        return CheckFolder(self.output_dir)

    @property
    def run_timeout_s(self) -> float:
        return 60.0 * self.run_timeout_minutes

    @property
    def regime_steps(self) -> int:
        """The regime's steps: ``regime_passes`` over the training pixels (every 8th image held out)."""
        s = self.scene
        pixels = (s.num_cameras - math.ceil(s.num_cameras / 8)) * s.width * s.height
        return math.ceil(self.regime_passes * pixels / self.regime_rays)


def parse_group(group: str) -> tuple[str, ...]:
    """``baseline/method/...`` as its methods; a clear error for anything else."""
    methods = tuple(group.split("/"))
    if len(methods) < 2 or len(set(methods)) != len(methods):
        raise ValueError(f"groups must be 'baseline/method/...' with two or more different methods, got {group!r}")
    for method in methods:
        check_choice("groups' methods", method, tuple(METHODS))
    return methods
