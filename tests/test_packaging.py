"""The wheel holds the product: every module of ``s2camp_ns`` (no subpackage dropped) and nothing of the benchmarks,
which are the development package ``s2camp_bench`` (benchmarks/pyproject.toml)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_wheel_holds_the_package_and_no_benchmark(tmp_path: Path) -> None:
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(ROOT / "s2camp_ns", source / "s2camp_ns", ignore=shutil.ignore_patterns("__pycache__"))
    command = [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "-q"]
    subprocess.run([*command, "-w", str(tmp_path / "wheel")], check=True, capture_output=True, timeout=600)
    (wheel,) = (tmp_path / "wheel").glob("s2camp_ns-*.whl")
    archive = zipfile.ZipFile(wheel)
    names = {name for name in archive.namelist() if name.endswith(".py")}
    modules = {path.relative_to(ROOT).as_posix() for path in (ROOT / "s2camp_ns").rglob("*.py")}
    assert names == modules
    assert not any("bench" in name for name in archive.namelist())
    (entry_file,) = [name for name in archive.namelist() if name.endswith(".dist-info/entry_points.txt")]
    entry_points = archive.read(entry_file)
    assert b"s2camp-bench" not in entry_points and b"s2camp-export-cameras" in entry_points
