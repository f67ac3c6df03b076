"""Every image of a scene decoded in full once, where the data parser reads it, so that a damaged one is named there:
a truncated image keeps a valid header, and nerfstudio's loader would fail later without naming the file.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from PIL import Image
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

DECODE_THREADS = min(8, os.cpu_count() or 1)
"""Threads that decode images at once (each holds one decoded image)."""
PROGRESS_MIN_IMAGES = 200
"""Scenes of at least this many images show a progress bar while their images are decoded."""
LOG = Console(stderr=True, width=120)
"""The progress bar's console: stderr, as the data parser's notes."""


class ImageFileError(ValueError):
    """An image a scene lists that cannot be decoded: missing, truncated, corrupt or not an image."""


def _decode(path: Path) -> tuple[int, int] | BaseException:
    """(width, height) of the image at ``path`` after decoding all of it, or the error that stopped the decoding."""
    try:
        with Image.open(path) as image:
            image.load()
            return image.size
    except Exception as error:  # noqa: BLE001 (whatever stops PIL is a bad image; named by the caller)
        return error


def decoded_sizes(paths: Sequence[Path], listed_by: Path | str, what: str = "images") -> list[tuple[int, int]]:
    """(width, height) of each image of ``paths``, decoded in full on threads. ``ImageFileError`` names the first
    image that cannot be, ``listed_by`` (the scene file) and why; ``what`` names the images in the progress bar."""
    sizes: list[tuple[int, int]] = []
    progress = Progress(
        TextColumn(f"[dim]Decoding the {what} of {listed_by}"), BarColumn(), MofNCompleteColumn(),
        TimeRemainingColumn(), console=LOG, transient=True, disable=len(paths) < PROGRESS_MIN_IMAGES,
    )  # fmt: skip
    with progress, ThreadPoolExecutor(max_workers=DECODE_THREADS) as pool:
        task = progress.add_task("decode", total=len(paths))
        for path, result in zip(paths, pool.map(_decode, paths), strict=True):
            if isinstance(result, BaseException):
                pool.shutdown(cancel_futures=True)
                raise ImageFileError(_message(Path(path), listed_by, result)) from result
            sizes.append(result)
            progress.advance(task)
    return sizes


def _message(path: Path, listed_by: Path | str, error: BaseException) -> str:
    if isinstance(error, FileNotFoundError):
        return f"image {path}, listed by {listed_by}, does not exist"
    reason = str(error) or type(error).__name__
    return (
        f"image {path}, listed by {listed_by}, cannot be decoded: {reason}; expected a complete image file (a copy "
        "cut short or a damaged file: copy or export it again)"
    )


__all__ = ["DECODE_THREADS", "PROGRESS_MIN_IMAGES", "ImageFileError", "decoded_sizes"]
