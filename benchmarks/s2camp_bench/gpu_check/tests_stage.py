"""The ``cuda`` tests stage: ``pytest -m cuda`` on the files that hold them (``config.CUDA_TEST_FILES``), passed only
if every test it collected (one at least) ran and passed: on a CUDA machine none may skip. The counts come from
pytest's JUnit file, written at its end (a pytest stopped at its limit writes none; its verbose log keeps the rest).
"""

from __future__ import annotations

import sys
import time
import xml.etree.ElementTree as ElementTree
from pathlib import Path

from .config import CUDA_TEST_FILES, GpuCheckConfig
from .processes import Deadline, failure, run_logged
from .records import StageResult

STAGE = "`pytest -m cuda`"


def pytest_command(junit_path: Path, files: tuple[str, ...] = CUDA_TEST_FILES) -> list[str]:
    return [
        sys.executable, "-m", "pytest", "-m", "cuda", *files, "-v", "-rA", "-p", "no:cacheprovider",
        f"--junitxml={junit_path}",
    ]  # fmt: skip


def junit_counts(junit_path: Path) -> dict[str, int]:
    """Totals of a pytest JUnit XML file: tests, failures, errors, skipped, and passed (the rest)."""
    root = ElementTree.parse(junit_path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
    keys = ("tests", "failures", "errors", "skipped")
    counts = {key: sum(int(suite.get(key, 0)) for suite in suites) for key in keys}
    counts["passed"] = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    return counts


def cuda_tests_result(status: int | None, counts: dict[str, int] | None, log_path: Path, timeout_s: float,
                      seconds: float | None = None) -> StageResult:  # fmt: skip
    """Passed only if pytest succeeded, ran at least one test and skipped none (on CUDA nothing may skip);
    ``counts`` None: pytest wrote no JUnit file (stopped at its limit, or it failed before the end)."""
    if counts is None:
        return StageResult(STAGE, False, failure("pytest", status, log_path, timeout_s), seconds)
    if counts["tests"] == 0:
        return StageResult(STAGE, False, f"no test marked cuda was collected; log {log_path}", seconds)
    summary = ", ".join(f"{counts[key]} {key}" for key in ("passed", "failures", "errors", "skipped") if counts[key])
    passed = status == 0 and counts["passed"] == counts["tests"]
    return StageResult(STAGE, passed, summary + ("" if passed else f"; log {log_path}"), seconds)


def run_cuda_tests(config: GpuCheckConfig, deadline: Deadline) -> StageResult:
    junit_path = config.output_dir / "logs" / "cuda-tests.xml"
    junit_path.unlink(missing_ok=True)
    log_path = junit_path.with_suffix(".log")
    timeout_s = deadline.limit(config.run_timeout_s)
    began = time.perf_counter()
    status = run_logged(pytest_command(junit_path), log_path, timeout_s)
    counts = junit_counts(junit_path) if junit_path.is_file() else None
    return cuda_tests_result(status, counts, log_path, timeout_s, time.perf_counter() - began)
