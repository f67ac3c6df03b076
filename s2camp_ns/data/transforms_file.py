"""A nerfstudio ``transforms.json`` read and checked before anything uses it (every reader here uses
``read_transforms``); nerfstudio's parser trusts the file.

A ``TransformsFileError`` (a ValueError) names the file, the frame (index and ``file_path``), the problem and what is
allowed, for: text that is not JSON, or not an object with a non-empty ``frames`` list; a frame without a
``file_path`` or a ``transform_matrix`` of 3 or 4 rows of 4 numbers; intrinsics (``INTRINSICS_KEYS``) missing from
both the top level and the frame; a NaN or infinite number anywhere; two frames with the same image, by path or by
file name (an image's name is its file name, and nerfstudio reads ``images_<k>/<file name>``).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

INTRINSICS_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
"""Keys nerfstudio's parser needs for every frame, at the top level (shared) or in the frame."""
EXPECTED = (
    "expected nerfstudio's transforms.json: an object with the intrinsics (fl_x, fl_y, cx, cy, w, h; at the top "
    "level or in every frame) and a list 'frames' of objects, each with a 'file_path' and a 4x4 'transform_matrix'"
)


class TransformsFileError(ValueError):
    """A transforms.json that cannot be trained on: it names the file, the frame, the problem and what is allowed."""


def read_transforms(source: Path) -> dict[str, Any]:
    """The content of the transforms.json ``source``, checked (module docstring); raises ``TransformsFileError``."""
    try:
        text = Path(source).read_text(encoding="utf8")
    except UnicodeDecodeError as error:
        raise TransformsFileError(f"{source} is not UTF-8 text (byte {error.start}); {EXPECTED}") from error
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as error:
        raise TransformsFileError(
            f"{source} is not valid JSON: {error.msg} at line {error.lineno}, column {error.colno} (a file cut short "
            f"or edited by hand?); {EXPECTED}"
        ) from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        found = type(meta).__name__ if not isinstance(meta, dict) else "an object without a 'frames' list"
        raise TransformsFileError(f"{source} holds {found}; {EXPECTED}")
    if not meta["frames"]:
        raise TransformsFileError(f"{source} lists no frames: the scene is empty")
    _check_finite(source, meta)
    for index, frame in enumerate(meta["frames"]):
        _check_frame(source, meta, index, frame)
    _check_unique_images(source, meta["frames"])
    return meta


def _frame_name(index: int, frame: Any) -> str:
    """``frame 3 ('images/a.png')``, or ``frame 3`` when it has no file_path string."""
    file_path = frame.get("file_path") if isinstance(frame, dict) else None
    return f"frame {index} ('{file_path}')" if isinstance(file_path, str) else f"frame {index}"


def _non_finite(value: Any, path: str) -> tuple[str, float] | None:
    """The first (JSON path, value) below ``value`` that is a NaN or infinite number, or None."""
    if isinstance(value, float) and not math.isfinite(value):
        return path, value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found = _non_finite(item, f"{path}[{key!r}]" if isinstance(key, str) else f"{path}[{key}]")
        if found is not None:
            return found
    return None


def _check_finite(source: Path, meta: dict[str, Any]) -> None:
    """Every number of the file finite; the error names the key and, inside a frame, the frame."""
    for key, value in meta.items():
        if key == "frames":
            continue
        found = _non_finite(value, repr(key))
        if found is not None:
            raise TransformsFileError(f"{source}: {found[0]} is {found[1]}; every number must be finite")
    for index, frame in enumerate(meta["frames"]):
        found = _non_finite(frame, "")
        if found is not None:
            raise TransformsFileError(
                f"{source}: {_frame_name(index, frame)} holds {found[1]} at {found[0]}; every number must be finite"
            )


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_frame(source: Path, meta: dict[str, Any], index: int, frame: Any) -> None:
    """One frame: an object with a ``file_path`` string, a 3x4 or 4x4 ``transform_matrix`` of numbers, and every
    intrinsic the top level does not give."""
    name = _frame_name(index, frame)
    if not isinstance(frame, dict):
        raise TransformsFileError(f"{source}: {name} is a {type(frame).__name__}; {EXPECTED}")
    if not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
        raise TransformsFileError(f"{source}: {name} has no 'file_path' (the image's path, a string); {EXPECTED}")
    matrix = frame.get("transform_matrix")
    rows_ok = isinstance(matrix, list) and len(matrix) in (3, 4)
    if not rows_ok or not all(isinstance(row, list) and len(row) == 4 and all(map(_is_number, row)) for row in matrix):
        found = "no 'transform_matrix'" if matrix is None else f"the transform_matrix {json.dumps(matrix)[:120]}"
        raise TransformsFileError(
            f"{source}: {name} has {found}; expected the camera-to-world matrix as 4 rows of 4 numbers"
        )
    missing = [key for key in INTRINSICS_KEYS if key not in meta and key not in frame]
    if missing:
        raise TransformsFileError(
            f"{source}: {name} has no {', '.join(missing)}, and the file gives none at the top level; every frame "
            f"needs {', '.join(INTRINSICS_KEYS)} (at the top level or in the frame)"
        )
    for key in INTRINSICS_KEYS:
        value = frame.get(key, meta.get(key))
        where = "the top level" if key not in frame else name
        if not _is_number(value):
            raise TransformsFileError(f"{source}: {where} has {key} = {json.dumps(value)}; expected a number")


def _check_unique_images(source: Path, frames: list[dict[str, Any]]) -> None:
    """No image listed twice, by path or by file name (module docstring)."""
    by_path: dict[str, int] = {}
    by_name: dict[str, int] = {}
    for index, frame in enumerate(frames):
        path = os.path.normpath(frame["file_path"])
        name = Path(path).name
        if path in by_path:
            raise TransformsFileError(
                f"{source}: frames {by_path[path]} and {index} both list the image '{frame['file_path']}': one image "
                "under two poses is ambiguous; each image may appear in one frame only"
            )
        if name in by_name:
            first = frames[by_name[name]]["file_path"]
            raise TransformsFileError(
                f"{source}: frames {by_name[name]} ('{first}') and {index} ('{frame['file_path']}') list images of one "
                f"file name '{name}': images are named by their file name (the exported COLMAP model, the image "
                "tracks) and read as images_<k>/<file name> when downscaled, so file names must be unique"
            )
        by_path[path], by_name[name] = index, index


__all__ = ["INTRINSICS_KEYS", "TransformsFileError", "read_transforms"]
