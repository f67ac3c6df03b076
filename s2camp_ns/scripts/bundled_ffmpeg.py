"""imageio-ffmpeg's ffmpeg for nerfstudio's renderer on machines without a system ffmpeg.

``ns-render`` stops with "Could not find ffmpeg" without an ``ffmpeg`` on PATH, and mediapy runs that ``ffmpeg``.
``use_bundled_ffmpeg`` (called by ``S2CampPipeline`` when set up) hands imageio-ffmpeg's static binary to mediapy and
puts it on this process's PATH as ``ffmpeg`` (a temporary folder removed at exit), only where PATH has no ffmpeg.
``IMAGEIO_FFMPEG_EXE`` picks another binary.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

NAME = "ffmpeg.exe" if os.name == "nt" else "ffmpeg"
"""The name nerfstudio and mediapy look for on PATH."""


def bundled_ffmpeg_exe() -> Path | None:
    """imageio-ffmpeg's binary (or ``IMAGEIO_FFMPEG_EXE``), None where there is none."""
    try:
        import imageio_ffmpeg

        exe = shutil.which(imageio_ffmpeg.get_ffmpeg_exe())
    except (ImportError, RuntimeError):
        return None
    return None if exe is None else Path(exe)


def use_bundled_ffmpeg() -> Path | None:
    """Where no ``ffmpeg`` is on PATH: imageio-ffmpeg's binary as ``ffmpeg`` on PATH and mediapy's; returns the path
    put on PATH, None where an ffmpeg was found (or no binary is)."""
    if shutil.which("ffmpeg") is not None:
        return None
    exe = bundled_ffmpeg_exe()
    if exe is None:
        return None
    folder = Path(tempfile.mkdtemp(prefix="s2camp-ffmpeg-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    link = folder / NAME
    try:
        link.symlink_to(exe)
    except OSError:  # no symbolic links (Windows without the privilege): a copy
        shutil.copy2(exe, link)
    os.environ["PATH"] = os.pathsep.join(filter(None, [str(folder), os.environ.get("PATH", "")]))
    import mediapy

    mediapy.set_ffmpeg(str(link))
    return link


__all__ = ["bundled_ffmpeg_exe", "use_bundled_ffmpeg"]
