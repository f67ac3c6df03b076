"""The ``ffmpeg`` console script (imageio-ffmpeg's binary) that nerfstudio's ns-render needs on PATH; the end-to-end
render is ``tests/test_e2e.py::test_ns_render_writes_a_video_without_a_system_ffmpeg``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hang_guard import HANG_GUARD_S

from s2camp_ns import bundled_ffmpeg

RUN_SCRIPT = "import sys; from s2camp_ns.bundled_ffmpeg import entrypoint; sys.argv[0] = 'ffmpeg'; entrypoint()"


def test_pyproject_installs_the_script_and_its_binary():
    """Every install (``make venv``, ``pip install s2camp-ns``) gets the script beside ns-render, and the binary."""
    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text().splitlines()
    scripts = pyproject[pyproject.index("[project.scripts]") :]
    assert 'ffmpeg = "s2camp_ns.bundled_ffmpeg:entrypoint"' in scripts[: scripts.index("")]
    dependencies = pyproject[pyproject.index("dependencies = [") :]
    assert '    "imageio-ffmpeg",' in dependencies[: dependencies.index("]")]


def test_script_runs_the_bundled_binary_with_its_arguments(tmp_path: Path):
    """Arguments, stdin, stdout and the exit status pass through: two raw 4x2 frames piped in become a PNG."""
    frames = bytes(range(4 * 2 * 3)) * 2
    result = subprocess.run(
        [sys.executable, "-c", RUN_SCRIPT, "-hide_banner", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt",
         "rgb24", "-s", "4x2", "-i", "-", "-frames:v", "1", str(tmp_path / "frame.png")],
        input=frames, capture_output=True, timeout=HANG_GUARD_S, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr.decode()[-2000:]
    from PIL import Image

    with Image.open(tmp_path / "frame.png") as image:
        assert image.size == (4, 2)
        assert list(image.getdata())[:2] == [(0, 1, 2), (3, 4, 5)]
    failed = subprocess.run(
        [sys.executable, "-c", RUN_SCRIPT, "-i", str(tmp_path / "missing.mp4")],
        capture_output=True, timeout=HANG_GUARD_S, check=False,
    )  # fmt: skip
    assert failed.returncode != 0 and b"missing.mp4" in failed.stderr


def test_script_started_by_imageio_ffmpegs_own_search_does_not_search_again():
    """imageio-ffmpeg probes ``<prefix>/bin/ffmpeg`` (this script) when its binary is missing: that probe must fail
    at once instead of starting the search again, endlessly."""
    environment = {**os.environ, "S2CAMP_BUNDLED_FFMPEG_RUNNING": "1"}
    result = subprocess.run(
        [sys.executable, "-c", RUN_SCRIPT, "-version"],
        env=environment,
        capture_output=True,
        timeout=HANG_GUARD_S,
        check=False,
    )
    assert result.returncode == 127 and b"ffmpeg version" not in result.stdout


def test_script_folder_joins_path_only_when_no_ffmpeg_is_found(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    scripts = tmp_path / "venv" / "bin"
    scripts.mkdir(parents=True)
    (scripts / "ffmpeg").write_text("#!/bin/sh\n")
    (scripts / "ffmpeg").chmod(0o755)
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setattr(sys, "executable", str(scripts / "python"))
    monkeypatch.setenv("PATH", str(empty))
    assert bundled_ffmpeg.make_bundled_ffmpeg_findable() is True
    assert os.environ["PATH"] == os.pathsep.join([str(scripts), str(empty)])
    # An ffmpeg already on PATH (the system's, or the activated environment's) is left alone.
    system = tmp_path / "system"
    system.mkdir()
    (system / "ffmpeg").write_text("#!/bin/sh\n")
    (system / "ffmpeg").chmod(0o755)
    monkeypatch.setenv("PATH", str(system))
    assert bundled_ffmpeg.make_bundled_ffmpeg_findable() is False
    assert os.environ["PATH"] == str(system)
    # No script beside this Python (another install layout): nothing to add.
    (scripts / "ffmpeg").unlink()
    monkeypatch.setenv("PATH", str(empty))
    assert bundled_ffmpeg.make_bundled_ffmpeg_findable() is False
    assert os.environ["PATH"] == str(empty)
