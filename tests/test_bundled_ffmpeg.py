"""imageio-ffmpeg's binary handed to nerfstudio's renderer where the machine has no ffmpeg, without a console script
named like the system tool (``s2camp_ns.scripts.bundled_ffmpeg``); the end-to-end render is
``tests/test_e2e.py::test_ns_render_writes_a_video_without_a_system_ffmpeg``."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from s2camp_ns.scripts import bundled_ffmpeg

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


@pytest.fixture
def mediapy_ffmpeg():
    """mediapy's ffmpeg setting, put back after the test."""
    import mediapy

    saved = mediapy._config.ffmpeg_name_or_path
    yield mediapy
    mediapy.set_ffmpeg(saved)


def test_no_console_script_takes_a_system_tools_name_and_the_binary_is_a_dependency():
    lines = PYPROJECT.read_text().splitlines()
    scripts = lines[lines.index("[project.scripts]") + 1 :]
    scripts = [line.split("=")[0].strip() for line in scripts[: scripts.index("")] if not line.startswith("#")]
    assert scripts and all(name.startswith("s2camp-") for name in scripts), scripts
    dependencies = lines[lines.index("dependencies = [") :]
    assert '    "imageio-ffmpeg",' in dependencies[: dependencies.index("]")]


def test_without_an_ffmpeg_the_bundled_one_is_on_path_and_writes_mediapys_video(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mediapy_ffmpeg
):
    """PATH holds only an empty folder (``.venv/bin/ns-render`` run on a machine without ffmpeg): nerfstudio's check
    (``shutil.which("ffmpeg")``) then finds imageio-ffmpeg's binary, and mediapy writes an H.264 video with it."""
    import imageio_ffmpeg

    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    link = bundled_ffmpeg.use_bundled_ffmpeg()
    assert link is not None and link.name == bundled_ffmpeg.NAME
    assert Path(shutil.which("ffmpeg")) == link
    assert link.resolve() == Path(imageio_ffmpeg.get_ffmpeg_exe()).resolve()
    assert os.environ["PATH"] == os.pathsep.join([str(link.parent), str(empty)])
    assert mediapy_ffmpeg._config.ffmpeg_name_or_path == str(link)
    frames = np.stack([np.full((16, 24, 3), 40 * i, dtype=np.uint8) for i in range(4)])
    video = tmp_path / "video.mp4"
    mediapy_ffmpeg.write_video(video, frames, fps=4)
    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    assert meta["codec"].startswith("h264") and tuple(meta["size"]) == (24, 16)
    assert len(list(reader)) == 4
    # A second call (another pipeline in the same process) finds it and changes nothing.
    assert bundled_ffmpeg.use_bundled_ffmpeg() is None
    assert os.environ["PATH"] == os.pathsep.join([str(link.parent), str(empty)])


def test_an_ffmpeg_on_path_is_left_alone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mediapy_ffmpeg):
    system = tmp_path / "system"
    system.mkdir()
    (system / "ffmpeg").write_text("#!/bin/sh\n")
    (system / "ffmpeg").chmod(0o755)
    monkeypatch.setenv("PATH", str(system))
    before = mediapy_ffmpeg._config.ffmpeg_name_or_path
    assert bundled_ffmpeg.use_bundled_ffmpeg() is None
    assert os.environ["PATH"] == str(system)
    assert mediapy_ffmpeg._config.ffmpeg_name_or_path == before


def test_without_a_bundled_binary_nothing_changes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mediapy_ffmpeg):
    """``IMAGEIO_FFMPEG_EXE`` naming a binary that does not exist: nerfstudio's own message is left to say so."""
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", str(tmp_path / "missing-ffmpeg"))
    assert bundled_ffmpeg.bundled_ffmpeg_exe() is None
    assert bundled_ffmpeg.use_bundled_ffmpeg() is None
    assert os.environ["PATH"] == str(tmp_path)
