"""imageio-ffmpeg's ffmpeg for nerfstudio's renderer on machines without a system ffmpeg.

nerfstudio's ``ns-render`` stops with "Could not find ffmpeg" when no executable named ``ffmpeg`` is on PATH
(checked after it loads the run, even with ``--output-format images``), and mediapy, which writes its videos, runs
that same ``ffmpeg``. The registry package imageio-ffmpeg (a dependency) ships a static ffmpeg binary, H.264
included, under a name of its own. ``use_bundled_ffmpeg``, which ``S2CampPipeline`` calls when it is set up (the
first thing ``ns-render`` does with a run), hands that binary to mediapy (``mediapy.set_ffmpeg``) and puts it on this
process's PATH as ``ffmpeg``, in a temporary folder of its own removed when the process ends; only where no ffmpeg is
found on PATH, so a system ffmpeg is always the one used, and nothing is installed under the name of a system tool.
``IMAGEIO_FFMPEG_EXE`` (imageio-ffmpeg's own setting) picks another binary.
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
    """Where no ``ffmpeg`` is on PATH: imageio-ffmpeg's binary as ``ffmpeg`` on this process's PATH and mediapy's
    ffmpeg (module docstring); returns the name put on PATH, None where an ffmpeg was found (or no binary is)."""
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
