"""``make gpu-check`` / ``python -m s2camp_bench.gpu_check``: the stages in order within a deadline.

1. the machine (refused without CUDA), written first; gsplat's kernels start building in the background;
2. the scene and its image tracks, then the timing of each pair at the methods' defaults (nerfacto against s2camp,
   splatfacto against s2camp-splat), one process per pair;
3. ``pytest -m cuda`` on the files that hold the ``cuda`` tests;
4. while time remains: the four methods trained and evaluated side by side, and with two GPUs NCCL.

Every stage's result is appended to ``stages.jsonl`` as it ends and the report is rebuilt from the folder after each
stage; ``--report-from FOLDER`` rebuilds it for a check that was cut. A stage that would start with too little time
left before ``--deadline`` is recorded as skipped; a training run stops cleanly before it. The exit status is 0 only
if every stage that ran passed; 2 when the check cannot run (no CUDA, bad options).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass

import tyro
from rich.console import Console

from . import gsplat_kernels, report
from .config import SPLAT_METHODS, STAGE_MINIMUM_S, GpuCheckConfig, parse_pair
from .environment import GpuCheckError, describe, detect_environment, install_tinycudann, require_cuda
from .processes import Deadline, stop
from .records import StageResult, append_record, skipped
from .rest import run_nccl, train_and_evaluate
from .scene_stage import prepare_scene
from .tests_stage import run_cuda_tests
from .timing import run_pair

CONSOLE = Console()


@dataclass
class CheckRun:
    """A check under way: its configuration, deadline and the gsplat build in the background."""

    config: GpuCheckConfig
    deadline: Deadline
    build: gsplat_kernels.KernelBuild | None = None
    passed: bool = True

    def record(self, stage: StageResult) -> StageResult:
        """Append ``stage`` to the folder's records, say it, and rebuild the report."""
        append_record(self.config.folder.stages_path, stage)
        CONSOLE.print(f"    {stage.name}: {stage.outcome}: {stage.detail}", highlight=False)
        self.passed = self.rebuild_report()
        return stage

    def rebuild_report(self) -> bool:
        return report.build(self.config, self.config.folder, report.COMMAND, rebuilt=False)[1]

    def allows(self, stage: str, name: str) -> bool:
        """Whether ``stage`` may start now; if not, it is recorded as skipped under ``name``."""
        if self.deadline.allows(STAGE_MINIMUM_S[stage]):
            CONSOLE.print(f">>> {name}", highlight=False)
            return True
        self.record(skipped(name, STAGE_MINIMUM_S[stage], self.deadline.remaining()))
        return False

    def building(self) -> bool:
        """Whether gsplat's kernels are being built in the background now."""
        process = None if self.build is None else self.build.process
        return process is not None and self.build.result is None and process.poll() is None

    def gsplat_ready(self) -> bool:
        """Wait for gsplat's kernels (recorded once); whether they load."""
        if self.build is None:
            return False
        if self.build.result is None:  # waited for while a timing run still fits before the deadline
            end = None if self.deadline.end is None else self.deadline.end - STAGE_MINIMUM_S["timing"]
            self.record(gsplat_kernels.finish(self.build, Deadline(end), self.config.run_timeout_s))
        return bool(self.build.result.passed)


def run(config: GpuCheckConfig) -> bool:
    """Run the check; True when every stage that ran passed. Raises GpuCheckError when it cannot run at all."""
    config = config.effective()
    config.validate()
    if config.report_from is not None:
        return rebuild_report(config)
    check = CheckRun(config, Deadline.after(config.deadline))
    environment = detect_environment()
    if not config.cpu_smoke:
        require_cuda(environment)
    folder = config.folder
    folder.root.mkdir(parents=True, exist_ok=True)
    for records in (folder.timing_dir, folder.runs_dir):  # an earlier check's, which this report must not show
        shutil.rmtree(records, ignore_errors=True)
    for path in (folder.stages_path, folder.junit_path):
        path.unlink(missing_ok=True)
    began = time.perf_counter()
    if config.tcnn_source is not None:
        check.record(build_tinycudann(config, environment))
        environment = detect_environment()
    lines = describe(environment)
    folder.environment_path.write_text("\n".join(lines) + "\n", encoding="utf8")
    check.record(StageResult("machine", True, "; ".join(lines[:2]), time.perf_counter() - began))
    if not config.cpu_smoke and needs_gsplat(config):
        check.build = gsplat_kernels.start(folder.logs_dir / "gsplat-kernels.log", config.gsplat_jobs, environment.nvcc)
    try:
        run_stages(check, environment.device_count)
    finally:
        stop_build(check)
    print(folder.report_path.read_text(), flush=True)
    CONSOLE.print(f"report: {folder.report_path}")
    return check.passed


def needs_gsplat(config: GpuCheckConfig) -> bool:
    pairs = [method for pair in config.pairs for method in parse_pair(pair)] if "timing" in config.stages else []
    return "tests" in config.stages or any(method in SPLAT_METHODS for method in pairs)


def run_stages(check: CheckRun, device_count: int) -> None:
    config, deadline = check.config, check.deadline
    if not {"timing", "rest", "nccl"} & set(config.stages):
        scene = None
    else:
        CONSOLE.print(">>> scene and image tracks", highlight=False)
        stage = check.record(prepare_scene(config.scene, config.folder.scene_dir, config.folder.logs_dir / "tracks.log",
                                           deadline))  # fmt: skip
        scene = config.folder.scene_dir if stage.passed else None
    if "timing" in config.stages and scene is not None:
        for pair in config.pairs:
            name = f"timing {pair}"
            if any(method in SPLAT_METHODS for method in parse_pair(pair)) and not check.gsplat_ready():
                check.record(StageResult(name, None, "not run: gsplat's CUDA kernels are not available (see above)"))
            elif check.allows("timing", name):
                overlapped = check.building()
                result = run_pair(config, pair, scene, deadline)
                if overlapped:
                    result.detail += "; gsplat's kernels were building in the background (niced) meanwhile"
                check.record(result)
    if "tests" in config.stages and check.allows("tests", "`pytest -m cuda`"):
        if check.build is not None:
            check.gsplat_ready()  # the gsplat tests would otherwise build the kernels inside their time limit
        check.record(run_cuda_tests(config, deadline))
    if "rest" in config.stages and scene is not None:
        for method in config.rest_methods:
            if check.allows("rest", f"rest: {method}"):
                check.record(train_and_evaluate(config, method, scene, deadline))
    if "nccl" in config.stages and scene is not None and check.allows("nccl", "nccl"):
        check.record(run_nccl(config, scene, device_count, deadline))


def stop_build(check: CheckRun) -> None:
    """A build the check never waited for: its result if it ended, else stopped (not needed before the end)."""
    build = check.build
    if build is None or build.result is not None:
        return
    if build.process is not None and build.process.poll() is None:
        stop(build.process)
        seconds = time.perf_counter() - build.began
        check.record(StageResult(gsplat_kernels.STAGE, None, f"not needed; stopped after {seconds:.0f} s", seconds))
        return
    check.gsplat_ready()


def rebuild_report(config: GpuCheckConfig) -> bool:
    """The report of the check whose folder is ``config.report_from``, from what it left there."""
    folder = type(config.folder)(config.report_from)
    command = f"{report.COMMAND} --report-from {folder.root.as_posix()}"
    command += " --write-docs" if config.write_docs else ""
    path, passed = report.build(config, folder, command, rebuilt=True)
    print(path.read_text(), flush=True)
    CONSOLE.print(f"report: {path}")
    return passed


def build_tinycudann(config: GpuCheckConfig, environment) -> StageResult:
    name = "tiny-cuda-nn build"
    log_path = config.folder.logs_dir / "tinycudann.log"
    try:
        install_tinycudann(config.tcnn_source, environment, log_path, config.run_timeout_s)
    except GpuCheckError as error:
        return StageResult(name, False, str(error))
    return StageResult(name, True, f"from {config.tcnn_source}")


def main(config: GpuCheckConfig) -> int:
    try:
        passed = run(config)
    except (GpuCheckError, ValueError) as error:
        CONSOLE.print(f"[bold red]gpu-check: {error}", highlight=False)
        return 2
    CONSOLE.print("[bold green]gpu-check passed" if passed else "[bold red]gpu-check FAILED (see the report)")
    return 0 if passed else 1


def entrypoint() -> None:
    raise SystemExit(main(tyro.cli(GpuCheckConfig, description=__doc__)))
