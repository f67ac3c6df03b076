"""The reference cameras of the split (``metadata["reference_cameras"]``: the camera errors, the viewer's reference
frusta, the held-out views): the unperturbed input cameras, or with ``--reference-model`` the true cameras of a
COLMAP model, matched by name and similarity-aligned into the input's normalized frame (``reference_from_model``)."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.utils.colmap_parsing_utils import qvec2rotmat

from s2camp_ns.core.camera import CAMERA_MODEL_PROJECTION
from s2camp_ns.core.colmap_models import SUPPORTED_COLMAP_MODELS, colmap_to_values
from s2camp_ns.nerfstudio.camera_conversion import projection_of
from s2camp_ns.nerfstudio.camera_fields import replace_cameras
from s2camp_ns.nerfstudio.colmap_model import model_file, read_model_file
from s2camp_ns.nerfstudio.colmap_scene import NERFSTUDIO_DISTORTION, distortion_of
from s2camp_ns.nerfstudio.colmap_world import colmap_world_to_c2w
from s2camp_ns.nerfstudio.scene_formats import ParsedSplit

if TYPE_CHECKING:
    from s2camp_ns.nerfstudio.dataparser import S2CampDataParserConfig


def reference_cameras(
    config: S2CampDataParserConfig, data_format: str, source: Path, outputs: DataparserOutputs, parsed: ParsedSplit
) -> Cameras:
    """The split's reference cameras: a copy of the (unperturbed) input cameras ``outputs.cameras``, or those of
    ``config.reference_model`` (COLMAP scenes only: images are matched by name)."""
    if config.reference_model is None:
        return copy.deepcopy(outputs.cameras)
    if data_format != "colmap":
        raise ValueError(
            f"reference_model {config.reference_model} needs a COLMAP scene (images matched by name), but "
            f"--data {config.data} is a {data_format} scene ({source})"
        )
    return reference_from_model(
        config.reference_model,
        source,
        parsed.image_names,
        outputs.cameras,
        outputs.dataparser_transform,
        float(outputs.dataparser_scale),
    )


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
    pinhole, distortion = _reference_intrinsics(reference_cameras, reference_images, reference_file, names, cameras)
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


def _reference_intrinsics(
    reference_cameras: dict, reference_images: dict, reference_file: Path, names: list[str], cameras: Cameras
) -> tuple[torch.Tensor, torch.Tensor]:
    """fx, fy, cx, cy [N, 4] of the reference's camera of each named image, scaled to the size of ``cameras``, and
    its distortion [N, 6] (float64); its projection must be the input's."""
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
    return pinhole, distortion


__all__ = ["reference_cameras", "reference_from_model"]
