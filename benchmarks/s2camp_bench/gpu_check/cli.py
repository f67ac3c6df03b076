"""``make gpu-check`` / ``python -m s2camp_bench.gpu_check``: the stages in order within a deadline.

1. the machine (refused without CUDA), written first;
2. the scene and its image tracks, then the timing of each group at the methods' defaults (refinement off against
   s2camp-so3xr3 and s2camp; splat-off against s2camp-splat-so3xr3 and s2camp-splat), one process per group;
3. ``pytest -m cuda`` on the files that hold the ``cuda`` tests.

Every stage's result is appended to ``stages.jsonl`` as it ends and the report is rebuilt from the folder after each
stage; ``--report-from FOLDER`` rebuilds it for a check that was cut. A stage that would start with too little time
left before ``--deadline`` is recorded as skipped; a training run stops cleanly before it. The exit status is 0 only
if every stage that ran passed; 2 when the check cannot run (no CUDA, bad options).
"""

from __future__ import annotations

import shutil
import time

import tyro

from . import report
from .config import STAGE_MINIMUM_S, GpuCheckConfig
from .environment import GpuCheckError, describe, detect_environment, require_cuda
from .processes import Deadline
from .records import StageResult, append_record, skipped
from .scene_stage import prepare_scene
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


def run_stages(config: GpuCheckConfig, deadline: Deadline) -> bool:
    """The scene and the timing groups (if asked for), then the tests; whether every stage that ran passed."""
    passed = True
    if "timing" in config.stages:
        print(">>> scene and image tracks", flush=True)
        scene_dir, logs = config.output_dir / "scene", config.output_dir / "logs"
        stage = prepare_scene(config.scene, scene_dir, logs / "tracks.log", deadline)
        passed = record(config, stage)
        for group in config.groups if stage.passed else ():
            if allowed(config, deadline, "timing", f"timing {group}"):
                passed = record(config, run_group(config, group, scene_dir, deadline))
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
    shutil.rmtree(folder.root / "timing", ignore_errors=True)  # an earlier check's, which this report must not show
    for path in (folder.stages_path, folder.junit_path):
        path.unlink(missing_ok=True)
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
