"""Options of the GPU check, the scene it and the regime command train on, and the layout of its output folder."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_bench.scene.make_scene import validate as validate_scene
from s2camp_ns.core.validation import check_choice, check_positive_int

STAGES = ("timing", "tests")
"""After the machine and the scene, in this order: ``timing`` the groups at their defaults; ``tests`` ``pytest -m
cuda``."""
_OFF = ["--pipeline.model.camera-optimizer.mode", "off"]
METHODS: dict[str, tuple[str, list[str]]] = {
    "off": ("s2camp", _OFF), "s2camp-so3xr3": ("s2camp-so3xr3", []), "s2camp": ("s2camp", []),
    "splat-off": ("s2camp-splat", _OFF), "s2camp-splat-so3xr3": ("s2camp-splat-so3xr3", []),
    "s2camp-splat": ("s2camp-splat", []),
}  # fmt: skip
"""A timed method: its ``ns-train`` method and options. "off" is s2camp with camera refinement off (nerfacto's
field and data path), "splat-off" likewise for s2camp-splat."""
GROUPS = ("off/s2camp-so3xr3/s2camp", "splat-off/s2camp-splat-so3xr3/s2camp-splat")
"""``baseline/method/...``: each group trains in one process, the baseline (refinement off) first; the report gives
each method's time per step over the baseline's."""
SPLAT_METHODS = ("splat-off", "s2camp-splat-so3xr3", "s2camp-splat")
"""Methods that rasterize with gsplat's CUDA kernels (not in a CPU smoke run)."""
CUDA_TEST_FILES = (
    "tests/test_cuda.py",
    "tests/test_device_audit.py",
    "tests/test_mixed_precision.py",
    "tests/test_splat_alignment.py",
    "tests/test_splat_identity.py",
)
"""The test modules that hold tests marked ``cuda``: ``pytest -m cuda`` is given these files, not the folder, so
that no other module is collected on the GPU machine."""
STAGE_MINIMUM_S = {"timing": 45.0, "tests": 60.0}
"""The least time before the deadline at which a stage is started; a stage that would start with less is recorded
as skipped."""
STOP_RESERVE_S = 15.0
"""Training stops this long before the deadline, to write its last records and exit."""
LEASE_SCENE = MakeSceneConfig(
    num_cameras=40, width=640, height=480, fov="narrow", k1=0.0, k2=0.0, supersample=1, points_per_image=200, seed=0
)
"""40 images of 640x480 (35 train, every 8th held out) with mip-NeRF 360 room's 52-degree horizontal field of view.
Pinhole, because the CamP perturbation zeroes distortion (a distorted scene would leave an error no method can
remove); one ray per pixel."""
SMOKE_SCENE = {"num_cameras": 16, "width": 320, "height": 240, "points_per_image": 100}
"""``--cpu-smoke``'s scene (image tracks need about 320x240)."""


@dataclass(frozen=True)
class CheckFolder:
    """Where a check writes: everything its report is rebuilt from (``--report-from``) and the training outputs."""

    root: Path

    @property
    def environment_path(self) -> Path:
        """The machine as the check found it, written first."""
        return self.root / "environment.txt"

    @property
    def stages_path(self) -> Path:
        """One ``StageResult`` per line, appended as each stage ends."""
        return self.root / "stages.jsonl"

    def steps_log(self, method: str) -> Path:
        """The timing stage's step log of ``method`` (``step_log``)."""
        return self.root / "timing" / f"{method}.jsonl"

    @property
    def junit_path(self) -> Path:
        """pytest's JUnit file of the ``cuda`` tests."""
        return self.root / "logs" / "cuda-tests.xml"


@dataclass
class GpuCheckConfig:
    """Prove the CUDA path within a deadline: the machine, the time per step of each group at the methods' defaults,
    then the ``cuda`` tests."""

    output_dir: Path = Path("outputs/gpu-check")
    """Scene, records, logs and the report ``gpu-check.md`` go here."""
    deadline: float | None = None
    """Seconds from the start by which the check must be done: a stage that would start with too little time left
    is recorded as skipped, and a training run stops cleanly before it with what it measured kept. None: none."""
    stages: tuple[str, ...] = STAGES
    """Stages to run after the machine and the scene, in this order."""
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
    scene: MakeSceneConfig = field(default_factory=lambda: replace(LEASE_SCENE))
    """The generated scene (s2camp-make-scene options); written to <output_dir>/scene."""
    run_timeout_minutes: float = 6.0
    """Any one command (a group's process, pytest) running longer than this is stopped and fails."""
    report_from: Path | None = None
    """Run nothing: rebuild the report from the folder of an earlier check, finished or cut, into output_dir."""
    cpu_smoke: bool = False
    """Test this command itself without a GPU: the first group's timing on the CPU, a small scene and field, a few
    steps. Its numbers mean nothing and its report says so."""

    def effective(self) -> GpuCheckConfig:
        """This configuration, or with ``cpu_smoke`` its CPU version (the smoke sizes where the command line left
        the defaults; the timing of nerfacto's group only)."""
        if not self.cpu_smoke:
            return self
        smoke = dict(groups=GROUPS[:1], timing_steps=8, warmup_steps=2, refresh_repeats=1, log_every=3,
                     scene=replace(self.scene, **SMOKE_SCENE))  # fmt: skip
        default = GpuCheckConfig()
        chosen = {key: value for key, value in smoke.items() if getattr(self, key) == getattr(default, key)}
        return replace(self, stages=tuple(s for s in self.stages if s == "timing"), **chosen)

    def validate(self) -> None:
        if self.deadline is not None and not (isinstance(self.deadline, (int, float)) and self.deadline > 0):
            raise ValueError(f"deadline must be a number of seconds > 0 (or None: no deadline), got {self.deadline!r}")
        for stage in self.stages:
            check_choice("stages", stage, STAGES)
        for group in self.groups:
            parse_group(group)
        for name in ("timing_steps", "log_every"):
            check_positive_int(name, getattr(self, name))
        if not (isinstance(self.warmup_steps, int) and 0 <= self.warmup_steps < self.timing_steps - 1):
            raise ValueError(
                f"warmup_steps must be an integer in [0, {self.timing_steps - 1}) (timing_steps - 1, so that at "
                f"least two steps are timed), got {self.warmup_steps!r}"
            )
        repeats = self.refresh_repeats
        if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 0:
            raise ValueError(f"refresh_repeats must be an integer >= 0, got {repeats!r}")
        if not self.run_timeout_minutes > 0:
            raise ValueError(f"run_timeout_minutes must be > 0, got {self.run_timeout_minutes!r}")
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


def parse_group(group: str) -> tuple[str, ...]:
    """``baseline/method/...`` as its methods; a clear error for anything else."""
    methods = tuple(group.split("/"))
    if len(methods) < 2 or len(set(methods)) != len(methods):
        raise ValueError(f"groups must be 'baseline/method/...' with two or more different methods, got {group!r}")
    for method in methods:
        check_choice("groups' methods", method, tuple(METHODS))
    return methods
