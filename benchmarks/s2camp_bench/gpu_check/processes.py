"""Commands as subprocesses with a log and a time limit, and the deadline of a whole command.

Every command runs in its own process group with stdout and stderr in its log; one that outlives its limit is
killed with its children (data-loader workers, COLMAP's threads).
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from s2camp_bench.train_commands import training_environment


@dataclass(frozen=True)
class Deadline:
    """The moment (``time.time()`` seconds) by which a command must be done; ``end`` None: no deadline."""

    end: float | None = None

    @classmethod
    def after(cls, seconds: float | None) -> Deadline:
        """The deadline ``seconds`` from now (None: none)."""
        if seconds is None:
            return cls(None)
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds > 0):
            raise ValueError(f"deadline must be a number of seconds > 0, got {seconds!r}")
        return cls(time.time() + float(seconds))

    def remaining(self) -> float:
        """Seconds left (infinite without a deadline, never below 0)."""
        return math.inf if self.end is None else max(0.0, self.end - time.time())

    def allows(self, seconds: float) -> bool:
        return self.remaining() >= seconds

    def limit(self, timeout_s: float) -> float:
        """``timeout_s``, or the time left if that is shorter."""
        return min(timeout_s, self.remaining())

    def stop_at(self, reserve_s: float) -> float | None:
        """When training must stop to end in time: ``reserve_s`` before the deadline (None without one)."""
        return None if self.end is None else self.end - reserve_s


def run_logged(command: list[str], log_path: Path, timeout_s: float) -> int | None:
    """Run ``command`` in its own session with its output in ``log_path`` (the training environment); its exit
    status, or None when it was killed for running past ``timeout_s``."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w", encoding="utf8") as output:
        process = subprocess.Popen(
            command, stdout=output, stderr=subprocess.STDOUT, env=training_environment(), start_new_session=True
        )
    try:
        return process.wait(timeout=max(timeout_s, 0.0))
    except subprocess.TimeoutExpired:
        stop(process)
        return None
    except BaseException:  # Ctrl-C does not reach the command's own session: stop it here, then stop
        stop(process)
        raise


def stop(process: subprocess.Popen) -> None:
    """Kill the command and everything it started."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    process.wait()


def failure(what: str, status: int | None, log_path: Path, timeout_s: float) -> str:
    """Why a command failed, naming its log: its exit status, or the limit it ran past."""
    if status is None:
        return f"{what} ran past {timeout_s / 60:.3g} minutes and was stopped; log {log_path}"
    return f"{what} exited with status {status}; log {log_path}"
