"""Data parser for S2CamP: mip-NeRF 360 COLMAP scenes or nerfstudio transforms.json, optional CamP perturbation.

``--data`` may point at

- a mip-NeRF 360 style scene: ``images/``, ``images_2/``, ``images_4/``, ... and ``sparse/0/`` (or nerfstudio's own
  ``colmap/sparse/0``), read through nerfstudio's ``ColmapDataParser``;
- a nerfstudio scene: ``transforms.json`` (or the json file itself), read through nerfstudio's parser.

Downscaled images are taken from the pre-made ``images_{k}`` folder; nothing is regenerated (nerfstudio would ask
on the terminal and exit). Intrinsics are rescaled to the actual size of those images: mip-NeRF 360's
``images_4`` round the sizes (3114 -> 779) where nerfstudio floors them (778), which would shift the principal
point by half a pixel.

Before training, the scene is validated (corrupt or truncated model files, images listed by the model but missing
on disk, images whose size is not the one the COLMAP camera or the transforms.json ``w``/``h`` declare, unsupported
camera models, empty scenes) with errors that name the file and what was expected. Both formats get the same image
size check and intrinsics fit (``_fit_intrinsics_to_images``), against the images the parser actually uses.

Camera models: COLMAP SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV (k4 = k5 = k6 = 0) and
OPENCV_FISHEYE; transforms.json with camera_model OPENCV or OPENCV_FISHEYE (what ``ns-process-data`` writes).
COLMAP parameters map explicitly to nerfstudio's distortion_params [k1, k2, k3, k4, p1, p2]
(``core.colmap_models``): nerfstudio's own COLMAP reader refuses FULL_OPENCV and any nonzero k4, including the
OPENCV_FISHEYE k4 it does represent, so this parser fills the distortion in itself.

The CamP perturbation (off by default; ``ns-train s2camp --data D s2camp-data --perturbation.enabled True``) is applied
to the training cameras after nerfstudio's orientation and scale normalization, so its sigmas are in normalized
scene units (the cameras fit in [-1, 1]^3), as CamP applies them in its own normalized scene. The unperturbed
cameras of the split are kept in ``metadata["reference_cameras"]``; evaluation cameras are never perturbed. The
scene's own tracks, made with the unperturbed cameras, would tell the track prior where the reference is: perturbed
cameras get tracks made from the images with the perturbed cameras instead, or no prior.
With ``--reference-model`` (a COLMAP model of the true cameras, e.g. a rendered scene's when the input is an SfM
reconstruction of it), the reference cameras are the true ones instead, similarity-aligned into the input's frame.
"""

from __future__ import annotations

import copy
import json
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers import colmap_dataparser
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.data.utils.colmap_parsing_utils import qvec2rotmat
from PIL import Image
from rich.console import Console
from rich.markup import escape

from s2camp_ns.camera_optimizer import (
    SUPPORTED_CAMERA_TYPES,
    camera_model_of,
    group_identical_intrinsics,
    intrinsics_from_cameras,
    projection_of,
)
from s2camp_ns.core.camera import CAMERA_MODEL_PROJECTION, Intrinsics, opengl_to_opencv
from s2camp_ns.core.colmap_models import SUPPORTED_COLMAP_MODELS, colmap_to_values
from s2camp_ns.core.perturbation import PerturbationConfig, perturb_cameras
from s2camp_ns.core.track_fit import TrackEvidence
from s2camp_ns.core.tracks import track_reprojection_rms
from s2camp_ns.core.validation import check_range
from s2camp_ns.nerfstudio.colmap_model import ColmapModelError, model_file, read_model_file
from s2camp_ns.nerfstudio.colmap_tracks import check_sfm_track_rms, read_colmap_tracks
from s2camp_ns.nerfstudio.colmap_world import c2w_to_colmap_world, colmap_world_to_c2w
from s2camp_ns.nerfstudio.export_cameras import export_cameras
from s2camp_ns.nerfstudio.image_tracks import image_tracks
from s2camp_ns.nerfstudio.transforms_tracks import colmap_model_of_transforms, full_size_images, transforms_track_rms

NERFSTUDIO_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
"""nerfstudio's distortion_params order."""

COLMAP_PATH_CANDIDATES = (Path("sparse/0"), Path("colmap/sparse/0"), Path("sparse"))
"""Where a COLMAP model is looked for when ``colmap_path`` is not given (mip-NeRF 360 first, then nerfstudio's)."""

AUTO_DOWNSCALE_FACTOR = 4
"""``downscale_factor=None`` uses ``images_4`` when it exists (the mip-NeRF 360 convention), else ``images``."""

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")


@dataclass
class S2CampDataParserConfig(DataParserConfig):
    """S2CamP data parser: mip-NeRF 360 / COLMAP or transforms.json scenes, optional CamP camera perturbation."""

    _target: type = field(default_factory=lambda: S2CampDataParser)
    """Target class to instantiate."""
    data: Path = Path()
    """Scene folder (mip-NeRF 360 layout or transforms.json), or a transforms json file."""
    data_format: Literal["auto", "colmap", "nerfstudio"] = "auto"
    """Scene format; auto detects a COLMAP model (sparse/0) first, then transforms.json."""
    downscale_factor: int | None = None
    """Use the pre-downscaled images_{k} folder; None picks images_4 when present, else the full-size images."""
    colmap_path: Path | None = None
    """COLMAP model folder relative to data; None tries sparse/0, colmap/sparse/0, sparse. For a transforms.json
    scene, the model of its tracks, relative to the json's folder (None: colmap/sparse/0)."""
    images_path: Path = Path("images")
    """Full-size image folder relative to data (the downscaled ones are its siblings with suffix _k)."""
    scale_factor: float = 1.0
    """Extra scale applied to the camera centres after the automatic scaling."""
    scene_scale: float = 1.0
    """Half side of the scene box."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    """Orientation normalization of nerfstudio."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """Centring normalization of nerfstudio."""
    auto_scale_poses: bool = True
    """Scale the camera centres into [-1, 1]^3 (the perturbation sigmas are in these units)."""
    eval_mode: Literal["fraction", "filename", "interval", "all"] = "interval"
    """Train / eval split; interval takes every eval_interval-th image for eval (the mip-NeRF 360 protocol)."""
    train_split_fraction: float = 0.9
    """Fraction of the images used for training with eval_mode fraction."""
    eval_interval: int = 8
    """Every eval_interval-th image is held out with eval_mode interval."""
    load_3D_points: bool = True
    """Load the COLMAP sparse points into metadata (needed by point-initialized models; cheap)."""
    tracks: bool = True
    """Measure each training camera's reprojection error against the COLMAP model's tracks, as the cameras are given
    (after any perturbation): ``metadata["track_rms_px"]`` (``core.tracks``), and the tracks with those cameras in
    the model's world, ``metadata["track_evidence"]``, from which the camera optimizer's track prior takes its anchor
    and scale (``core.track_fit``). COLMAP scenes with points, and transforms.json scenes with the model
    ns-process-data leaves beside them (``colmap/sparse/0``, cameras checked against it, ``transforms_tracks``);
    images the model does not hold get NaN. Scenes without them get tracks made from their images (``image_tracks``).
    With the perturbation on, the scene's own tracks (made with the unperturbed cameras) are never used: the
    perturbed cameras get tracks made from the images (``image_tracks`` auto or always) or none (never), and the log
    says which. False measures nothing (no prior)."""
    image_tracks: Literal["auto", "always", "never"] = "auto"
    """Tracks made from the scene's own images for the track prior (``nerfstudio/image_tracks.py``: SIFT matches,
    points triangulated with the given training cameras, bundle-adjusted with them and aligned to them by a
    similarity; built once, on the CPU, and cached). auto: where the scene has no SfM tracks (phone exports, hand-made
    or converted transforms.json files); always: in place of the scene's own tracks; never: only the scene's tracks.
    Without tracks the photometric loss leaves the focal length and forward motion barely determined
    (docs/DESIGN-NOTES.md sec. 15)."""
    image_tracks_cache: Path | None = None
    """Folder of the image tracks' cache (read and written; an error when a build is needed and it cannot be
    written); None: ``s2camp_image_tracks`` in the scene folder (beside the transforms.json), read where it exists,
    and where the scene folder cannot be written new entries go to ``$XDG_CACHE_HOME/s2camp-ns/image_tracks``
    (``~/.cache/...``; ``nerfstudio/track_cache.py``)."""
    perturbation: PerturbationConfig = field(default_factory=PerturbationConfig)
    """CamP perturbation of the training cameras (evaluation protocol, off by default)."""
    reference_model: Path | None = None
    """COLMAP model of the true cameras (images matched by name, COLMAP scenes only): the reference cameras of the
    camera errors, the viewer's reference frusta and the held-out views come from it instead of the input cameras,
    similarity-aligned into the input's frame (``reference_from_model``)."""


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


def detect_format(config: S2CampDataParserConfig) -> tuple[Literal["colmap", "nerfstudio"], Path]:
    """Return the scene format and the path to read (COLMAP model folder or transforms json)."""
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


def _list_images(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]


def validate_colmap_cameras(recon_dir: Path) -> dict[int, str]:
    """Check every COLMAP camera uses a supported model; return camera id -> model name.

    Reads the file nerfstudio's parser reads (``cameras.txt`` first, as it does); a corrupt or truncated file raises
    ``ColmapModelError`` naming it (see ``colmap_model``).
    """
    path = model_file(recon_dir, "cameras")
    cameras = read_model_file(path, "cameras")
    if not cameras:
        raise ValueError(f"COLMAP model {path} holds no cameras: the scene is empty")
    models = {}
    for camera_id, camera in sorted(cameras.items()):
        if camera.model not in SUPPORTED_COLMAP_MODELS:
            raise ValueError(
                f"{path}: camera {camera_id} uses the COLMAP camera model {camera.model}, which is not supported; "
                f"supported: {', '.join(SUPPORTED_COLMAP_MODELS)} (FULL_OPENCV with k4 = k5 = k6 = 0)"
            )
        try:
            colmap_to_values(camera.model, camera.params)
        except ValueError as error:
            raise ValueError(f"{path}: camera {camera_id}: {error}") from error
        models[camera_id] = camera.model
    if len(set(models.values())) > 1:
        raise ValueError(f"{path}: cameras use several models {sorted(set(models.values()))}; use one model")
    return models


def nerfstudio_frame_intrinsics(camera) -> dict:
    """Per-frame intrinsics in the keys of nerfstudio's COLMAP reader, mapped explicitly (``core.colmap_models``).

    k4 is left out on purpose: nerfstudio's reader refuses any nonzero k4 (even OPENCV_FISHEYE's, which its fisheye
    renderer does use); ``distortion_of`` supplies all six coefficients afterwards.
    """
    values = colmap_to_values(camera.model, camera.params)
    fisheye = CAMERA_MODEL_PROJECTION[camera.model] == "fisheye"
    frame = {"w": camera.width, "h": camera.height, "camera_model": "OPENCV_FISHEYE" if fisheye else "OPENCV"}
    frame.update(fl_x=values["fx"], fl_y=values["fy"], cx=values["cx"], cy=values["cy"])
    frame.update({name: values[name] for name in NERFSTUDIO_DISTORTION if name != "k4"})
    return frame


def distortion_of(camera) -> list[float]:
    """nerfstudio's distortion_params [k1, k2, k3, k4, p1, p2] of a COLMAP camera (the same coefficients in COLMAP's
    meaning: OpenCV's radial-tangential k1, k2, k3, p1, p2, or OPENCV_FISHEYE's k1..k4)."""
    values = colmap_to_values(camera.model, camera.params)
    return [values[name] for name in NERFSTUDIO_DISTORTION]


@contextmanager
def _explicit_camera_mapping():
    """Let nerfstudio's COLMAP reader use ``nerfstudio_frame_intrinsics`` for the per-camera step (its own raises
    NotImplementedError for FULL_OPENCV); restored on exit."""
    original = colmap_dataparser.parse_colmap_camera_params
    colmap_dataparser.parse_colmap_camera_params = nerfstudio_frame_intrinsics
    try:
        yield
    finally:
        colmap_dataparser.parse_colmap_camera_params = original


class _ValidatingColmapDataParser(ColmapDataParser):
    """nerfstudio's COLMAP parser plus file checks; remembers the full-size image sizes for the intrinsics fix and
    each image's distortion (``distortion_of``)."""

    def __init__(self, config: ColmapDataParserConfig, image_folder: Path):
        super().__init__(config)
        self.image_folder = image_folder
        self.full_sizes: dict[str, tuple[int, int]] = {}
        self.distortion: dict[str, list[float]] = {}
        self.size_source: dict[str, str] = {}
        """Image name -> the COLMAP camera that declares its size (for errors)."""

    def _get_all_images_and_cameras(self, recon_dir: Path):
        camera_models = validate_colmap_cameras(recon_dir)
        images_file = model_file(recon_dir, "images")
        if not images_file.exists():
            raise FileNotFoundError(
                f"COLMAP model {recon_dir} has {model_file(recon_dir, 'cameras').name} but no {images_file.name}"
            )
        # Read strictly first, so that a corrupt file is named before nerfstudio's reader trips over it.
        cameras = read_model_file(model_file(recon_dir, "cameras"), "cameras")
        images = read_model_file(images_file, "images")
        for image_id, image in images.items():
            if image.camera_id not in camera_models:
                raise ColmapModelError(
                    f"{images_file}: image {image_id} ('{image.name}') refers to camera {image.camera_id}, which "
                    f"{model_file(recon_dir, 'cameras').name} does not hold (cameras: {sorted(camera_models)})"
                )
        self.distortion = {image.name: distortion_of(cameras[image.camera_id]) for image in images.values()}
        cameras_file = model_file(recon_dir, "cameras")
        self.size_source = {
            image.name: f"its COLMAP camera {image.camera_id} in {cameras_file}" for image in images.values()
        }
        try:
            with _explicit_camera_mapping():
                out = super()._get_all_images_and_cameras(recon_dir)
        except AssertionError as error:
            if "No images" in str(error):
                raise ValueError(f"COLMAP model {images_file} lists no images: the scene is empty") from error
            raise
        on_disk = _list_images(self.image_folder) if self.image_folder.is_dir() else []
        if not on_disk:
            raise ValueError(
                f"the scene is empty: image folder {self.image_folder} holds no images "
                f"({', '.join(IMAGE_SUFFIXES)}) but {images_file} lists {len(out['frames'])}"
            )
        full_folder = self.config.data / self.config.images_path
        missing = []
        for frame in out["frames"]:
            name = Path(frame["file_path"]).relative_to(full_folder).as_posix()
            self.full_sizes[name] = (int(frame["w"]), int(frame["h"]))
            if not (self.image_folder / name).is_file():
                missing.append(name)
        if missing:
            raise FileNotFoundError(
                f"{images_file} lists image '{missing[0]}' but {self.image_folder / missing[0]} does not exist "
                f"({len(missing)} of {len(out['frames'])} listed images missing from {self.image_folder})"
            )
        return out

    def _load_3D_points(self, colmap_path: Path, transform_matrix: torch.Tensor, scale_factor: float):
        # Read strictly first: a corrupt file is named before nerfstudio's reader trips over it.
        read_model_file(model_file(colmap_path, "points3D"), "points3D")
        return super()._load_3D_points(colmap_path, transform_matrix, scale_factor)


def replace_cameras(cameras: Cameras, **fields) -> Cameras:
    """A copy of ``cameras`` with the given fields replaced (nerfstudio's Cameras has no such method)."""
    values = dict(
        camera_to_worlds=cameras.camera_to_worlds,
        fx=cameras.fx,
        fy=cameras.fy,
        cx=cameras.cx,
        cy=cameras.cy,
        width=cameras.width,
        height=cameras.height,
        distortion_params=cameras.distortion_params,
        camera_type=cameras.camera_type,
        times=cameras.times,
        metadata=cameras.metadata,
    )
    values.update(fields)
    return Cameras(**values)


def _fit_intrinsics_to_images(
    cameras: Cameras, image_filenames: list[Path], declared: list[tuple[int, int, str]], k: int
) -> Cameras:
    """Check each image's size against the size its scene file declares and fit the cameras to the images.

    ``declared[i]`` = (width, height, where it is declared) of image i at full size (the COLMAP camera's or the
    transforms.json ``w``/``h``). The image, read from the folder the parser uses (``images_{k}`` at downscale factor
    k), must be that size divided by k within a pixel (rounding of the downscaled folder); otherwise a ValueError
    names the image, the declaring file and both sizes: with a wrong size every ray would go through the wrong pixel.
    Each camera then gets its image's size, and its intrinsics (already divided by k) the true per-axis resize
    ratio, so that a rounded folder (mip-NeRF 360's 3114 -> 779) does not shift the principal point. Only image
    headers are read (PIL's ``Image.open`` decodes no pixels).
    """
    fx, fy, cx, cy = (getattr(cameras, name).clone() for name in ("fx", "fy", "cx", "cy"))
    width, height = cameras.width.clone(), cameras.height.clone()
    for i, path in enumerate(image_filenames):
        full_w, full_h, declared_by = declared[i]
        with Image.open(path) as image:
            w, h = image.size
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
        # nerfstudio already divided the intrinsics by k; correct for the rounding of the stored image size.
        sx, sy = w / (full_w / k), h / (full_h / k)
        fx[i], cx[i], fy[i], cy[i] = fx[i] * sx, cx[i] * sx, fy[i] * sy, cy[i] * sy
        width[i], height[i] = w, h
    return replace_cameras(cameras, fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)


def transforms_declared_sizes(source: Path, k: int) -> dict[str, tuple[int, int]]:
    """Full-size (w, h) of every frame of a transforms.json, keyed by the image path nerfstudio's parser reads at
    downscale factor k (``images_{k}/<name>`` beside the json for k > 1); the top-level ``w``/``h`` win over a
    frame's, as in nerfstudio's parser."""
    with open(source, encoding="utf8") as f:
        meta = json.load(f)
    data_dir = source.parent
    sizes = {}
    for frame in meta.get("frames", []):
        file_path = Path(frame["file_path"])
        path = data_dir / file_path if k == 1 else data_dir / f"images_{k}" / file_path.name
        w, h = meta["w"] if "w" in meta else frame["w"], meta["h"] if "h" in meta else frame["h"]
        sizes[os.path.normpath(path)] = (int(w), int(h))
    return sizes


def perturb_nerfstudio_cameras(cameras: Cameras, config: PerturbationConfig) -> Cameras:
    """Apply the CamP perturbation to nerfstudio (OpenGL) cameras; zero their distortion if configured.

    Perspective and fisheye cameras: the protocol draws poses and focal lengths only, which both projections share
    (a fisheye's focal scales its image-space angle as a pinhole's scales its tangent); zeroed distortion leaves a
    fisheye equidistant.
    """
    unsupported = sorted({int(t) for t in cameras.camera_type.reshape(-1).tolist()} - set(SUPPORTED_CAMERA_TYPES))
    if unsupported:
        names = ", ".join(CameraType(t).name for t in unsupported)
        raise ValueError(f"the camera perturbation supports PERSPECTIVE and FISHEYE cameras, got {names}")
    c2w = opengl_to_opencv(cameras.camera_to_worlds.double())
    out = perturb_cameras(c2w, cameras.fx[:, 0].double(), cameras.fy[:, 0].double(), config)
    dtype = cameras.camera_to_worlds.dtype
    distortion = cameras.distortion_params
    if config.zero_distortion and distortion is not None:
        distortion = torch.zeros_like(distortion)
    return replace_cameras(
        cameras,
        camera_to_worlds=opengl_to_opencv(out.c2w).to(dtype),
        fx=out.fx[:, None].to(cameras.fx.dtype),
        fy=out.fy[:, None].to(cameras.fy.dtype),
        distortion_params=distortion,
    )


def check_supported_cameras(cameras: Cameras, source: Path) -> Intrinsics:
    """Cameras the S2CamP camera optimizer can refine (its ``intrinsics_from_cameras`` mapping and validation:
    perspective or fisheye, distortion one-to-one over the image), as ``Intrinsics``; names the source file
    otherwise."""
    try:
        return intrinsics_from_cameras(cameras)
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from error


@dataclass
class S2CampDataParser(DataParser):
    """See the module docstring."""

    config: S2CampDataParserConfig

    def __init__(self, config: S2CampDataParserConfig):
        super().__init__(config=config)
        self.config = config

    def _validate_config(self) -> None:
        config = self.config
        check_range("scale_factor", config.scale_factor, low=0.0, low_inclusive=False)
        check_range("scene_scale", config.scene_scale, low=0.0, low_inclusive=False)
        check_range("train_split_fraction", config.train_split_fraction, low=0.0, high=1.0)
        if (
            isinstance(config.eval_interval, bool)
            or not isinstance(config.eval_interval, int)
            or config.eval_interval < 1
        ):
            raise ValueError(f"eval_interval must be an integer in [1, inf), got {config.eval_interval!r}")
        config.perturbation.validate()

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        self._validate_config()
        data_format, source = detect_format(self.config)
        data = Path(self.config.data)
        if data_format == "colmap":
            outputs, extra = self._parse_colmap(data, source, split)
        else:
            outputs, extra = self._parse_transforms(source, split)
        intrinsics = check_supported_cameras(outputs.cameras, source)

        reference = copy.deepcopy(outputs.cameras)
        if self.config.reference_model is not None:
            reference = self._reference_from_model(data_format, source, outputs, extra)
        cameras = outputs.cameras
        perturbed = split == "train" and self.config.perturbation.enabled
        if perturbed:
            cameras = perturb_nerfstudio_cameras(cameras, self.config.perturbation)
        metadata = dict(outputs.metadata)
        metadata.update(extra)
        # The scene's own tracks were made with the unperturbed cameras: a prior on them would lead the perturbed
        # cameras back to the reference the evaluation compares with. Perturbed cameras get tracks made from the
        # images with the perturbed cameras instead (image_tracks auto or always), or no prior (never).
        scene_tracks = self.config.tracks and self.config.image_tracks != "always" and not perturbed
        if perturbed and self.config.tracks:
            self._note_perturbed_tracks(source)
        if data_format == "colmap" and scene_tracks and self.config.load_3D_points and self._has_points(source):
            rms, evidence = colmap_track_evidence(cameras, source, extra["image_names"], outputs)
            metadata.update(track_rms_px=rms, track_evidence=evidence)
            model = source
        elif data_format == "nerfstudio" and scene_tracks:
            result = self._transforms_track_rms(source, cameras, outputs, extra)
            if result is not None:
                metadata["track_rms_px"], metadata["track_evidence"] = result
            model = colmap_model_of_transforms(source, self.config.colmap_path)
        if "track_rms_px" in metadata:  # the scene's own tracks under its given cameras
            fallback = "pass s2camp-data --image-tracks always (tracks made from the images) or --tracks False"
            model_width = extra["full_image_size"][:, 0]
            check_sfm_track_rms(
                metadata["track_rms_px"], cameras.width, model_width, model_file(model, "images"), fallback
            )
        made = self.config.tracks and self.config.image_tracks != "never" and "track_evidence" not in metadata
        if made and split == "train":  # only the training cameras are refined
            result = self._image_track_evidence(data_format, source, cameras, outputs, extra)
            if result is not None:
                metadata["track_rms_px"], metadata["track_evidence"] = result
        metadata.update(
            reference_cameras=reference,
            # One id per physical camera: images whose given intrinsics agree (COLMAP's camera_id in practice; the
            # global intrinsics of a transforms.json), grouped before any perturbation.
            camera_ids=group_identical_intrinsics(reference).tolist(),
            # The COLMAP model whose distortion the camera optimizer's "all" preset refines (sizes its latent before
            # DDP wraps the model and before the optimizers are built).
            camera_model=camera_model_of(intrinsics),
            dataparser_scale=float(outputs.dataparser_scale),
            dataparser_transform=outputs.dataparser_transform.clone(),
            perturbed=perturbed,
            source_format=data_format,
            source_path=source.resolve(),
        )
        return DataparserOutputs(
            image_filenames=outputs.image_filenames,
            cameras=cameras,
            alpha_color=outputs.alpha_color,
            scene_box=outputs.scene_box,
            mask_filenames=outputs.mask_filenames,
            dataparser_transform=outputs.dataparser_transform,
            dataparser_scale=outputs.dataparser_scale,
            metadata=metadata,
        )

    def _note_perturbed_tracks(self, source: Path) -> None:
        """Say, once, which evidence the perturbed cameras' track prior gets (``_generate_dataparser_outputs``)."""
        if self.config.image_tracks == "never":
            evidence = "no track prior (image_tracks never)"
        else:
            evidence = "tracks made from the images with the perturbed cameras (image_tracks)"
        _show_once(
            (source.resolve(), "perturbed-tracks"),
            f"[bold yellow]Perturbed cameras: the scene's own tracks were made with the unperturbed cameras and are "
            f"not used; the track prior gets {evidence}",
        )

    def _reference_from_model(self, data_format: str, source: Path, outputs: DataparserOutputs, extra: dict) -> Cameras:
        if data_format != "colmap":
            raise ValueError(
                f"reference_model {self.config.reference_model} needs a COLMAP scene (images matched by name), but "
                f"--data {self.config.data} is a {data_format} scene ({source})"
            )
        return reference_from_model(
            self.config.reference_model,
            source,
            extra["image_names"],
            outputs.cameras,
            outputs.dataparser_transform,
            float(outputs.dataparser_scale),
        )

    def _common_kwargs(self) -> dict:
        c = self.config
        return dict(
            scale_factor=c.scale_factor,
            scene_scale=c.scene_scale,
            orientation_method=c.orientation_method,
            center_method=c.center_method,
            auto_scale_poses=c.auto_scale_poses,
            eval_mode=c.eval_mode,
            train_split_fraction=c.train_split_fraction,
            eval_interval=c.eval_interval,
        )

    def _parse_colmap(self, data: Path, model: Path, split: str) -> tuple[DataparserOutputs, dict]:
        k = resolve_downscale(data, self.config.images_path, self.config.downscale_factor)
        full_folder = data / self.config.images_path
        image_folder = full_folder if k == 1 else full_folder.with_name(f"{full_folder.name}_{k}")
        colmap_config = ColmapDataParserConfig(
            data=data,
            colmap_path=model.relative_to(data),
            images_path=self.config.images_path,
            downscale_factor=k,
            load_3D_points=self.config.load_3D_points and self._has_points(model),
            **self._common_kwargs(),
        )
        parser = _ValidatingColmapDataParser(colmap_config, image_folder)
        outputs = parser.get_dataparser_outputs(split=split)
        if not outputs.image_filenames:
            raise ValueError(f"the {split} split of {model} is empty (eval_mode={self.config.eval_mode!r})")
        full_names = [Path(p).relative_to(image_folder).as_posix() for p in outputs.image_filenames]
        declared = [(*parser.full_sizes[name], parser.size_source[name]) for name in full_names]
        cameras = _fit_intrinsics_to_images(outputs.cameras, outputs.image_filenames, declared, k)
        distortion = torch.tensor([parser.distortion[name] for name in full_names], dtype=torch.float32)
        cameras = replace_cameras(cameras, distortion_params=distortion)
        outputs = DataparserOutputs(
            image_filenames=outputs.image_filenames,
            cameras=cameras,
            scene_box=outputs.scene_box,
            dataparser_transform=outputs.dataparser_transform,
            dataparser_scale=outputs.dataparser_scale,
            metadata=outputs.metadata,
        )
        names = [Path(p).relative_to(image_folder).as_posix() for p in outputs.image_filenames]
        full_size = torch.tensor([parser.full_sizes[name] for name in names], dtype=torch.int64)
        return outputs, dict(
            image_names=names, downscale_factor=k, colmap_model_path=model.resolve(), full_image_size=full_size
        )

    @staticmethod
    def _has_points(model: Path) -> bool:
        return (model / "points3D.bin").exists() or (model / "points3D.txt").exists()

    def _parse_transforms(self, source: Path, split: str) -> tuple[DataparserOutputs, dict]:
        data_dir = source.parent
        k = resolve_downscale(data_dir, self.config.images_path, self.config.downscale_factor)
        ns_config = NerfstudioDataParserConfig(
            data=source, downscale_factor=k, load_3D_points=False, **self._common_kwargs()
        )
        try:
            outputs = Nerfstudio(ns_config).get_dataparser_outputs(split=split)
        except (AssertionError, IndexError, ValueError, StopIteration) as error:
            frames = self._transforms_frames(source)
            if not frames:
                raise ValueError(f"{source} lists no frames: the scene is empty") from error
            raise
        missing = [p for p in outputs.image_filenames if not Path(p).is_file()]
        if missing:
            raise FileNotFoundError(
                f"{source} lists image '{missing[0]}', which does not exist ({len(missing)} of "
                f"{len(outputs.image_filenames)} {split} images missing)"
            )
        sizes = transforms_declared_sizes(source, k)
        declared = [(*sizes[os.path.normpath(p)], f"the w x h in {source}") for p in outputs.image_filenames]
        cameras = _fit_intrinsics_to_images(outputs.cameras, outputs.image_filenames, declared, k)
        outputs = DataparserOutputs(
            image_filenames=outputs.image_filenames,
            cameras=cameras,
            alpha_color=outputs.alpha_color,
            scene_box=outputs.scene_box,
            mask_filenames=outputs.mask_filenames,
            dataparser_transform=outputs.dataparser_transform,
            dataparser_scale=outputs.dataparser_scale,
            metadata=outputs.metadata,
        )
        # The frames' declared full size (the transforms.json's w x h): the export's "original" resolution.
        full_size = torch.tensor([declared_size[:2] for declared_size in declared], dtype=torch.int64)
        names = [Path(p).name for p in outputs.image_filenames]
        return outputs, dict(image_names=names, downscale_factor=k, full_image_size=full_size)

    def _transforms_track_rms(
        self, source: Path, cameras: Cameras, outputs: DataparserOutputs, extra: dict
    ) -> tuple[torch.Tensor, TrackEvidence] | None:
        """``track_rms_px`` and ``track_evidence`` of a transforms.json scene from the COLMAP model ns-process-data
        left beside it (``transforms_tracks``); None, with the reason shown once, when there are none."""
        model = colmap_model_of_transforms(source, self.config.colmap_path)
        k = extra["downscale_factor"]
        sizes = transforms_declared_sizes(source, k)
        scale = float(outputs.dataparser_scale)
        result = transforms_track_rms(
            source,
            model,
            outputs.image_filenames,
            [sizes[os.path.normpath(p)] for p in outputs.image_filenames],
            k,
            self.config.images_path,
            c2w_given=c2w_to_colmap_world(cameras.camera_to_worlds, outputs.dataparser_transform, scale),
            c2w_reference=c2w_to_colmap_world(outputs.cameras.camera_to_worlds, outputs.dataparser_transform, scale),
            intrinsics=intrinsics_from_cameras(cameras),
            world_scale=scale,
        )
        if result.rms is None or result.evidence is None:
            # A transforms.json that disagrees with its COLMAP model is a warning; a scene without one is normal.
            style = "bold yellow" if result.cause == "disagree" else "dim"
            _show_once((source.resolve(), result.cause), f"[{style}]No SfM tracks: {escape(result.reason)}")
            return None
        return result.rms, result.evidence

    def _image_track_evidence(
        self, data_format: str, source: Path, cameras: Cameras, outputs: DataparserOutputs, extra: dict
    ) -> tuple[torch.Tensor, TrackEvidence] | None:
        """``track_rms_px`` and ``track_evidence`` from tracks made from the scene's full-size images with the given
        ``cameras`` (``image_tracks``); None, with the reason shown once, when none could be made."""
        full_size = extra["full_image_size"]
        if data_format == "colmap":
            scene = Path(self.config.data)
            root, names = scene / self.config.images_path, extra["image_names"]
        else:
            scene = source.parent
            paths = full_size_images(source, outputs.image_filenames, extra["downscale_factor"])
            root = Path(os.path.commonpath([path.parent for path in paths]))
            names = [path.relative_to(root).as_posix() for path in paths]
        scale = float(outputs.dataparser_scale)
        given = export_cameras(
            cameras, outputs.dataparser_transform, scale, names, full_image_size=full_size,
            camera_ids=group_identical_intrinsics(cameras).tolist(),
        )  # fmt: skip
        cache = self.config.image_tracks_cache or scene / IMAGE_TRACKS_CACHE  # minutes for many large images, once
        result = image_tracks(given, root, cache, user_fallback=self.config.image_tracks_cache is None)
        if result.model is None:
            _show_once((source.resolve(), "image-tracks"), f"[bold yellow]No track prior: {escape(result.reason)}")
            return None
        _show_once(
            (result.model, "summary"),
            f"[dim]Track prior from tracks made from the images of {root} ({result.model}): {escape(result.summary)}",
        )
        return colmap_track_evidence(cameras, result.model, names, outputs)

    @staticmethod
    def _transforms_frames(source: Path) -> list:
        with open(source, encoding="utf8") as f:
            return list(json.load(f).get("frames", []))


IMAGE_TRACKS_CACHE = Path("s2camp_image_tracks")
"""The image tracks' cache folder in the scene folder (``image_tracks_cache`` None; the user's cache folder where the
scene folder cannot be written, ``track_cache.user_cache_folder``)."""
LOG = Console(stderr=True, width=120)
"""Notes of the data parser (why a scene has no track prior): on stderr, as the camera optimizer's."""
_SHOWN: set[tuple] = set()
"""Keys of the notes already shown: the data parser runs once per split, and once is enough."""


def _show_once(key: tuple, message: str) -> None:
    if key not in _SHOWN:
        _SHOWN.add(key)
        LOG.print(message)


def colmap_track_evidence(
    cameras: Cameras, model: Path, names: list[str], outputs: DataparserOutputs
) -> tuple[torch.Tensor, TrackEvidence]:
    """Reprojection RMS (px, float64 [N]) of the COLMAP model's tracks under ``cameras`` (normalized, as the data parser
    returns them; image i is the model's image ``names[i]``), measured in COLMAP's world frame (``core.tracks``), and
    the tracks with the cameras in that world (the track prior's anchor, ``core.track_fit``)."""
    # Keypoints from the model's camera size to the training images' (a rounded images_k folder included).
    size = torch.stack([cameras.width.reshape(-1), cameras.height.reshape(-1)], dim=-1)
    tracks = read_colmap_tracks(model, names, image_size=size)
    scale = float(outputs.dataparser_scale)
    c2w = c2w_to_colmap_world(cameras.camera_to_worlds, outputs.dataparser_transform, scale)
    rms = track_reprojection_rms(tracks, c2w, intrinsics_from_cameras(cameras))
    return rms, TrackEvidence(tracks, c2w, scale)


def _read_colmap_model(folder: Path) -> tuple[dict, dict, Path]:
    """COLMAP cameras and images of ``folder`` (binary or text, read strictly: a corrupt file is named), and the
    images file read."""
    if not any((folder / f"cameras{suffix}").exists() for suffix in (".bin", ".txt")):
        raise FileNotFoundError(
            f"no COLMAP model in {folder}: expected cameras.bin + images.bin or cameras.txt + images.txt"
        )
    images_file = model_file(folder, "images")
    return (
        read_model_file(model_file(folder, "cameras"), "cameras"),
        read_model_file(images_file, "images"),
        images_file,
    )


def _world_poses(images: dict, names: list[str]) -> torch.Tensor:
    """Original-world OpenCV camera-to-world [N, 3, 4] (float64) of the named COLMAP images."""
    by_name = {image.name: image for image in images.values()}
    poses = []
    for name in names:
        image = by_name[name]
        rotation = torch.tensor(qvec2rotmat(image.qvec), dtype=torch.float64)  # world -> camera
        translation = torch.tensor(image.tvec, dtype=torch.float64)
        poses.append(torch.cat([rotation.T, (-rotation.T @ translation)[:, None]], dim=1))
    return torch.stack(poses)


def reference_from_model(
    reference_model: Path,
    input_model: Path,
    names: list[str],
    cameras: Cameras,
    dataparser_transform: torch.Tensor,
    dataparser_scale: float,
) -> Cameras:
    """The split's cameras (``names``, in order) taken from the COLMAP model ``reference_model``, in the input's
    normalized frame.

    The reference world is mapped onto the input model's world by the similarity that best maps the reference camera
    centres onto the input's, over every image of the input model (Umeyama, ``s2camp_ns.core.alignment``): the same
    map for every split. nerfstudio's normalization of the input (``dataparser_transform``, ``dataparser_scale``)
    follows. Intrinsics are scaled from the reference camera's size to each camera's (training) image size; the
    distortion is every coefficient of the reference's COLMAP model (``colmap_to_values``, the mapping the input
    goes through), and its projection (perspective or fisheye) must be the input camera's.
    """
    from s2camp_ns.core.alignment import umeyama

    reference_model = Path(reference_model)
    if not reference_model.is_dir():
        raise FileNotFoundError(f"reference_model {reference_model} is not a folder (expected a COLMAP model)")
    reference_cameras, reference_images, reference_file = _read_colmap_model(reference_model)
    _, input_images, input_file = _read_colmap_model(input_model)
    available = {image.name for image in reference_images.values()}
    all_names = sorted(image.name for image in input_images.values())
    missing = [name for name in (*all_names, *names) if name not in available]
    if missing:
        raise ValueError(
            f"reference_model: image '{missing[0]}' of {input_file} is not in {reference_file} "
            f"({len(set(missing))} of {len(all_names)} images missing; images are matched by name)"
        )
    similarity = umeyama(
        _world_poses(reference_images, all_names)[:, :, 3], _world_poses(input_images, all_names)[:, :, 3]
    )
    world = similarity.apply_to_poses(_world_poses(reference_images, names))
    c2w = colmap_world_to_c2w(world, dataparser_transform, dataparser_scale)

    by_name = {image.name: image for image in reference_images.values()}
    input_projection = projection_of(cameras)
    pinhole = torch.zeros(len(names), 4, dtype=torch.float64)
    distortion = torch.zeros(len(names), len(NERFSTUDIO_DISTORTION), dtype=torch.float64)
    for i, name in enumerate(names):
        camera = reference_cameras[by_name[name].camera_id]
        if camera.model not in SUPPORTED_COLMAP_MODELS:
            raise ValueError(
                f"{reference_file}: camera {camera.id} uses the COLMAP camera model {camera.model}; supported: "
                f"{', '.join(SUPPORTED_COLMAP_MODELS)}"
            )
        projection = CAMERA_MODEL_PROJECTION[camera.model]
        if projection != input_projection:
            raise ValueError(
                f"{reference_file}: camera {camera.id} ({camera.model}) is a {projection} camera, but image "
                f"'{name}' of the input is {input_projection}; the reference must use the input's projection"
            )
        values = colmap_to_values(camera.model, camera.params)
        sx = float(cameras.width[i]) / camera.width
        sy = float(cameras.height[i]) / camera.height
        pinhole[i] = torch.tensor([values["fx"] * sx, values["fy"] * sy, values["cx"] * sx, values["cy"] * sy])
        distortion[i] = torch.tensor(distortion_of(camera))
    dtype = cameras.fx.dtype
    return replace_cameras(
        cameras,
        camera_to_worlds=c2w.to(cameras.camera_to_worlds.dtype),
        fx=pinhole[:, 0:1].to(dtype),
        fy=pinhole[:, 1:2].to(dtype),
        cx=pinhole[:, 2:3].to(dtype),
        cy=pinhole[:, 3:4].to(dtype),
        distortion_params=distortion.to(cameras.distortion_params.dtype),
    )


__all__ = [
    "S2CampDataParser",
    "S2CampDataParserConfig",
    "SUPPORTED_COLMAP_MODELS",
    "detect_format",
    "perturb_nerfstudio_cameras",
    "reference_from_model",
    "resolve_downscale",
    "validate_colmap_cameras",
]


def _specification():
    from nerfstudio.plugins.registry_dataparser import DataParserSpecification

    return DataParserSpecification(
        config=S2CampDataParserConfig(),
        description="mip-NeRF 360 / COLMAP layout or transforms.json, with optional CamP camera perturbation",
    )


s2camp_dataparser = _specification()
"""Registered as ``s2camp-data`` (entry point ``nerfstudio.dataparser_configs``): nerfstudio exposes dataparser
options only after the dataparser's subcommand, e.g.
``ns-train s2camp --data scene s2camp-data --perturbation.enabled True``."""
