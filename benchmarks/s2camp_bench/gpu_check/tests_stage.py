"""The ``cuda`` tests stage: ``pytest -m cuda`` on the files that hold them (``config.CUDA_TEST_FILES``).

Passed only if pytest ran at least one test, and every test it collected ran and passed: on a CUDA machine none may
skip. pytest writes its JUnit file at its end; a run stopped at the deadline is counted from its verbose log, one
line per finished test.
"""

from __future__ import annotations

import re
import sys
import time
import xml.etree.ElementTree as ElementTree
from pathlib import Path

from .config import CUDA_TEST_FILES, GpuCheckConfig
from .processes import Deadline, failure, run_logged
from .records import StageResult

STAGE = "`pytest -m cuda`"
OUTCOME = re.compile(r"^\S+::\S+ (PASSED|FAILED|ERROR|SKIPPED)\b", re.MULTILINE)
"""A finished test in pytest's ``-v`` output."""
LOG_KEYS = {"PASSED": "passed", "FAILED": "failures", "ERROR": "errors", "SKIPPED": "skipped"}


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


def log_counts(log_path: Path) -> dict[str, int]:
    """The same totals from pytest's ``-v`` log, for a run stopped before its JUnit file was written."""
    counts = dict.fromkeys(("tests", "failures", "errors", "skipped", "passed"), 0)
    text = log_path.read_text(encoding="utf8", errors="replace") if log_path.is_file() else ""
    for outcome in OUTCOME.findall(text):
        counts[LOG_KEYS[outcome]] += 1
        counts["tests"] += 1
    return counts


def progress(log_path: Path) -> str:
    counts = log_counts(log_path)
    return f"pytest: {counts['tests']} tests finished, {counts['passed']} passed"


def cuda_tests_result(
    status: int | None, counts: dict[str, int] | None, log_path: Path, timeout_s: float, seconds: float | None = None
) -> StageResult:
    """Passed only if pytest succeeded, ran at least one test and skipped none (on CUDA nothing may skip);
    ``status`` None: stopped at its limit, ``counts`` then those of the tests that finished before."""
    if counts is None:
        return StageResult(STAGE, False, failure("pytest", status, log_path, timeout_s), seconds)
    summary = ", ".join(f"{counts[key]} {key}" for key in ("passed", "failures", "errors", "skipped") if counts[key])
    if status is None:
        finished = summary or "no test finished"
        stopped = f"{finished} before pytest was stopped after {timeout_s / 60:.3g} minutes; log {log_path}"
        return StageResult(STAGE, False, stopped, seconds)
    if counts["tests"] == 0:
        return StageResult(STAGE, False, f"no test marked cuda was collected; log {log_path}", seconds)
    passed = status == 0 and counts["passed"] == counts["tests"]
    return StageResult(STAGE, passed, summary + ("" if passed else f"; log {log_path}"), seconds)


def run_cuda_tests(config: GpuCheckConfig, deadline: Deadline) -> StageResult:
    folder = config.folder
    junit_path = folder.junit_path
    junit_path.unlink(missing_ok=True)
    log_path = folder.logs_dir / "cuda-tests.log"
    timeout_s = deadline.limit(config.run_timeout_s)
    began = time.perf_counter()
    status = run_logged(pytest_command(junit_path), log_path, timeout_s, progress=lambda: progress(log_path))
    seconds = time.perf_counter() - began
    counts = junit_counts(junit_path) if junit_path.is_file() else (log_counts(log_path) if status is None else None)
    return cuda_tests_result(status, counts, log_path, timeout_s, seconds)
