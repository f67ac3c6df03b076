"""The records the GPU check writes as it goes, one JSON object per line, appended and flushed as soon as a result
exists (a check cut at any moment leaves every finished result), and how they are read back."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


def append_record(path: Path, record: Any) -> None:
    """Append the dataclass ``record`` to the JSON-lines file ``path`` (created with its folder), flushed; every
    non-finite float written as null (JSON has no NaN)."""

    def finite(value: Any) -> Any:
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, dict):
            return {key: finite(item) for key, item in value.items()}
        return [finite(item) for item in value] if isinstance(value, list) else value

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf8") as file:
        file.write(json.dumps(finite(dataclasses.asdict(record))) + "\n")
        file.flush()


def read_lines(path: Path) -> list[dict]:
    """The JSON objects of the lines of ``path``, none when the file is missing; a last line cut short by a stop is
    left out, any other line that is not JSON is an error naming the file and the line."""
    if not path.is_file():
        return []
    lines = path.read_text(encoding="utf8").splitlines()
    values = []
    for number, line in enumerate(lines, start=1):
        try:
            values.append(json.loads(line))
        except json.JSONDecodeError as error:
            if number == len(lines):
                break
            raise ValueError(f"{path}: line {number} is not JSON ({error})") from error
    return values


def as_record(kind: type[T], values: dict) -> T:
    """The dataclass ``kind`` from a JSON object (keys it has no field for are ignored)."""
    names = {f.name for f in dataclasses.fields(kind)}
    return kind(**{key: value for key, value in values.items() if key in names})


def read_records(path: Path, kind: type[T]) -> list[T]:
    """The records of ``path`` as ``kind`` (``read_lines``, ``as_record``)."""
    return [as_record(kind, values) for values in read_lines(path)]


@dataclass
class StageResult:
    """One stage of a command: ``passed`` None when it did not run (``detail`` says why)."""

    name: str
    passed: bool | None
    detail: str
    seconds: float | None = None
    """Its wall time (None: not run)."""
    finished: float = field(default_factory=time.time)
    """When it ended (``time.time()``)."""

    @property
    def outcome(self) -> str:
        return "not run" if self.passed is None else ("passed" if self.passed else "FAILED")


def skipped(name: str, needs_s: float, left_s: float) -> StageResult:
    """A stage not started because too little time was left before the deadline."""
    return StageResult(name, None, f"skipped: {left_s:.0f} s left before the deadline, it needs about {needs_s:.0f} s")
