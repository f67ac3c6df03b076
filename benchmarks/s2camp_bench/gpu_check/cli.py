"""``make gpu-check`` / ``python -m s2camp_bench.gpu_check``: the stages in order within a deadline.

1. the machine (refused without CUDA), written first; the scene before the first training (its image tracks are
   built by the first run's set-up and cached in the scene folder: no step is timed while they are built);
2. ``timing``: each group at the methods' defaults (refinement off against s2camp-so3xr3 and s2camp; splat-off
   against s2camp-splat-so3xr3 and s2camp-splat), one process per group;
3. ``regime``: s2camp at real resolution beside the tracks alone and the images alone (``regime``);
4. ``tests``: ``pytest -m cuda`` on the files that hold the ``cuda`` tests.

Every stage's result is appended to ``stages.jsonl`` as it ends and the report is rebuilt from the folder after each
stage; ``--report-from FOLDER`` rebuilds it for a check that was cut. A stage that would start with too little time
left before ``--deadline`` is recorded as skipped; a training run stops cleanly before it. The exit status is 0 only
if every stage that ran passed; 2 when the check cannot run (no CUDA, bad options).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import replace
from pathlib import Path

import tyro

from s2camp_bench.common import generated_scene

from . import report
from .config import STAGE_MINIMUM_S, STOP_RESERVE_S, GpuCheckConfig
from .environment import GpuCheckError, describe, detect_environment, require_cuda
from .processes import Deadline
from .records import StageResult, append_record, skipped
from .regime import run_regime
from .tests_stage import run_cuda_tests
from .timing import run_group


def record(config: GpuCheckConfig, stage: StageResult) -> bool:
    """Append ``stage`` to the folder's records, say it, and rebuild the report; whether every stage passed."""
    append_record(config.folder.stages_path, stage)
    print(f"    {stage.name}: {stage.outcome}: {stage.detail}", flush=True)
    return report.build(config, config.folder, report.COMMAND, rebuilt=False)[1]


def allowed(config: GpuCheckConfig, deadline: Deadline, stage: str, name: str) -> bool:
    """Whether ``stage`` may start now; if not, it is recorded as skipped under ``name``."""
    if deadline.allows(STAGE_MINIMUM_S[stage]):
        print(f">>> {name}", flush=True)
        return True
    record(config, skipped(name, STAGE_MINIMUM_S[stage], deadline.remaining()))
    return False


def prepare_scene(config: GpuCheckConfig, scene: Path) -> StageResult:
    """The generated scene in ``scene``, reused when generated there with the same settings."""
    began, s = time.perf_counter(), config.scene
    try:
        generated_scene(replace(s, output_dir=scene))
    except (ValueError, RuntimeError) as error:
        return StageResult("scene", False, f"s2camp-make-scene failed: {error}", time.perf_counter() - began)
    return StageResult("scene", True, f"{s.num_cameras} images {s.width}x{s.height}", time.perf_counter() - began)


def run_stages(config: GpuCheckConfig, deadline: Deadline) -> bool:
    """The scene (if a stage trains), the timing groups, the regime, the tests, as asked for; whether every stage
    that ran passed."""
    passed, scene = True, config.output_dir / "scene"
    if {"timing", "regime"} & set(config.stages):
        print(">>> scene", flush=True)
        passed = record(config, prepare_scene(config, scene))
        if not passed:
            return False
    for group in config.groups if "timing" in config.stages else ():
        if allowed(config, deadline, "timing", f"timing {group}"):
            passed = record(config, run_group(config, group, scene, deadline))
    if "regime" in config.stages and allowed(config, deadline, "regime", "regime"):
        reserve = STOP_RESERVE_S + (STAGE_MINIMUM_S["tests"] if "tests" in config.stages else 0.0)
        passed = record(config, run_regime(config, scene, deadline, reserve))
    if "tests" in config.stages and allowed(config, deadline, "tests", "`pytest -m cuda`"):
        passed = record(config, run_cuda_tests(config, deadline))
    return passed


def run(config: GpuCheckConfig) -> bool:
    """Run the check; True when every stage that ran passed. Raises GpuCheckError when it cannot run at all."""
    config = config.effective()
    config.validate()
    if config.report_from is not None:
        command = f"{report.COMMAND} --report-from {config.report_from.as_posix()}"
        path, passed = report.build(config, type(config.folder)(config.report_from), command, rebuilt=True)
        print(path.read_text(), flush=True)
        return passed
    deadline = Deadline.after(config.deadline)
    environment = detect_environment()
    if not config.cpu_smoke:
        require_cuda(environment)
    folder = config.folder
    folder.root.mkdir(parents=True, exist_ok=True)
    for records in ("timing", "errors"):  # an earlier check's, which this report must not show
        shutil.rmtree(folder.root / records, ignore_errors=True)
    folder.stages_path.unlink(missing_ok=True)
    began = time.perf_counter()
    lines = describe(environment)
    folder.environment_path.write_text("\n".join(lines) + "\n", encoding="utf8")
    passed = record(config, StageResult("machine", True, "; ".join(lines[:2]), time.perf_counter() - began))
    passed = run_stages(config, deadline) and passed
    print((folder.root / "gpu-check.md").read_text(), flush=True)
    return passed


def main(config: GpuCheckConfig) -> int:
    try:
        passed = run(config)
    except (GpuCheckError, ValueError) as error:
        print(f"gpu-check: {error}", flush=True)
        return 2
    print("gpu-check passed" if passed else "gpu-check FAILED (see the report)", flush=True)
    return 0 if passed else 1


def entrypoint() -> None:
    raise SystemExit(main(tyro.cli(GpuCheckConfig, description=__doc__)))
