"""``s2camp-export-cameras``: a trained run's refined scene, a folder nerfstudio and COLMAP open as they open the input.

    s2camp-export-cameras --load-config outputs/scene/s2camp/DATE/config.yml --output-dir refined
    ns-train splatfacto --data refined                                  # refined/transforms.json
    ns-train nerfacto --data refined colmap --colmap-path sparse/0      # refined/sparse/0

``refined/sparse/0``: the refined cameras (S2CamP's pose, intrinsics and distortion; nerfstudio's optimizer: pose
only) out of nerfstudio's normalization, in OpenCV axes, one COLMAP camera per physical camera in COLMAP's distortion
models (``camera_model``; nerfstudio's perspective k4 has no counterpart and is refused, skew is dropped); the images
with their keypoints; the points the anchors were fitted to (``core.anchor_tracks``) with their tracks, each
re-triangulated in the refined cameras where that lowers its reprojection error (``core.triangulation``), coloured
from the images. All in the input's world. ``refined/transforms.json`` and ``refined/sparse_pc.ply``: the same, as
ns-process-data writes them (nerfstudio's ``colmap_to_json``, the input's world kept). ``refined/images`` (and
``images_2``, ``images_4``, ``images_8`` where the input has them): links to the input's image folders; where
splatfacto trained on undistorted images (a distorted camera model), those images, written there, with their refined
pinhole cameras at the training resolution.

Loading does no track work: the tracks come from the run's ``anchor_tracks.pt``. A run without one (written by an
earlier version) is loaded as for training once, which makes the tracks and fits the anchors, and the file is kept.
"""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import tyro
from nerfstudio.cameras.cameras import Cameras
from rich.console import Console

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer
from s2camp_ns.core.anchor_tracks import ANCHOR_TRACKS_FILE, AnchorTracks
from s2camp_ns.core.tracks import Tracks
from s2camp_ns.core.triangulation import retriangulated_points
from s2camp_ns.data.camera_conversion import (
    group_identical_intrinsics,
    intrinsics_from_cameras,
    refined_nerfstudio_cameras,
)
from s2camp_ns.data.camera_fields import has_distortion
from s2camp_ns.data.colmap_world import c2w_to_colmap_world
from s2camp_ns.data.colmap_writer import CameraModel, nerfstudio_to_reconstruction, read_points
from s2camp_ns.method.pipeline import TRAINING_MODE
from s2camp_ns.tracks.transforms_tracks import full_size_images, image_folder_and_names

LOG = Console(stderr=True)
"""What the command is doing while it loads the run (stderr)."""
MODEL_FOLDER = Path("sparse") / "0"
"""Where in the scene folder the COLMAP model goes (the mip-NeRF 360 layout)."""
EXPORT_KEY = "s2camp_export"
"""transforms.json key naming the run an export came from (nerfstudio's parsers ignore it)."""
DOWNSCALED = (2, 4, 8)
"""The downscaled image folders (``images_k``) linked where the input has them."""


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
    """Export a trained S2CamP (or nerfstudio) run's refined scene: COLMAP model, transforms.json, points, images."""

    load_config: Path
    """config.yml of the trained run (outputs/<scene>/<method>/<timestamp>/config.yml)."""
    output_dir: Path
    """Scene folder to write (created if needed); a path ending in sparse/0 (the earlier form) writes two folders up."""
    resolution: Literal["original", "training"] = "original"
    """Intrinsics for the input's full-size images (original) or for the images trained on."""
    camera_model: CameraModel = "auto"
    """COLMAP camera model; auto: OPENCV_FISHEYE for fisheye cameras, else the simplest of RADIAL (fx = fy, no
    tangential terms), OPENCV and FULL_OPENCV (k3) that holds every camera."""
    include_points: bool = True
    """Write the anchors' points with their tracks (a run without tracks: the input model's points, no tracks)."""
    text: bool = False
    """Also write the model as text (cameras.txt, images.txt, points3D.txt) into sparse/0/text."""


@dataclass(frozen=True)
class ImageFolders:
    """Where the exported images are: the folder ``images`` links to, each image's name in it, and the ``images_k``
    folders linked beside it."""

    root: Path
    names: list[str]
    downscaled: dict[str, Path]


def scene_folder(output_dir: Path) -> Path:
    """The scene folder of ``--output-dir``: itself, or two folders up from one ending in sparse/0 (with a note)."""
    if output_dir.parts[-2:] == MODEL_FOLDER.parts:
        root = output_dir.parent.parent
        LOG.print(f"[yellow]--output-dir {output_dir} ends in {MODEL_FOLDER}: the model goes there and the rest of the "
                  f"scene (transforms.json, sparse_pc.ply, images) into {root}; pass --output-dir {root}")  # fmt: skip
        return root
    return output_dir


def load_run(load_config: Path):
    """The run's pipeline and its anchors' tracks: from ``ANCHOR_TRACKS_FILE`` (no track work), else (an earlier
    version's run) from a pipeline built as for training, the file then written."""
    from nerfstudio.utils.eval_utils import eval_setup

    stored = load_config.parent / ANCHOR_TRACKS_FILE
    if stored.is_file():
        LOG.print(f"[dim]s2camp-export-cameras: loading {load_config} (checkpoint; tracks from {stored})")
        _, pipeline, _, _ = eval_setup(load_config, test_mode="inference")
        return pipeline, AnchorTracks.load(stored)
    LOG.print(
        f"[yellow]{load_config.parent} has no {ANCHOR_TRACKS_FILE} (a run of an earlier version): making its tracks "
        "and fitting its anchors once, as training does; the file is kept for the next export"
    )
    _, pipeline, _, _ = eval_setup(load_config, test_mode=TRAINING_MODE)
    tracks = getattr(pipeline, "anchor_tracks", None)
    if tracks is not None:
        try:
            tracks.save(stored)
        except OSError as error:
            LOG.print(f"[yellow]could not keep {stored}: {error}")
    return pipeline, tracks


def dataparser_outputs(pipeline):
    """The training split's data parser outputs of a loaded pipeline."""
    datamanager = pipeline.datamanager
    return getattr(datamanager, "train_dataparser_outputs", None) or datamanager.train_dataset._dataparser_outputs


def image_folders(pipeline, resolution: str) -> ImageFolders:
    """The training images' folder at ``resolution`` and their names in it; the input's downscaled folders."""
    outputs = dataparser_outputs(pipeline)
    metadata = outputs.metadata
    k = int(metadata.get("downscale_factor", 1))
    if metadata.get("source_format") == "colmap":  # the model's names under images/ (or images_k/)
        names = list(metadata["image_names"])
        depth = len(Path(names[0]).parts)
        root = Path(outputs.image_filenames[0]).parents[depth - 1]
        if resolution == "original" and k > 1:
            root = root.with_name(root.name.removesuffix(f"_{k}"))
    else:
        paths = [Path(p) for p in outputs.image_filenames]
        if resolution == "original":
            paths = full_size_images(Path(metadata["source_path"]), outputs.image_filenames, k)
        root, names = image_folder_and_names(paths)
    downscaled = {}
    if resolution == "original":
        for factor in DOWNSCALED:
            folder = root.with_name(f"{root.name}_{factor}")
            if folder.is_dir():
                downscaled[f"images_{factor}"] = folder
    return ImageFolders(root.resolve(), names, {name: folder.resolve() for name, folder in downscaled.items()})


def exported_tracks(tracks: AnchorTracks | None, cameras: Cameras, outputs) -> Tracks | None:
    """The anchors' tracks with each point re-triangulated in the refined ``cameras`` (training pixels)."""
    if tracks is None or tracks.tracks is None:
        return None
    if tracks.num_images != cameras.shape[0]:
        raise ValueError(
            f"the run's {ANCHOR_TRACKS_FILE} holds tracks of {tracks.num_images} images, its checkpoint "
            f"{cameras.shape[0]}: the file belongs to another run"
        )
    c2w = c2w_to_colmap_world(cameras.camera_to_worlds, outputs.dataparser_transform, outputs.dataparser_scale)
    points = retriangulated_points(tracks.tracks, c2w, intrinsics_from_cameras(cameras.to("cpu")))
    return Tracks(points, tracks.tracks.image, tracks.tracks.point, tracks.tracks.pixels)


def undistorted_images(pipeline) -> list[torch.Tensor] | None:
    """The undistorted training images [H, W, 3] a full-image data manager (splatfacto's) trained on when the given
    cameras are distorted (the refined cameras are then those images' pinholes, ``method.pipeline``); else None."""
    datamanager = pipeline.datamanager
    if not hasattr(type(datamanager), "cached_train") or not has_distortion(dataparser_outputs(pipeline).cameras):
        return None
    return [entry["image"] for entry in datamanager.cached_train]


def write_images(folder: Path, names: list[str], images: list[torch.Tensor]) -> None:
    """Each image [H, W, 3] (uint8, or float in [0, 1]) as ``folder/name`` (a link there is replaced)."""
    from PIL import Image

    if folder.is_symlink():
        folder.unlink()
    for name, image in zip(names, images, strict=True):
        pixels = image[..., :3].cpu()
        pixels = pixels if pixels.dtype == torch.uint8 else (pixels.clamp(0, 1) * 255).round().to(torch.uint8)
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(pixels.numpy()).save(folder / name)


def link_images(root: Path, folders: ImageFolders) -> None:
    """``root/images`` and the ``images_k`` links to the input's folders (links already there are replaced)."""
    for name, target in {"images": folders.root, **folders.downscaled}.items():
        link = root / name
        if link.is_symlink():
            link.unlink()
        elif link.exists():
            if link.resolve() == target:
                continue
            raise FileExistsError(f"{link} exists and is not a link to {target}: pass an --output-dir without it")
        link.symlink_to(target, target_is_directory=True)


def check_not_overwriting(root: Path) -> None:
    """FileExistsError where ``root`` holds a transforms.json or sparse_pc.ply that no export wrote (``EXPORT_KEY``):
    an input scene's, which the export must not replace."""
    transforms = root / "transforms.json"
    ours = False
    if transforms.is_file():
        try:
            ours = EXPORT_KEY in json.loads(transforms.read_text(encoding="utf8"))
        except (ValueError, OSError):
            ours = False
    for name in ("transforms.json", "sparse_pc.ply"):
        if (root / name).exists() and not ours:
            raise FileExistsError(
                f"{root / name} exists and was not written by s2camp-export-cameras: pass an --output-dir of its own "
                "(e.g. refined), the export does not replace a scene's files"
            )


def write_transforms(root: Path, load_config: Path) -> None:
    """``root/transforms.json`` and ``root/sparse_pc.ply`` of ``root/sparse/0`` by nerfstudio's ``colmap_to_json``
    (ns-process-data's writer), in the model's world, marked with ``EXPORT_KEY``; its console lines are left out."""
    from nerfstudio.process_data.colmap_utils import colmap_to_json

    with contextlib.redirect_stdout(io.StringIO()):
        colmap_to_json(root / MODEL_FOLDER, root, keep_original_world_coordinate=True)
    transforms = root / "transforms.json"
    content = json.loads(transforms.read_text(encoding="utf8"))
    content[EXPORT_KEY] = {"load_config": str(load_config.resolve())}
    transforms.write_text(json.dumps(content, indent=4), encoding="utf8")


def main(config: ExportCamerasConfig) -> Path:
    if not config.load_config.is_file():
        raise FileNotFoundError(f"--load-config {config.load_config} does not exist")
    root = scene_folder(config.output_dir)
    check_not_overwriting(root)
    model_dir = root / MODEL_FOLDER
    pipeline, anchor = load_run(config.load_config)
    outputs = dataparser_outputs(pipeline)
    metadata = outputs.metadata
    cameras = refined_training_cameras(pipeline)
    undistorted = undistorted_images(pipeline)
    resolution = "training" if undistorted is not None else config.resolution
    if undistorted is not None and config.resolution == "original":
        LOG.print("[yellow]The run trained on undistorted images (splatfacto's full-image data manager): the export "
                  "holds them, with their refined pinhole cameras, at the training resolution")  # fmt: skip
    folders = image_folders(pipeline, resolution)
    if config.include_points and anchor is not None and anchor.tracks is not None:
        LOG.print(f"[dim]re-triangulating {anchor.tracks.points.shape[0]} points in the refined cameras")
    tracks = exported_tracks(anchor, cameras, outputs) if config.include_points else None
    xyz = rgb = None
    model_path = metadata.get("colmap_model_path")
    if config.include_points and tracks is None and model_path is not None and Path(model_path).exists():
        xyz, rgb = read_points(Path(model_path))
    optimizer = getattr(pipeline.model, "camera_optimizer", None)
    shared = isinstance(optimizer, S2CampCameraOptimizer) and optimizer.refiner.factorisation == "block"
    # One COLMAP camera per physical camera: the shared refinement's groups, else images with identical intrinsics.
    camera_ids = optimizer.refiner.camera_of_image.tolist() if shared else group_identical_intrinsics(cameras).tolist()
    reconstruction = nerfstudio_to_reconstruction(
        cameras, outputs.dataparser_transform, outputs.dataparser_scale, folders.names,
        metadata.get("full_image_size") if resolution == "original" else None, xyz, rgb, config.camera_model,
        camera_ids=camera_ids, tracks=tracks,
    )  # fmt: skip
    model_dir.mkdir(parents=True, exist_ok=True)
    if undistorted is None:
        link_images(root, folders)
    else:
        write_images(root / "images", folders.names, undistorted)
    if tracks is not None:
        reconstruction.extract_colors_for_all_images(str(root / "images"))
    reconstruction.write_binary(str(model_dir))
    if config.text:
        (model_dir / "text").mkdir(exist_ok=True)
        reconstruction.write_text(str(model_dir / "text"))
    write_transforms(root, config.load_config)
    tracked = f"with tracks over {sum(len(i.points2D) for i in reconstruction.images.values())} keypoints"
    print(
        f"wrote {reconstruction.num_images()} images of {reconstruction.num_cameras()} cameras and "
        f"{reconstruction.num_points3D()} points{' ' + tracked if tracks is not None else ''} to {model_dir}; "
        f"transforms.json, sparse_pc.ply and {'the undistorted images' if undistorted else 'the image links'} to {root}"
    )
    return root


def entrypoint() -> None:
    """Console script ``s2camp-export-cameras``."""
    main(tyro.cli(ExportCamerasConfig))


if __name__ == "__main__":
    entrypoint()
