"""gsplat's CUDA kernels, built ahead in the background while the check does other work.

    python -m s2camp_bench.gpu_check.gsplat_kernels    # exit 0 once gsplat's kernels load

gsplat from the package registry compiles its CUDA kernels with nvcc the first time they are used (minutes) and
keeps them in torch's extension folder. The check starts that build at its beginning, at the lowest CPU priority and
with ``MAX_JOBS`` compiler jobs, and waits for it only before the first run that needs it (splatfacto, the ``cuda``
tests); a build still running at the check's end is stopped.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .processes import Deadline, start_logged, stop
from .records import StageResult

STAGE = "gsplat kernels"


@dataclass
class KernelBuild:
    """A build started in the background (``process`` None: not started, ``detail`` says why)."""

    process: subprocess.Popen | None
    log_path: Path
    began: float
    detail: str = ""
    result: StageResult | None = None
    """Set once the build has ended (``finish``)."""


def start(log_path: Path, jobs: int, nvcc: str | None) -> KernelBuild:
    """Start the build (niced, ``jobs`` compiler jobs); without a CUDA compiler there is nothing to build."""
    began = time.perf_counter()
    if nvcc is None:
        return KernelBuild(None, log_path, began, "not built: no CUDA compiler (nvcc) on this machine")
    environment = {**os.environ, "MAX_JOBS": str(jobs), "PYTHONUNBUFFERED": "1"}
    command = ["nice", "-n", "19", sys.executable, "-m", __spec__.name]
    return KernelBuild(start_logged(command, log_path, environment), log_path, began)


def finish(build: KernelBuild, deadline: Deadline, timeout_s: float) -> StageResult:
    """Wait for the build, at most ``timeout_s`` from its start and until the deadline; its result (stopped and
    failed when either comes first)."""
    if build.result is not None:
        return build.result
    if build.process is None:
        build.result = StageResult(STAGE, False, build.detail)
        return build.result
    try:
        left_s = deadline.limit(timeout_s - (time.perf_counter() - build.began))
        status = build.process.wait(timeout=max(0.0, left_s))
    except subprocess.TimeoutExpired:
        stop(build.process)
        status = None
    seconds = time.perf_counter() - build.began
    if status == 0:
        build.result = StageResult(STAGE, True, f"ready {seconds:.0f} s after the start of the build", seconds)
    elif status is None:
        detail = f"still building after {seconds:.0f} s, stopped; log {build.log_path}"
        build.result = StageResult(STAGE, False, detail, seconds)
    else:
        build.result = StageResult(STAGE, False, f"build failed (status {status}); log {build.log_path}", seconds)
    return build.result


def main() -> None:
    from gsplat.cuda._backend import _C

    if _C is None:
        raise SystemExit("gsplat's CUDA kernels are not available (gsplat found no CUDA toolkit)")
    print("gsplat's CUDA kernels are built and load", flush=True)


if __name__ == "__main__":
    main()
