"""``s2camp-export-cameras``: write the refined training cameras of a trained model as a COLMAP model.

    s2camp-export-cameras --load-config outputs/scene/s2camp/DATE/config.yml --output-dir refined/sparse/0

The refined cameras (S2CamP's pose, intrinsics and distortion; nerfstudio's optimizer: pose only) are taken out of
nerfstudio's normalization, flipped from OpenGL to OpenCV and written with pycolmap
(``colmap_writer.nerfstudio_to_reconstruction``): one COLMAP camera per physical camera, in COLMAP's distortion models
(``camera_model``; nerfstudio's perspective k4 has no counterpart and is refused, skew is dropped). The input model's
sparse points are carried over without their tracks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import tyro
from nerfstudio.cameras.cameras import Cameras
from rich.console import Console

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer
from s2camp_ns.data.camera_conversion import group_identical_intrinsics, refined_nerfstudio_cameras
from s2camp_ns.data.colmap_writer import CameraModel, nerfstudio_to_reconstruction, read_points

LOG = Console(stderr=True)
"""What the command is doing while it loads the run (stderr)."""


def refined_training_cameras(pipeline) -> Cameras:
    """Refined cameras of every training image (nerfstudio's normalized OpenGL frame)."""
    model = pipeline.model
    optimizer = getattr(model, "camera_optimizer", None)
    cameras = pipeline.datamanager.train_dataset.cameras
    if optimizer is None:
        return cameras
    if isinstance(optimizer, S2CampCameraOptimizer):  # pose, fx, fy, cx, cy, distortion of every image
        return refined_nerfstudio_cameras(optimizer.refiner, cameras)
    # nerfstudio's optimizer refines poses only, one camera at a time (it reads cam_idx from the metadata).
    poses = []
    for i in range(cameras.shape[0]):
        camera = cameras[i : i + 1]
        camera.metadata = {"cam_idx": i}
        with torch.no_grad():
            poses.append(optimizer.apply_to_camera(camera).reshape(3, 4).cpu())
    refined = cameras.to("cpu")
    return Cameras(
        camera_to_worlds=torch.stack(poses).to(refined.camera_to_worlds.dtype),
        fx=refined.fx,
        fy=refined.fy,
        cx=refined.cx,
        cy=refined.cy,
        width=refined.width,
        height=refined.height,
        distortion_params=refined.distortion_params,
        camera_type=refined.camera_type,
    )


@dataclass
class ExportCamerasConfig:
    """Export the refined training cameras of a trained S2CamP (or nerfstudio) model as a COLMAP model."""

    load_config: Path
    """config.yml of the trained run (outputs/<scene>/<method>/<timestamp>/config.yml)."""
    output_dir: Path
    """Folder that receives cameras.bin, images.bin, points3D.bin (created if needed)."""
    resolution: Literal["original", "training"] = "original"
    """Intrinsics for the input model's full-size images (original) or for the images trained on."""
    camera_model: CameraModel = "auto"
    """COLMAP camera model; auto: OPENCV_FISHEYE for fisheye cameras, else the simplest of RADIAL (fx = fy, no
    tangential terms), OPENCV and FULL_OPENCV (k3) that holds every camera."""
    include_points: bool = True
    """Copy the sparse points of the input COLMAP model (if the scene came from one)."""
    text: bool = False
    """Also write the model as text (cameras.txt, images.txt, points3D.txt) into output_dir/text."""


def main(config: ExportCamerasConfig) -> Path:
    from nerfstudio.utils.eval_utils import eval_setup

    if not config.load_config.is_file():
        raise FileNotFoundError(f"--load-config {config.load_config} does not exist")
    LOG.print(f"[dim]s2camp-export-cameras: loading {config.load_config} (scene, tracks, checkpoint)", highlight=False)
    _, pipeline, _, _ = eval_setup(config.load_config, test_mode="inference")
    datamanager = pipeline.datamanager
    outputs = getattr(datamanager, "train_dataparser_outputs", None) or datamanager.train_dataset._dataparser_outputs
    metadata = outputs.metadata
    cameras = refined_training_cameras(pipeline)
    names = metadata.get("image_names") or [Path(p).name for p in outputs.image_filenames]
    full_size = metadata.get("full_image_size") if config.resolution == "original" else None
    xyz = rgb = None
    model_path = metadata.get("colmap_model_path")
    if config.include_points and model_path is not None and Path(model_path).exists():
        xyz, rgb = read_points(Path(model_path))
    optimizer = getattr(pipeline.model, "camera_optimizer", None)
    shared = isinstance(optimizer, S2CampCameraOptimizer) and optimizer.refiner.factorisation == "block"
    # One COLMAP camera per physical camera: the shared refinement's groups, else images with identical intrinsics.
    camera_ids = optimizer.refiner.camera_of_image.tolist() if shared else group_identical_intrinsics(cameras).tolist()
    reconstruction = nerfstudio_to_reconstruction(
        cameras,
        outputs.dataparser_transform,
        outputs.dataparser_scale,
        names,
        full_size,
        xyz,
        rgb,
        config.camera_model,
        camera_ids=camera_ids,
    )
    config.output_dir.mkdir(parents=True, exist_ok=True)
    reconstruction.write_binary(str(config.output_dir))
    if config.text:
        (config.output_dir / "text").mkdir(exist_ok=True)
        reconstruction.write_text(str(config.output_dir / "text"))
    print(
        f"wrote {reconstruction.num_images()} images of {reconstruction.num_cameras()} cameras and "
        f"{reconstruction.num_points3D()} points to {config.output_dir}"
    )
    return config.output_dir


def entrypoint() -> None:
    """Console script ``s2camp-export-cameras``."""
    main(tyro.cli(ExportCamerasConfig))


if __name__ == "__main__":
    entrypoint()
