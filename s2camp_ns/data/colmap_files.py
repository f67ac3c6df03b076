"""COLMAP model files read strictly: a corrupt or truncated file is named, with the layout that was expected.

nerfstudio's readers (``colmap_parsing_utils``) trust their input (random bytes fail with a bare ``KeyError``). Here
any parse failure becomes a ``ColmapModelError`` naming the file and its layout, and a binary file's header count
must fit in the file and its records must account for every byte. Which file is read follows nerfstudio's
``ColmapDataParser`` (``model_file``).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Literal

from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils

Kind = Literal["cameras", "images", "points3D"]

BINARY_LAYOUT: dict[str, str] = {
    "cameras": (
        "a uint64 camera count, then per camera: int32 camera_id, int32 model_id (0-10), uint64 width, "
        "uint64 height, float64 params[number of the model's parameters]"
    ),
    "images": (
        "a uint64 image count, then per image: int32 image_id, float64 qvec[4], float64 tvec[3], int32 camera_id, "
        "a NUL-terminated UTF-8 name, uint64 num_points2D, then num_points2D x (float64 x, float64 y, "
        "int64 point3D_id)"
    ),
    "points3D": (
        "a uint64 point count, then per point: uint64 point3D_id, float64 xyz[3], uint8 rgb[3], float64 error, "
        "uint64 track_length, then track_length x (int32 image_id, int32 point2D_idx)"
    ),
}
TEXT_LAYOUT: dict[str, str] = {
    "cameras": "one line per camera: CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]",
    "images": (
        "two lines per image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then POINTS2D[] as (X, Y, POINT3D_ID)"
    ),
    "points3D": "one line per point: POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)",
}
MIN_RECORD_BYTES: dict[str, int] = {
    "cameras": 24 + 8 * min(model.num_params for model in colmap_utils.CAMERA_MODELS),
    "images": 64 + 1 + 8,  # fixed part, an empty name's NUL, the points2D count
    "points3D": 43 + 8,  # fixed part, the track length
}
"""Smallest possible size of one binary record, to check a header's count against the file size before reading."""
_RECORD = {"cameras": "camera", "images": "image", "points3D": "point"}

_PARSE_ERRORS = (struct.error, KeyError, IndexError, ValueError, TypeError, AssertionError, MemoryError, OverflowError)
"""What nerfstudio's readers raise on malformed input (UnicodeDecodeError is a ValueError)."""


class ColmapModelError(ValueError):
    """A COLMAP model file that cannot be read: corrupt, truncated or inconsistent."""


def model_file(recon_dir: Path, kind: Kind) -> Path:
    """The file of ``kind`` nerfstudio's ColmapDataParser reads from ``recon_dir`` (may not exist): ``cameras.txt``
    and ``images.txt`` when ``cameras.txt`` exists, else ``.bin``; ``points3D.bin`` before ``.txt``."""
    if kind == "points3D":
        binary = recon_dir / "points3D.bin"
        return binary if binary.exists() else recon_dir / "points3D.txt"
    suffix = ".txt" if (recon_dir / "cameras.txt").exists() else ".bin"
    return recon_dir / f"{kind}{suffix}"


def _expected(kind: Kind, path: Path) -> str:
    layout = BINARY_LAYOUT[kind] if path.suffix == ".bin" else TEXT_LAYOUT[kind]
    return f"expected a COLMAP {path.name} ({layout})"


def _describe(error: BaseException, kind: Kind, path: Path) -> str:
    if isinstance(error, struct.error):
        return f"the file ends inside a record ({error})"
    if isinstance(error, KeyError) and kind == "cameras" and path.suffix == ".bin":
        return f"unknown camera model id {error.args[0]}"
    if isinstance(error, UnicodeDecodeError):
        return f"an image name is not UTF-8 ({error.reason} at byte {error.start})"
    if isinstance(error, MemoryError | OverflowError):
        return "a record announces more data than the file can hold"
    return f"{type(error).__name__}: {error}"


def _record_count(path: Path, kind: Kind) -> int:
    """The header's record count, checked against the file size (so no reader tries to allocate a huge buffer)."""
    size = path.stat().st_size
    if size < 8:
        raise ColmapModelError(
            f"{path} is truncated: it holds {size} bytes, fewer than the 8-byte record count; {_expected(kind, path)}"
        )
    with open(path, "rb") as f:
        (count,) = struct.unpack("<Q", f.read(8))
    if count * MIN_RECORD_BYTES[kind] > size - 8:
        raise ColmapModelError(
            f"{path} is corrupt or truncated: its header announces {count} {_RECORD[kind]} records, which take at "
            f"least {count * MIN_RECORD_BYTES[kind]} bytes, but only {size - 8} bytes follow; {_expected(kind, path)}"
        )
    return count


def _binary_size(kind: Kind, records: dict) -> int:
    """Bytes that ``records`` take in the binary format (the header included)."""
    if kind == "cameras":
        return 8 + sum(24 + 8 * len(camera.params) for camera in records.values())
    if kind == "images":
        return 8 + sum(
            64 + len(image.name.encode("utf-8")) + 1 + 8 + 24 * len(image.point3D_ids) for image in records.values()
        )
    return 8 + sum(43 + 8 + 8 * len(point.image_ids) for point in records.values())


def _check_records(kind: Kind, path: Path, records: dict) -> None:
    """Values no valid model holds: parameter counts that do not match the model, non-finite numbers, an image name
    given to two images."""
    names: dict[str, int] = {}
    for record_id, record in records.items():
        if kind == "cameras":
            model = colmap_utils.CAMERA_MODEL_NAMES.get(record.model)
            if model is not None and len(record.params) != model.num_params:
                raise ColmapModelError(
                    f"{path}: camera {record_id} ({record.model}) has {len(record.params)} parameters, expected "
                    f"{model.num_params}"
                )
            values = [record.width, record.height, *record.params]
            if record.width <= 0 or record.height <= 0:
                raise ColmapModelError(
                    f"{path}: camera {record_id} has size {record.width}x{record.height}, expected positive sizes "
                    "(corrupt file?)"
                )
        elif kind == "images":
            values = [*record.qvec, *record.tvec]
            if record.name in names:
                raise ColmapModelError(
                    f"{path}: images {names[record.name]} and {record_id} are both named '{record.name}': one image "
                    "under two poses is ambiguous; image names must be unique"
                )
            names[record.name] = record_id
        else:
            values = list(record.xyz)
        if not all(math.isfinite(float(v)) for v in values):
            raise ColmapModelError(f"{path}: {kind} record {record_id} holds NaN or infinite values (corrupt file?)")


def read_model_file(path: Path, kind: Kind) -> dict:
    """Records of one COLMAP model file (``cameras``, ``images`` or ``points3D``, ``.bin`` or ``.txt``), by id.
    FileNotFoundError when missing, ``ColmapModelError`` when it cannot be parsed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"COLMAP model file {path} does not exist; {_expected(kind, path)}")
    binary = path.suffix == ".bin"
    readers: dict[str, tuple[Callable[[Path], dict], Callable[[Path], dict]]] = {
        "cameras": (colmap_utils.read_cameras_binary, colmap_utils.read_cameras_text),
        "images": (colmap_utils.read_images_binary, colmap_utils.read_images_text),
        "points3D": (colmap_utils.read_points3D_binary, colmap_utils.read_points3D_text),
    }
    read_binary, read_text = readers[kind]
    count = _record_count(path, kind) if binary else None
    try:
        records = read_binary(path) if binary else read_text(path)
    except _PARSE_ERRORS as error:
        raise ColmapModelError(
            f"{path} is corrupt or truncated: {_describe(error, kind, path)}; {_expected(kind, path)}"
        ) from error
    if binary:
        size, used = path.stat().st_size, _binary_size(kind, records)
        if len(records) != count or used != size:
            raise ColmapModelError(
                f"{path} is corrupt: its header announces {count} {_RECORD[kind]} records, which take {used} bytes, "
                f"but the file holds {size} bytes ({len(records)} distinct ids); {_expected(kind, path)}"
            )
    _check_records(kind, path, records)
    return records


__all__ = ["BINARY_LAYOUT", "ColmapModelError", "TEXT_LAYOUT", "model_file", "read_model_file"]
