"""``ffmpeg`` for nerfstudio's render commands on machines without a system ffmpeg.

nerfstudio's ``ns-render`` refuses to start without an executable named ``ffmpeg`` on PATH ("Could not find
ffmpeg", checked even with ``--output-format images``), and mediapy, which writes its videos, pipes the frames into
that same ``ffmpeg``. The registry package imageio-ffmpeg ships a static ffmpeg binary (H.264 included) but names it
by platform and version, so neither finds it. This package therefore installs a console script ``ffmpeg``
(``[project.scripts]`` in pyproject.toml) next to ``ns-render`` that runs imageio-ffmpeg's binary with the same
arguments: any install (``make venv``, ``pip install s2camp-ns``) puts it on PATH wherever its ``ns-render`` is.

With the environment not activated (``.venv/bin/ns-render`` called by its path), that folder is not on PATH; the
nerfstudio glue then calls ``make_bundled_ffmpeg_findable`` on import (an s2camp run's config imports it before
nerfstudio's check), which adds the folder to this process's PATH when no other ffmpeg is found.

In an activated environment this script comes before a system ffmpeg on PATH and runs imageio-ffmpeg's static
build (H.264 and PNG included); ``IMAGEIO_FFMPEG_EXE`` (imageio-ffmpeg's own setting) points it at another binary,
the system's for example.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

SCRIPT_NAME = "ffmpeg"
"""Name of the console script, the name nerfstudio and mediapy look for."""
_RECURSION_GUARD = "S2CAMP_BUNDLED_FFMPEG_RUNNING"
"""Set while the script looks for the binary: imageio-ffmpeg probes ``<prefix>/bin/ffmpeg`` and ``ffmpeg`` on PATH
(this script) when its own binary is missing, and must not start this script again."""


def bundled_ffmpeg_exe() -> str:
    """Path of imageio-ffmpeg's ffmpeg binary (or ``IMAGEIO_FFMPEG_EXE``); RuntimeError when there is none."""
    try:
        import imageio_ffmpeg
    except ImportError as error:
        raise RuntimeError(
            "the ffmpeg script of s2camp-ns needs the package imageio-ffmpeg (a dependency of s2camp-ns): "
            "pip install imageio-ffmpeg, or install a system ffmpeg"
        ) from error
    previous = os.environ.get(_RECURSION_GUARD)
    os.environ[_RECURSION_GUARD] = "1"
    try:
        exe = imageio_ffmpeg.get_ffmpeg_exe()
    finally:
        if previous is None:
            del os.environ[_RECURSION_GUARD]
        else:
            os.environ[_RECURSION_GUARD] = previous
    resolved = shutil.which(exe) or exe
    if Path(resolved).resolve() == Path(sys.argv[0]).resolve():
        raise RuntimeError(f"imageio-ffmpeg points back at this script ({resolved}); set IMAGEIO_FFMPEG_EXE")
    return resolved


def entrypoint() -> None:
    """``ffmpeg ARGS``: run imageio-ffmpeg's binary with ARGS (stdin, stdout and the exit status pass through)."""
    if os.environ.get(_RECURSION_GUARD):
        # Started by imageio-ffmpeg's own search: answer "not a valid ffmpeg" instead of searching again.
        sys.exit(127)
    try:
        exe = bundled_ffmpeg_exe()
    except RuntimeError as error:
        print(f"ffmpeg (s2camp-ns): {error}", file=sys.stderr)
        sys.exit(127)
    arguments = [exe, *sys.argv[1:]]
    if os.name == "nt":  # no exec on Windows: run it as a child and pass its status on
        sys.exit(subprocess.call(arguments))
    os.execv(exe, arguments)


def make_bundled_ffmpeg_findable() -> bool:
    """Put the folder of this package's ``ffmpeg`` script (beside the running Python) on this process's PATH when
    no ``ffmpeg`` is found on PATH; True when it did. Nothing changes where an ffmpeg is already found."""
    if shutil.which(SCRIPT_NAME) is not None:
        return False
    scripts = Path(sys.executable).parent
    if shutil.which(SCRIPT_NAME, path=str(scripts)) is None:
        return False
    os.environ["PATH"] = os.pathsep.join(filter(None, [str(scripts), os.environ.get("PATH", "")]))
    return True


__all__ = ["bundled_ffmpeg_exe", "entrypoint", "make_bundled_ffmpeg_findable"]
