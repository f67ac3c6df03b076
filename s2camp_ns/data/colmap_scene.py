"""A COLMAP scene (mip-NeRF 360 layout) read through nerfstudio's ``ColmapDataParser``, validated: model files read
strictly, camera models checked and their distortion mapped explicitly (``core.colmap_camera_models``), the listed
images found on disk and the intrinsics fitted to their sizes (``scene_formats.fit_intrinsics_to_images``). Its
frames are ours (``ValidatingColmapDataParser._get_all_images_and_cameras``, the parser's extension point); splits,
scaling and orientation are nerfstudio's."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils

from s2camp_ns.core.camera import CAMERA_MODEL_PROJECTION
from s2camp_ns.core.colmap_camera_models import SUPPORTED_COLMAP_MODELS, colmap_to_values
from s2camp_ns.data.camera_fields import replace_cameras
from s2camp_ns.data.colmap_files import ColmapModelError, model_file, read_model_file
from s2camp_ns.data.scene_config import SceneConfig
from s2camp_ns.data.scene_formats import (
    IMAGE_SUFFIXES,
    ParsedSplit,
    fit_intrinsics_to_images,
    list_images,
    nerfstudio_parser_options,
    resolve_downscale,
)

NERFSTUDIO_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
"""nerfstudio's distortion_params order."""


def validate_colmap_cameras(recon_dir: Path) -> dict[int, str]:
    """Camera id -> model name of the model's cameras; ValueError unless every camera uses one supported model
    (``ColmapModelError`` for a corrupt file)."""
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
    """Per-frame intrinsics in the keys of nerfstudio's COLMAP reader, without k4 (which that reader refuses even
    for OPENCV_FISHEYE; ``distortion_of`` supplies all six coefficients afterwards)."""
    values = colmap_to_values(camera.model, camera.params)
    fisheye = CAMERA_MODEL_PROJECTION[camera.model] == "fisheye"
    frame = {"w": camera.width, "h": camera.height, "camera_model": "OPENCV_FISHEYE" if fisheye else "OPENCV"}
    frame.update(fl_x=values["fx"], fl_y=values["fy"], cx=values["cx"], cy=values["cy"])
    frame.update({name: values[name] for name in NERFSTUDIO_DISTORTION if name != "k4"})
    return frame


def distortion_of(camera) -> list[float]:
    """nerfstudio's distortion_params [k1, k2, k3, k4, p1, p2] of a COLMAP camera."""
    values = colmap_to_values(camera.model, camera.params)
    return [values[name] for name in NERFSTUDIO_DISTORTION]


COLMAP_TO_NERFSTUDIO_WORLD = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])
"""nerfstudio's world convention for COLMAP models (``assume_colmap_world_coordinate_convention``): COLMAP's y (its
gravity guess points along -y) becomes nerfstudio's z: (x, y, z) -> (x, z, -y)."""


def opengl_c2w(image) -> np.ndarray:
    """Camera-to-world [3, 4] of a COLMAP image (its world-to-camera qvec, tvec), in nerfstudio's OpenGL camera axes
    (y up, z backwards: the OpenCV y and z columns negated)."""
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = colmap_utils.qvec2rotmat(image.qvec), image.tvec
    c2w = np.linalg.inv(w2c)[:3]
    c2w[:, 1:3] *= -1.0
    return c2w


class ValidatingColmapDataParser(ColmapDataParser):
    """nerfstudio's COLMAP parser plus file checks; remembers each image's full size and distortion."""

    def __init__(self, config: ColmapDataParserConfig, image_folder: Path):
        super().__init__(config)
        self.image_folder = image_folder
        self.full_sizes: dict[str, tuple[int, int]] = {}
        self.distortion: dict[str, list[float]] = {}
        self.size_source: dict[str, str] = {}
        """Image name -> the COLMAP camera that declares its size (for errors)."""

    def _get_all_images_and_cameras(self, recon_dir: Path) -> dict:
        """The frames nerfstudio's parser reads (in image-id order: path, OpenGL c2w, image id, the intrinsics of
        ``nerfstudio_frame_intrinsics``, mask and depth paths), the camera model and the world transform it applies,
        from the model read strictly; its own reader refuses FULL_OPENCV."""
        cameras, images, images_file = self._read_model_strictly(recon_dir)
        if not images:
            raise ValueError(f"COLMAP model {images_file} lists no images: the scene is empty")
        config, convention = self.config, self.config.assume_colmap_world_coordinate_convention
        frames = []
        for image_id in sorted(images):
            image = images[image_id]
            c2w = opengl_c2w(image)
            if convention:
                c2w = COLMAP_TO_NERFSTUDIO_WORLD[:, :3] @ c2w
            frame = {
                "file_path": (config.data / config.images_path / image.name).as_posix(),
                "transform_matrix": np.concatenate([c2w, [[0.0, 0.0, 0.0, 1.0]]]),
                "colmap_im_id": image_id,
                **nerfstudio_frame_intrinsics(cameras[image.camera_id]),
            }
            for key, folder in (("mask_path", config.masks_path), ("depth_path", config.depths_path)):
                if folder is not None:
                    frame[key] = (config.data / folder / image.name).with_suffix(".png").as_posix()
            frames.append(frame)
        self._check_images_on_disk(frames, images_file)
        out = {"frames": frames, "camera_model": frames[0]["camera_model"]}
        if convention:
            out["applied_transform"] = COLMAP_TO_NERFSTUDIO_WORLD.tolist()
        return out

    def _read_model_strictly(self, recon_dir: Path) -> tuple[dict, dict, Path]:
        """Read the cameras and images strictly (a corrupt file named before anything trips over it), remember each
        image's distortion and size source; returns the cameras and images (nerfstudio's records) and the images
        file."""
        camera_models = validate_colmap_cameras(recon_dir)
        images_file = model_file(recon_dir, "images")
        if not images_file.exists():
            raise FileNotFoundError(
                f"COLMAP model {recon_dir} has {model_file(recon_dir, 'cameras').name} but no {images_file.name}"
            )
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
        return cameras, images, images_file

    def _check_images_on_disk(self, frames: list[dict], images_file: Path) -> None:
        """Every listed image in the folder read; remembers each one's full size."""
        on_disk = list_images(self.image_folder) if self.image_folder.is_dir() else []
        if not on_disk:
            raise ValueError(
                f"the scene is empty: image folder {self.image_folder} holds no images "
                f"({', '.join(IMAGE_SUFFIXES)}) but {images_file} lists {len(frames)}"
            )
        full_folder = self.config.data / self.config.images_path
        missing = []
        for frame in frames:
            name = Path(frame["file_path"]).relative_to(full_folder).as_posix()
            self.full_sizes[name] = (int(frame["w"]), int(frame["h"]))
            if not (self.image_folder / name).is_file():
                missing.append(name)
        if missing:
            raise FileNotFoundError(
                f"{images_file} lists image '{missing[0]}' but {self.image_folder / missing[0]} does not exist "
                f"({len(missing)} of {len(frames)} listed images missing from {self.image_folder})"
            )

    def _load_3D_points(self, colmap_path: Path, transform_matrix: torch.Tensor, scale_factor: float):
        # Read strictly first: a corrupt file is named before nerfstudio's reader trips over it.
        read_model_file(model_file(colmap_path, "points3D"), "points3D")
        return super()._load_3D_points(colmap_path, transform_matrix, scale_factor)


def has_points(model: Path) -> bool:
    """Whether the COLMAP model folder holds sparse points (points3D.bin or .txt)."""
    return (model / "points3D.bin").exists() or (model / "points3D.txt").exists()


def parse_colmap(
    config: SceneConfig, data: Path, model: Path, split: str
) -> tuple[DataparserOutputs, ParsedSplit]:
    """The split of the COLMAP scene ``data`` (model folder ``model``): nerfstudio's outputs, cameras fitted to the
    images read, and the ``ParsedSplit``."""
    k = resolve_downscale(data, config.images_path, config.downscale_factor)
    full_folder = data / config.images_path
    image_folder = full_folder if k == 1 else full_folder.with_name(f"{full_folder.name}_{k}")
    colmap_config = ColmapDataParserConfig(
        data=data, colmap_path=model.relative_to(data), images_path=config.images_path, downscale_factor=k,
        load_3D_points=config.load_3D_points and has_points(model), **nerfstudio_parser_options(config),
    )  # fmt: skip
    parser = ValidatingColmapDataParser(colmap_config, image_folder)
    outputs = parser.get_dataparser_outputs(split=split)
    if not outputs.image_filenames:
        raise ValueError(f"the {split} split of {model} is empty (eval_mode={config.eval_mode!r})")
    names = [Path(p).relative_to(image_folder).as_posix() for p in outputs.image_filenames]
    declared = [(*parser.full_sizes[name], parser.size_source[name]) for name in names]
    images_file = model_file(model, "images")
    cameras = fit_intrinsics_to_images(outputs.cameras, outputs.image_filenames, declared, k, images_file)
    distortion = torch.tensor([parser.distortion[name] for name in names], dtype=torch.float32)
    cameras = replace_cameras(cameras, distortion_params=distortion)
    full_size = torch.tensor([parser.full_sizes[name] for name in names], dtype=torch.int64)
    parsed = ParsedSplit(
        image_names=names, full_image_size=full_size, downscale_factor=k, colmap_model_path=model.resolve()
    )
    return dataclasses.replace(outputs, cameras=cameras), parsed


__all__ = [
    "NERFSTUDIO_DISTORTION",
    "ValidatingColmapDataParser",
    "distortion_of",
    "has_points",
    "nerfstudio_frame_intrinsics",
    "parse_colmap",
    "validate_colmap_cameras",
]
