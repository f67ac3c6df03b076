"""``s2camp-bench anchors``: where the tracks alone put the cameras, with the detected and with the refined keypoints,
from the regime's starts; and the keypoint error of those tracks where the generated scene's truth defines it.

The anchor is where the default starts every camera with tracks and where the tracks alone (``photometric False``,
the regime's "tracks" rows) keep it. Protocol: the regime scene (``robustness.SCENES["regime-wide"]``) and its starts
sfm, perturbed and phone, with the data parser, options and seeds of the training rows (``grid.start_arguments``: the
seeds vary the phone start's drift; SfM and CamP's perturbation are drawn once). Per start, seed and
``--refine-keypoints``, the pipeline of the "tracks" row (``robustness.train_command``) is built, not trained, in a
child process (``ns-train``'s own parse), and its training cameras at step 0 are measured by
``evaluation.camera_metrics`` against the true cameras. The method gets what the training rows get; the truth only
scores.

Keypoint error (px): for every ordered pair (i, j) of observations of a track, the surface point that i's keypoint
sees through i's true camera (``scene.procedural.intersect``), projected through j's true camera, against j's
keypoint; over pairs whose point j's camera sees unoccluded. The tracks: SfM's model and its re-adjusted keypoints
(``robust_adjustment``), or the image tracks each run built (its own cache folder), matched observation for
observation (the refinement keeps every observation).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap
import torch
from torch import Tensor

from s2camp_bench.data_parser import ns_train_environment
from s2camp_bench.scene.procedural import intersect
from s2camp_ns.core.alignment import align_cameras

from . import grid
from .common import DEFAULT_OUTPUT_DIR, generated_scene, in_work_folder, log
from .robustness import SCENES, RobustnessConfig, train_command

SCENE = "regime-wide"
STARTS = ("sfm", "perturbed", "phone")
VISIBLE = 0.01
"""Relative depth within which a projected surface point counts as seen by the other camera (not occluded)."""


@dataclass
class AnchorsConfig:
    """The anchors of the regime's starts with and without keypoint refinement (module docstring)."""

    starts: tuple[str, ...] = STARTS
    seeds: int = 3
    """Seeds of the phone start (the others are drawn once)."""
    quick: bool = False
    """Small run for CI: CamP's perturbation only."""
    work_dir: Path | None = None
    """Scenes, SfM and track caches (a temporary folder by default, removed after)."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    write: bool = True
    json: bool = False

    def effective(self) -> AnchorsConfig:
        return replace(self, starts=("perturbed",), seeds=1) if self.quick else self

    def command(self) -> str:
        return "s2camp-bench anchors" + (" --quick" if self.quick else "")


def run(config: AnchorsConfig) -> list[dict]:
    config = config.effective()
    unknown = sorted(set(config.starts) - set(STARTS))
    if unknown or config.seeds < 1:
        raise ValueError(f"starts must be among {STARTS} and seeds at least 1, got {config.starts}, {config.seeds}")
    return in_work_folder(config.work_dir, "s2camp-anchors-", lambda root: _run(config, root))


def _run(config: AnchorsConfig, root: Path) -> list[dict]:
    scene = SCENES[SCENE]
    truth_dir = generated_scene(replace(scene.scene, output_dir=root / "scenes" / SCENE))
    os.environ["XDG_CACHE_HOME"] = str(root / "xdg")  # the re-adjusted SfM tracks, read back here (``_sfm_tracks``)
    rows = []
    for start in config.starts:
        for seed in range(config.seeds if start == "phone" else 1):
            for refine in (False, True):
                rows.append(_one(start, seed, refine, scene, truth_dir, root))
                log(f"anchors: {start} seed {seed} {rows[-1]['keypoints']}: rotation {rows[-1]['rot_err']:.4g} deg")
    return rows


def _one(start: str, seed: int, refine: bool, scene: grid.GridScene, truth_dir: Path, root: Path) -> dict:
    spec = grid.RunSpec(SCENE, start, "tracks", seed)
    data, truth = (grid.sfm_scene(SCENE, truth_dir, root), truth_dir) if start == "sfm" else (truth_dir, None)
    cache = root / "caches" / f"{start}-{seed}-{refine}"
    command = train_command(spec, data, root / "runs", RobustnessConfig(), truth)[1:]
    command += ["--refine-keypoints", str(refine), "--image-tracks-cache", str(cache)]
    began = time.perf_counter()
    metrics = _anchor_metrics(command, root / "child.json")
    tracks = _sfm_tracks(data, refine) if start == "sfm" else _image_tracks(cache)
    row = {"start": start, "seed": seed, "keypoints": "refined" if refine else "detected", **metrics}
    row |= keypoint_error(tracks, pycolmap.Reconstruction(truth_dir / "sparse" / "0"))
    row["seconds"] = time.perf_counter() - began
    return row


_CHILD = """
import json, sys, warnings
import tyro
from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion
from s2camp_bench.evaluation import camera_metrics, estimated_cameras
from s2camp_bench.anchors import relative_rotation_error
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
config = tyro.cli(AnnotatedBaseConfigUnion, args=json.loads(sys.argv[2]))
config.pipeline.datamanager.data = config.data
pipeline = config.pipeline.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)
model = pipeline.model
points = pipeline.datamanager.train_dataparser_outputs.metadata["points3D_xyz"].double()
given = model._train_cameras
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    start = camera_metrics(model, points, given.camera_to_worlds.double(), intrinsics_from_cameras(given))
    anchor = camera_metrics(model, points, *estimated_cameras(model))
reference = model.reference_cameras()
reference = (model._train_cameras if reference is None else reference).camera_to_worlds.double().cpu()
anchor["rot_err_relative"] = relative_rotation_error(estimated_cameras(model)[0], reference)
start["rot_err_relative"] = relative_rotation_error(given.camera_to_worlds.double().cpu(), reference)
with open(sys.argv[1], "w") as output:
    json.dump({**anchor, **{f"start_{key}": value for key, value in start.items()}}, output)
"""


def relative_rotation_error(c2w: Tensor, reference: Tensor) -> float:
    """Mean rotation error (degrees) of the cameras ``c2w`` [n, 3, 4] against ``reference`` after the similarity
    alignment of their centres, less the rotation error all cameras share (their mean error vector in the world, the
    part a centre alignment of a nearly planar ring leaves uncertain). Small angles: the vector of R_est R_ref^T's
    antisymmetric part."""
    aligned = align_cameras(c2w, reference).apply_to_poses(c2w)
    delta = aligned[:, :, :3] @ reference[:, :, :3].transpose(1, 2)  # [n, 3, 3]
    error = 0.5 * torch.stack([delta[:, 2, 1] - delta[:, 1, 2], delta[:, 0, 2] - delta[:, 2, 0],
                               delta[:, 1, 0] - delta[:, 0, 1]], dim=-1)  # fmt: skip
    return math.degrees(float((error - error.mean(dim=0)).norm(dim=-1).mean()))


def _anchor_metrics(arguments: list[str], output: Path) -> dict:
    """Camera errors of the training cameras at step 0 (the anchor) and as given, from a child process."""
    command = [sys.executable, "-c", _CHILD, str(output), json.dumps(arguments)]
    result = subprocess.run(command, env=ns_train_environment(), capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"building the pipeline failed:\n{result.stderr[-4000:]}")
    return json.loads(output.read_text(encoding="utf8"))


def _image_tracks(cache: Path) -> pycolmap.Reconstruction:
    """The one image tracks model the run built into ``cache``."""
    (entry,) = [folder for folder in cache.iterdir() if (folder / "images.bin").is_file()]
    return pycolmap.Reconstruction(entry)


def _sfm_tracks(data: Path, refine: bool) -> pycolmap.Reconstruction:
    """SfM's model with the keypoints the anchor was fitted to (refined: read from the run's re-adjustment cache)."""
    from s2camp_ns.tracks.robust_adjustment import readjusted_tracks

    model = pycolmap.Reconstruction(data / "sparse" / "0")
    if refine:
        keypoints = readjusted_tracks(data / "sparse" / "0", data / "images").keypoints
        for image_id, xys in keypoints.items():
            for index, xy in enumerate(xys):
                model.images[image_id].points2D[index].xy = xy
    return model


def keypoint_error(tracks: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> dict:
    """``keypoint_median`` / ``keypoint_p90`` (px) over the visible ordered pairs of ``tracks``' observations
    (module docstring), and their count ``keypoint_pairs``."""
    true_image = {image.name: image for image in truth.images.values()}
    errors = []
    for point in tracks.points3D.values():
        elements = list(point.track.elements)
        views = [true_image[tracks.images[element.image_id].name] for element in elements]
        xy = np.stack([tracks.images[e.image_id].points2D[e.point2D_idx].xy for e in elements])  # [l, 2]
        centres = np.stack([view.projection_center() for view in views])
        rays = [_ray(truth.cameras[view.camera_id], view, pixel) for view, pixel in zip(views, xy, strict=True)]
        directions = np.stack(rays)
        hits = intersect(centres, directions)
        surface = centres + hits.t[:, None] * directions  # [l, 3]: what each keypoint sees
        for i in range(len(elements)):
            for j in range(len(elements)):
                if i == j or not np.isfinite(hits.t[i]):
                    continue
                error = _seen_error(truth.cameras[views[j].camera_id], views[j], surface[i], xy[j])
                if error is not None:
                    errors.append(error)
    values = np.asarray(errors)
    return {
        "keypoint_median": float(np.median(values)), "keypoint_p90": float(np.percentile(values, 90)),
        "keypoint_pairs": len(values),
    }  # fmt: skip


def _ray(camera: pycolmap.Camera, image: pycolmap.Image, pixel: np.ndarray) -> np.ndarray:
    """The unit world direction of the ray through ``pixel`` (continuous px) of ``image``'s true camera."""
    normalized = camera.cam_from_img(pixel[None])[0]
    direction = np.asarray(image.cam_from_world().rotation.matrix()).T @ np.append(normalized, 1.0)
    return direction / np.linalg.norm(direction)


def _seen_error(camera: pycolmap.Camera, image: pycolmap.Image, xyz: np.ndarray, keypoint: np.ndarray) -> float | None:
    """Distance (px) of ``keypoint`` from ``xyz`` projected into ``image``'s true camera; None when the camera does
    not see ``xyz`` (behind it, or another surface in front)."""
    local = np.asarray(image.cam_from_world().matrix()) @ np.append(xyz, 1.0)
    if local[2] <= 0:
        return None
    centre = image.projection_center()
    distance = np.linalg.norm(xyz - centre)
    hit = intersect(centre[None], ((xyz - centre) / distance)[None]).t[0]
    if abs(hit - distance) > VISIBLE * distance:
        return None
    return float(np.linalg.norm(camera.img_from_cam(local[None])[0] - keypoint))


def report(rows: list[dict], config: AnchorsConfig) -> Path:
    from .anchors_report import write

    return write(rows, config)
