"""What the format parsers (``colmap_scene``, ``transforms_scene``) share: the format and file ``--data`` holds, the
downscaled image folder, ``ParsedSplit``, the image size check with the intrinsics fitted to the images, and the camera
check.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from jaxtyping import Int
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
from s2camp_ns.data.camera_fields import replace_cameras
from s2camp_ns.data.image_check import decoded_sizes
from s2camp_ns.data.scene_config import SceneConfig

COLMAP_PATH_CANDIDATES = (Path("sparse/0"), Path("colmap/sparse/0"), Path("sparse"))
"""Where a COLMAP model is looked for when ``colmap_path`` is not given (mip-NeRF 360 first, then nerfstudio's)."""
AUTO_DOWNSCALE_FACTOR = 4
"""``downscale_factor=None`` uses ``images_4`` when it exists (the mip-NeRF 360 convention), else ``images``."""
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")


@dataclass(frozen=True)
class ParsedSplit:
    """What a format's parser knows of the split's images (image i is ``outputs.image_filenames[i]``); its fields go
    into ``outputs.metadata`` under their names (``metadata``)."""

    image_names: list[str]
    """Image i's name: in the COLMAP model (its path under the full-size image folder), or its file name."""
    full_image_size: Int[Tensor, "n 2"]
    """(width, height) of image i at full size (int64): its COLMAP camera's, or the transforms.json ``w`` x ``h``."""
    downscale_factor: int
    """The factor of the image folder read (``resolve_downscale``)."""
    colmap_model_path: Path | None = None
    """The COLMAP model read (resolved; COLMAP scenes only, None for a transforms.json)."""

    def metadata(self) -> dict:
        """The metadata entries (``colmap_model_path`` only where set)."""
        entries: dict = dict(image_names=self.image_names, downscale_factor=self.downscale_factor)
        if self.colmap_model_path is not None:
            entries["colmap_model_path"] = self.colmap_model_path
        entries["full_image_size"] = self.full_image_size
        return entries


def _find_colmap_model(data: Path, colmap_path: Path | None) -> tuple[Path | None, list[str]]:
    """First folder holding cameras.bin/txt, and the descriptions of everything looked at."""
    candidates = (colmap_path,) if colmap_path is not None else COLMAP_PATH_CANDIDATES
    looked_for = []
    for candidate in candidates:
        folder = data / candidate
        looked_for.append(f"{folder}/cameras.bin or cameras.txt (COLMAP model)")
        if (folder / "cameras.bin").exists() or (folder / "cameras.txt").exists():
            return folder, looked_for
    return None, looked_for


def detect_format(config: SceneConfig) -> tuple[Literal["colmap", "nerfstudio"], Path]:
    """The scene format and the path to read (COLMAP model folder or transforms json); FileNotFoundError if none."""
    data = Path(config.data)
    if not data.exists():
        raise FileNotFoundError(f"--data {data} does not exist")
    if data.is_file():
        if data.suffix != ".json":
            raise ValueError(f"--data {data} is a file but not a transforms .json file")
        return "nerfstudio", data
    looked_for: list[str] = []
    if config.data_format in ("auto", "colmap"):
        model, looked_for = _find_colmap_model(data, config.colmap_path)
        if model is not None:
            return "colmap", model
    if config.data_format in ("auto", "nerfstudio"):
        looked_for.append(f"{data / 'transforms.json'} (nerfstudio format)")
        if (data / "transforms.json").exists():
            return "nerfstudio", data / "transforms.json"
    raise FileNotFoundError(
        f"no scene found in --data {data} (data_format={config.data_format!r}); looked for:\n  - "
        + "\n  - ".join(looked_for)
    )


def _image_folders(data: Path, images_path: Path) -> list[str]:
    base = images_path.name
    return sorted(p.name for p in (data / images_path).parent.glob(f"{base}*") if p.is_dir())


def resolve_downscale(data: Path, images_path: Path, downscale_factor: int | None) -> int:
    """Downscale factor whose image folder exists (``None``: images_4 if present, else 1)."""
    folder = data / images_path
    if downscale_factor is None:
        return AUTO_DOWNSCALE_FACTOR if folder.with_name(f"{folder.name}_{AUTO_DOWNSCALE_FACTOR}").is_dir() else 1
    if isinstance(downscale_factor, bool) or not isinstance(downscale_factor, int) or downscale_factor < 1:
        raise ValueError(f"downscale_factor must be an integer in [1, inf) or None, got {downscale_factor!r}")
    chosen = folder if downscale_factor == 1 else folder.with_name(f"{folder.name}_{downscale_factor}")
    if not chosen.is_dir():
        raise FileNotFoundError(
            f"downscale_factor={downscale_factor} needs the image folder {chosen}, which does not exist; image "
            f"folders present: {_image_folders(data, images_path) or 'none'} (downscaled images are not generated "
            "here: make them first, or pick another downscale_factor)"
        )
    return downscale_factor


def list_images(folder: Path) -> list[Path]:
    """The image files (``IMAGE_SUFFIXES``) under ``folder``, at any depth."""
    return [p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]


def nerfstudio_parser_options(config: SceneConfig) -> dict:
    """The options S2CamP's config passes on to nerfstudio's COLMAP and transforms.json parsers."""
    return dict(
        scale_factor=config.scale_factor, scene_scale=config.scene_scale, orientation_method=config.orientation_method,
        center_method=config.center_method, auto_scale_poses=config.auto_scale_poses, eval_mode=config.eval_mode,
        train_split_fraction=config.train_split_fraction, eval_interval=config.eval_interval,
    )  # fmt: skip


def fit_intrinsics_to_images(
    cameras: Cameras, image_filenames: list[Path], declared: list[tuple[int, int, str]], k: int, listed_by: Path
) -> Cameras:
    """The cameras fitted to their decoded images (``image_check.decoded_sizes``, naming ``listed_by`` on failure).

    ``declared[i]``: (width, height, where declared) of image i at full size. The image read (``images_{k}``) must be
    that size / k within a pixel, else ValueError; each camera gets its image's size and its intrinsics (already / k)
    the true per-axis ratio, so that a rounded folder (3114 -> 779 px) does not shift the principal point.
    """
    fx, fy, cx, cy = (getattr(cameras, name).clone() for name in ("fx", "fy", "cx", "cy"))
    width, height = cameras.width.clone(), cameras.height.clone()
    sizes = decoded_sizes(image_filenames, listed_by)
    for i, path in enumerate(image_filenames):
        full_w, full_h, declared_by = declared[i]
        w, h = sizes[i]
        if abs(w - full_w / k) > 1.0 or abs(h - full_h / k) > 1.0:
            if k == 1:
                expected, advice = "", "correct the size there"
            else:
                expected = f", which at downscale_factor {k} gives {full_w / k:g}x{full_h / k:g}"
                advice = "pick the downscale_factor that matches the folder, or correct the size there"
            raise ValueError(
                f"image {path} is {w}x{h} but {declared_by} is {full_w}x{full_h}{expected}: every ray would go "
                f"through the wrong pixel; {advice}"
            )
        sx, sy = w / (full_w / k), h / (full_h / k)
        fx[i], cx[i], fy[i], cy[i] = fx[i] * sx, cx[i] * sx, fy[i] * sy, cy[i] * sy
        width[i], height[i] = w, h
    return replace_cameras(cameras, fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)


def check_supported_cameras(cameras: Cameras, source: Path) -> Intrinsics:
    """``cameras`` as ``Intrinsics`` if the camera optimizer can refine them, else ValueError naming ``source``."""
    try:
        return intrinsics_from_cameras(cameras)
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from error


__all__ = [
    "AUTO_DOWNSCALE_FACTOR",
    "COLMAP_PATH_CANDIDATES",
    "IMAGE_SUFFIXES",
    "ParsedSplit",
    "check_supported_cameras",
    "detect_format",
    "fit_intrinsics_to_images",
    "list_images",
    "nerfstudio_parser_options",
    "resolve_downscale",
]
