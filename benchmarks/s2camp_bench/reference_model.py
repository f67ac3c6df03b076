"""The true cameras of a COLMAP model as the split's reference cameras (``metadata["reference_cameras"]``: the camera
errors, the viewer's reference frusta, the held-out views), matched by name and similarity-aligned into the input's
normalized frame: the sfm starts' truth (``s2camp-bench-data --reference-model``, ``data_parser``)."""

from __future__ import annotations

from pathlib import Path

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.utils.colmap_parsing_utils import qvec2rotmat

from s2camp_ns.core.camera import CAMERA_MODEL_PROJECTION, opengl_to_opencv
from s2camp_ns.core.colmap_camera_models import SUPPORTED_COLMAP_MODELS, colmap_to_values
from s2camp_ns.data.camera_conversion import projection_of
from s2camp_ns.data.camera_fields import replace_cameras
from s2camp_ns.data.colmap_files import model_file, read_model_file
from s2camp_ns.data.colmap_scene import NERFSTUDIO_DISTORTION, distortion_of


def _read_colmap_model(folder: Path) -> tuple[dict, dict, Path]:
    """COLMAP cameras and images of ``folder`` (binary or text, read strictly: a corrupt file is named), and the
    images file read."""
    if not any((folder / f"cameras{suffix}").exists() for suffix in (".bin", ".txt")):
        raise FileNotFoundError(
            f"no COLMAP model in {folder}: expected cameras.bin + images.bin or cameras.txt + images.txt"
        )
    cameras, images_file = read_model_file(model_file(folder, "cameras"), "cameras"), model_file(folder, "images")
    return cameras, read_model_file(images_file, "images"), images_file


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


def colmap_world_to_c2w(
    c2w_world: torch.Tensor, dataparser_transform: torch.Tensor, dataparser_scale: float
) -> torch.Tensor:
    """nerfstudio's normalization of original-world OpenCV c2w [N, 3, 4] (float64): the inverse of
    ``s2camp_ns.data.colmap_world.c2w_to_colmap_world`` (camera axes flipped to OpenGL, ``T @ c2w``, centres
    times the scale)."""
    c2w = opengl_to_opencv(c2w_world.detach().double().cpu())
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :4] = dataparser_transform.detach().double().cpu()
    bottom = torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(c2w.shape[0], 1, 4)
    normalized = (transform @ torch.cat([c2w, bottom], dim=1))[:, :3, :4]
    normalized[:, :, 3] = normalized[:, :, 3] * float(dataparser_scale)
    return normalized


def reference_from_model(
    reference_model: Path, input_model: Path, names: list[str], cameras: Cameras, dataparser_transform: torch.Tensor,
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
    values = {name: pinhole[:, i : i + 1].to(cameras.fx.dtype) for i, name in enumerate(("fx", "fy", "cx", "cy"))}
    return replace_cameras(
        cameras, camera_to_worlds=c2w.to(cameras.camera_to_worlds.dtype), **values,
        distortion_params=distortion.to(cameras.distortion_params.dtype),
    )  # fmt: skip


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


__all__ = ["colmap_world_to_c2w", "reference_from_model"]
