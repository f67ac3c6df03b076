"""Markdown reports of measurements: ``<folder>/<name>.md`` with a title, the command that regenerates it, the
machine line (``environment_line``) and its sections, written atomically (temporary name, then renamed)."""

from __future__ import annotations

import platform
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import torch


def environment_line() -> str:
    """One line naming the machine the numbers were measured on, and the date."""
    threads = torch.get_num_threads()
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else f"CPU ({threads} threads)"
    return (
        f"measured {time.strftime('%Y-%m-%d')} on {device}, {platform.machine()}, Python {platform.python_version()}, "
        f"torch {torch.__version__}"
    )


def format_value(value: object) -> str:
    """A table cell: floats to 4 significant digits (scientific below 1e-3 and from 1e4), anything else ``str``."""
    if isinstance(value, float):
        if value == 0 or 1e-3 <= abs(value) < 1e4:
            return f"{value:.4g}"
        return f"{value:.3e}"
    return str(value)


def markdown_table(rows: Sequence[dict], columns: Sequence[str], headers: Sequence[str] | None = None) -> str:
    """A markdown table, one line per row, cells ``format_value`` (empty where a row lacks the column)."""
    headers = list(headers or columns)
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for row in rows:
        lines.append("| " + " | ".join(format_value(row.get(column, "")) for column in columns) + " |")
    return "\n".join(lines)


def write_report(
    output_dir: Path, name: str, title: str, command: str, sections: Iterable[str], measured_on: str | None = None
) -> Path:
    """Write ``<output_dir>/<name>.md`` and return its path: ``# title``, "Regenerate with `command`.", the machine
    line (``measured_on``, default this machine's ``environment_line``), then the sections."""
    output_dir.mkdir(parents=True, exist_ok=True)
    path = output_dir / f"{name}.md"
    machine = environment_line() if measured_on is None else measured_on
    body = [f"# {title}", "", f"Regenerate with `{command}`.", "", f"_{machine}_", ""]
    body.extend(section.rstrip() + "\n" for section in sections)
    temporary = path.with_suffix(".md.tmp")
    temporary.write_text("\n".join(body))
    temporary.replace(path)
    return path
