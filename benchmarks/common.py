"""Shared plumbing for the benchmarks: reference frusta, report writing and JSON output."""

from __future__ import annotations

import json
import math
import platform
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from s2camp_ns.core.camera import Intrinsics

DEFAULT_OUTPUT_DIR = Path("docs/benchmarks")


@dataclass(frozen=True)
class FrustumPreset:
    """A camera whose frustum the benchmarks sample."""

    name: str
    description: str
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def intrinsics(self, device: torch.device | str = "cpu") -> Intrinsics:
        return Intrinsics.create(
            fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width, height=self.height, device=device
        )


FRUSTA: dict[str, FrustumPreset] = {
    # mip-NeRF 360 "room" at 1/4 resolution (docs/DESIGN-NOTES.md sec. 4): about 52 x 36 degrees.
    "room": FrustumPreset("room", "mip-NeRF 360 room, 1/4 res", 793.13, 793.49, 389.25, 259.375, 778, 518),
    # Outdoor-like wide field of view: 90 degrees horizontal, 3:2 aspect.
    "wide": FrustumPreset("wide", "90 deg horizontal, 3:2", 384.0, 384.0, 384.0, 256.0, 768, 512),
}


def environment_line() -> str:
    """One line naming the machine the numbers were measured on."""
    threads = torch.get_num_threads()
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else f"CPU ({threads} threads)"
    return (
        f"measured {time.strftime('%Y-%m-%d')} on {device}, {platform.machine()}, Python {platform.python_version()}, "
        f"torch {torch.__version__}"
    )


def format_value(value: object) -> str:
    if isinstance(value, float):
        if value == 0 or 1e-3 <= abs(value) < 1e4:
            return f"{value:.4g}"
        return f"{value:.3e}"
    return str(value)


def markdown_table(rows: Sequence[dict], columns: Sequence[str], headers: Sequence[str] | None = None) -> str:
    headers = list(headers or columns)
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for row in rows:
        lines.append("| " + " | ".join(format_value(row.get(column, "")) for column in columns) + " |")
    return "\n".join(lines)


def write_report(output_dir: Path, name: str, title: str, command: str, sections: Iterable[str]) -> Path:
    """Write ``docs/benchmarks/<name>.md`` with the command that regenerates it."""
    output_dir.mkdir(parents=True, exist_ok=True)
    path = output_dir / f"{name}.md"
    body = [f"# {title}", "", f"Regenerate with `{command}`.", "", f"_{environment_line()}_", ""]
    body.extend(section.rstrip() + "\n" for section in sections)
    temporary = path.with_suffix(".md.tmp")
    temporary.write_text("\n".join(body))
    temporary.replace(path)
    return path


def _json_safe(value: object) -> object:
    """NaN and infinities (e.g. a threshold never reached) become null: strict JSON has no NaN."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def emit_json(rows: list[dict]) -> None:
    """Print exactly one JSON object on stdout: ``{"rows": [...]}`` (strict JSON: NaN is written as null)."""
    safe = [{key: _json_safe(value) for key, value in row.items()} for row in rows]
    sys.stdout.write(json.dumps({"rows": safe}, allow_nan=False) + "\n")
    sys.stdout.flush()


def in_work_folder(folder: Path | None, prefix: str, body: Callable[[Path], list[dict]]) -> list[dict]:
    """``body(folder)``; without a folder, ``body`` of a temporary one that is removed afterwards."""
    if folder is not None:
        return body(folder)
    with tempfile.TemporaryDirectory(prefix=prefix) as temporary:
        return body(Path(temporary))


def log(message: str) -> None:
    """Progress goes to stderr so that ``--json`` keeps stdout machine-readable."""
    print(message, file=sys.stderr, flush=True)
