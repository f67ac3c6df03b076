"""What an image tracks build (``image_tracks``) is doing and how long it takes, on the terminal.

``BuildProgress`` shows one line per stage (rich, on a duplicate of the stderr descriptor, so it stays on the terminal
while COLMAP's log holds descriptors 1 and 2; one plain line per stage where stderr is not a terminal). Stages that
COLMAP records in its feature database as it goes (SIFT, matching) show per-item progress, read by a child process
(``DatabaseCounter``): pycolmap links its own SQLite, and two SQLite libraries in one process break each other's
POSIX locks. Other stages show their elapsed time, then their outcome.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

POLL_SECONDS = 0.5
"""How often (s) a stage with items reads its count from the feature database."""
LOG_WIDTH = 120
"""Line width where stderr is not a terminal (as the data parser's notices)."""


@dataclass
class Stage:
    """A stage: ``kind`` names it in ``BuildProgress.breakdown``; ``outcome``, set by the code that runs it, is shown
    when it ends; ``seconds``: its wall time."""

    description: str
    kind: str
    outcome: str = ""
    seconds: float = 0.0


def database_count(database: Path, table: str, where: str = "") -> int | None:
    """Rows of ``table`` in the COLMAP database (those satisfying the SQL ``where``), or None while it cannot be read.
    Only while no pycolmap call has the database open (during one: ``DatabaseCounter``)."""
    try:
        connection = sqlite3.connect(f"file:{database}?mode=ro", uri=True, timeout=0.05)
    except sqlite3.Error:
        return None
    try:
        condition = f" WHERE {where}" if where else ""
        return int(connection.execute(f"SELECT COUNT(*) FROM {table}{condition}").fetchone()[0])
    except sqlite3.Error:
        return None
    finally:
        connection.close()


_READER = """
import sqlite3, sys, time
path, query, interval = sys.argv[1], sys.argv[2], float(sys.argv[3])
while True:
    try:
        connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=0.05)
        try:
            print(int(connection.execute(query).fetchone()[0]), flush=True)
        finally:
            connection.close()
    except sqlite3.Error:
        pass
    time.sleep(interval)
"""
"""The child process of ``DatabaseCounter``: prints the query's count every ``interval`` seconds until killed."""


class DatabaseCounter:
    """The rows of ``table`` in the COLMAP database while COLMAP writes it, read by a child process every
    ``POLL_SECONDS`` (when ``enabled``) between entry and exit; calling it gives the latest count, or None."""

    def __init__(self, database: Path, table: str, enabled: bool = True) -> None:
        self.database, self.table, self.enabled = database, table, enabled
        self._latest: int | None = None
        self._child: subprocess.Popen | None = None
        self._thread: threading.Thread | None = None

    def __enter__(self) -> DatabaseCounter:
        if self.enabled:
            query = f"SELECT COUNT(*) FROM {self.table}"
            self._child = subprocess.Popen(
                [sys.executable, "-c", _READER, str(self.database), query, str(POLL_SECONDS)],
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            )  # fmt: skip
            self._thread = threading.Thread(target=self._read, daemon=True)
            self._thread.start()
        return self

    def _read(self) -> None:
        for line in self._child.stdout:
            self._latest = int(line)

    def __call__(self) -> int | None:
        return self._latest

    def __exit__(self, *exc_info) -> None:
        if self._child is not None:
            self._child.kill()
            self._child.wait()
            self._thread.join()
            self._child.stdout.close()


class BuildProgress:
    """The stages of one build on the terminal; a context manager around the whole build that ends with the line
    ``<title>: <breakdown>`` unless the build raised. ``console`` default: a duplicate of the stderr descriptor."""

    def __init__(self, title: str = "Built", console: Console | None = None) -> None:
        self.title = title
        self._own_stream = None
        if console is None:
            try:
                self._own_stream = os.fdopen(os.dup(2), "w", buffering=1, encoding="utf8", errors="replace")
            except OSError:  # no stderr descriptor (a daemon): nothing to show
                console = Console(quiet=True)
            else:
                console = Console(file=self._own_stream, width=None if self._own_stream.isatty() else LOG_WIDTH)
        self.console = console
        self.live = console.is_terminal and not console.is_dumb_terminal
        self._progress = Progress(
            SpinnerColumn(finished_text="[green]✓"), TextColumn("{task.description}"), BarColumn(bar_width=24),
            TextColumn("{task.fields[count]}"), TimeElapsedColumn(), console=console, disable=not self.live,
            redirect_stdout=False, redirect_stderr=False,
        )  # fmt: skip
        self.stages: list[Stage] = []
        self._start = time.perf_counter()

    def __enter__(self) -> BuildProgress:
        self._start = time.perf_counter()
        self._progress.start()
        return self

    def __exit__(self, exc_type, *exc_info) -> None:
        self._progress.stop()
        if exc_type is None:
            self.note(f"[dim]{escape(self.title)}: {escape(self.breakdown())}")
        if self._own_stream is not None:
            self._own_stream.close()

    @property
    def elapsed(self) -> float:
        """Seconds since the build started."""
        return time.perf_counter() - self._start

    def note(self, text: str) -> None:
        """A line above the stages (rich markup)."""
        self.console.print(text, highlight=False)

    @contextlib.contextmanager
    def stage(
        self,
        description: str,
        kind: str,
        total: int | None = None,
        unit: str = "",
        count: Callable[[], int | None] | None = None,
    ) -> Iterator[Stage]:
        """Show the stage ``description`` (of ``kind``) while the block runs: with ``total`` items (``unit``) and
        ``count`` (items done, or None), a bar of the items done, else a pulsing bar. At the end: its wall time and the
        ``outcome`` the block set on the yielded ``Stage``."""
        stage = Stage(description, kind)
        label = f" {unit}" if unit else ""
        shown = f"0/{total}{label}" if total is not None else ""
        task = self._progress.add_task(escape(description), total=total, count=shown)
        stop = threading.Event()
        poller = None
        if count is not None and total is not None and self.live:
            poller = threading.Thread(target=self._poll, args=(task, total, label, count, stop), daemon=True)
            poller.start()
        start = time.perf_counter()
        try:
            yield stage
        finally:
            stop.set()
            if poller is not None:
                poller.join()
            stage.seconds = time.perf_counter() - start
            self.stages.append(stage)
            done = f"{total}/{total}{label}" if total is not None else ""
            text = f"{description}: {stage.outcome}" if stage.outcome else description
            self._progress.update(task, description=escape(text), total=total or 1, completed=total or 1, count=done)
            self._progress.stop_task(task)
            if not self.live:
                items = f"{done}, " if done else ""
                self.note(f"  {escape(text)} ({items}{duration_text(stage.seconds)})")

    def _poll(self, task, total: int, label: str, count: Callable[[], int | None], stop: threading.Event) -> None:
        """Update ``task`` with ``count()`` until ``stop`` is set."""
        while not stop.wait(POLL_SECONDS):
            done = count()
            if done is not None:
                done = min(done, total)
                self._progress.update(task, completed=done, count=f"{done}/{total}{label}")

    def breakdown(self) -> str:
        """One line: each kind's wall time (its stage count in brackets when more than one) and the total, e.g.
        ``SIFT 12 s, triangulation 3.1 s (4), total 15 s``."""
        counts: dict[str, int] = {}
        for stage in self.stages:
            counts[stage.kind] = counts.get(stage.kind, 0) + 1
        parts = [
            f"{kind} {duration_text(seconds)}" + (f" ({counts[kind]})" if counts[kind] > 1 else "")
            for kind, seconds in self.seconds_by_kind().items()
        ]
        return ", ".join([*parts, f"total {duration_text(self.elapsed)}"])

    def seconds_by_kind(self) -> dict[str, float]:
        """Wall seconds of each kind of stage, summed over its stages, in the order the kinds first ran."""
        seconds: dict[str, float] = {}
        for stage in self.stages:
            seconds[stage.kind] = seconds.get(stage.kind, 0.0) + stage.seconds
        return seconds


def duration_text(seconds: float) -> str:
    """``0.4 s``, ``12 s``, ``3 min 05 s``, ``1 h 02 min``."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, rest = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes} min {rest:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


__all__ = ["POLL_SECONDS", "BuildProgress", "DatabaseCounter", "Stage", "database_count", "duration_text"]
