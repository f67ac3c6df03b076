"""``s2camp-bench image-tracks``: wall time of an image tracks build (``s2camp_ns.tracks.image_tracks``) at
several image counts of 1080p images, per stage.

One generated scene (``scene``: 300 images of 1920x1080 on a ring, 80 degrees wide, JPEG) is made once in ``scene_dir``
(not timed). Each count takes evenly spaced images of it, gives them the true cameras turned and moved as a phone's
visual-inertial poses are (``rotation_deg``, ``centre_noise``; one focal length ``focal_error`` long) and builds their
tracks into a fresh cache folder, as the data parser does before training (every pair matched up to
``EXHAUSTIVE_LIMIT`` images, else each image with its ``NEIGHBOURS``). A row records the build's wall time, its
stages', the pairs matched, the build's summary and the load average before and after (the CPU stages use every
core: a loaded machine slows them).
"""

from __future__ import annotations

import copy
import math
import os
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap

from s2camp_bench.report import markdown_table
from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_ns.tracks.image_tracks import EXHAUSTIVE_LIMIT, NEIGHBOURS, feature_device, image_tracks, neighbour_pairs

from .common import DEFAULT_OUTPUT_DIR, generated_scene, in_work_folder, log, write_report

STAGES = ("SIFT", "matching", "triangulation", "adjustment", "keypoints", "refined adjustment")
"""The build's kinds of stage (``image_tracks``' progress), the report's columns."""
REFINEMENT = ("keypoints", "refined adjustment")
"""The stages keypoint refinement adds (``image_tracks``, step 4): the build without them is the build without it."""


def _column(stage: str) -> str:
    return f"{stage.replace(' ', '_')}_seconds"


@dataclass
class ImageTracksCostConfig:
    """Wall time of image tracks builds of 50, 150 and 300 generated 1080p images (module docstring)."""

    counts: tuple[int, ...] = (300, 150, 50)
    """Image counts to build, each from evenly spaced images of the scene (the largest first: the one that matters)."""
    scene: MakeSceneConfig = field(
        default_factory=lambda: MakeSceneConfig(
            num_cameras=300, width=1920, height=1080, fov="wide", image_format="jpg", supersample=1, seed=0
        )
    )
    """The generated scene (s2camp-make-scene settings); its images are the largest count's."""
    rotation_deg: float = 1.0
    """RMS rotation error of the given cameras (degrees): a phone's visual-inertial poses."""
    centre_noise: float = 0.02
    """Per-axis centre noise of the given cameras (scene units; the generated ring's radius is 4)."""
    focal_error: float = 0.02
    """Relative error of the given focal length (one camera: a factory calibration)."""
    seed: int = 0
    """Seed of the given cameras' errors."""
    quick: bool = False
    """Small run for CI: 12 and 8 images of 160x120; asserts only that it runs."""
    scene_dir: Path | None = None
    """Where the scene and the caches go (a temporary folder by default, removed afterwards; name one to keep the
    scene for later runs)."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report (``--output-dir docs/benchmarks`` rewrites the committed one)."""
    write: bool = True
    json: bool = False

    def effective(self) -> ImageTracksCostConfig:
        if not self.quick:
            return self
        scene = replace(self.scene, num_cameras=12, width=160, height=120)
        return replace(self, counts=(12, 8), scene=scene)


def given_cameras(truth: pycolmap.Reconstruction, count: int, config: ImageTracksCostConfig) -> pycolmap.Reconstruction:
    """``count`` evenly spaced images of ``truth`` (by name) with the configured pose and focal errors, no points."""
    rng = np.random.default_rng(config.seed)
    images = sorted(truth.images.values(), key=lambda image: image.name)
    chosen = [images[i] for i in np.linspace(0, len(images), count, endpoint=False).astype(int)]
    given = pycolmap.Reconstruction()
    for camera_id in sorted({image.camera_id for image in chosen}):
        camera = copy.copy(truth.cameras[camera_id])
        params = camera.params.copy()
        params[0] *= 1.0 + config.focal_error
        camera.params = params
        given.add_camera_with_trivial_rig(camera)
    per_axis = math.radians(config.rotation_deg) / math.sqrt(3.0)
    for image in chosen:
        pose = image.cam_from_world()
        centre = -(pose.rotation.inverse() * pose.translation) + rng.normal(0.0, config.centre_noise, 3)
        rotation = pycolmap.Rotation3d(rng.normal(0.0, per_axis, 3)) * pose.rotation
        noisy = pycolmap.Rigid3d(rotation, -(rotation * centre))
        posed = pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id)
        given.add_image_with_trivial_frame(posed, noisy)
    return given


def run(config: ImageTracksCostConfig) -> list[dict]:
    config = config.effective()
    for count in config.counts:
        if count < 1 or count > config.scene.num_cameras:
            raise ValueError(f"counts must lie in 1..scene.num_cameras ({config.scene.num_cameras}), got {count}")
    return in_work_folder(config.scene_dir, "s2camp-image-tracks-", lambda root: _run(config, root))


def _run(config: ImageTracksCostConfig, root: Path) -> list[dict]:
    scene = generated_scene(replace(config.scene, output_dir=root / "scene"))
    truth = pycolmap.Reconstruction(scene / "sparse" / "0")
    rows = []
    for index, count in enumerate(config.counts):
        log(f"image-tracks: build {index + 1}/{len(config.counts)}, {count} images")
        cache = root / "caches" / f"{count}"
        shutil.rmtree(cache, ignore_errors=True)
        given = given_cameras(truth, count, config)
        load_before = os.getloadavg()
        start = time.perf_counter()
        result = image_tracks(given, scene / "images", cache)
        seconds = time.perf_counter() - start
        pairs = count * (count - 1) // 2 if count <= EXHAUSTIVE_LIMIT else len(neighbour_pairs(given))
        row = {
            "images": count, "size": f"{config.scene.width}x{config.scene.height}", "pairs": pairs, "seconds": seconds,
            **{_column(stage): result.stage_seconds.get(stage, 0.0) for stage in STAGES},
            "ratio": seconds / (seconds - sum(result.stage_seconds.get(stage, 0.0) for stage in REFINEMENT)),
            "summary": result.summary or result.reason,
            "device": "GPU" if feature_device()[0] == pycolmap.Device.cuda else "CPU",
            "load_before": round(load_before[0], 2), "load_after": round(os.getloadavg()[0], 2), "cpus": os.cpu_count(),
        }  # fmt: skip
        log(f"image-tracks: {count} images in {seconds:.0f} s: {row['summary']}")
        rows.append(row)
    return rows


def report(rows: list[dict], config: ImageTracksCostConfig) -> Path:
    config = config.effective()
    s = config.scene
    setup = (
        f"Image tracks builds (`s2camp_ns/tracks/image_tracks.py`) of evenly spaced images of one generated "
        f"scene ({s.num_cameras} images of {s.width}x{s.height} on a ring, {s.fov} field of view, {s.image_format}), "
        f"the given cameras {config.rotation_deg:g} deg RMS and {config.centre_noise:g} units per axis off, the "
        f"focal length {config.focal_error:.0%} long (a phone's poses); every pair matched up to {EXHAUSTIVE_LIMIT} "
        f"images, else each image with its {NEIGHBOURS} nearest cameras that face alike. Wall seconds of the whole "
        f"build and of each kind of stage; keypoints and refined adjustment are what keypoint refinement adds (the "
        f"refinement, then a last adjustment on its keypoints), and the ratio is the build's time over its time "
        f"without them, in the same build; load = the 1-minute load average before the build (the CPU stages use "
        f"every core: a loaded machine slows them)."
    )
    columns = ["images", "pairs", "seconds", *(_column(stage) for stage in STAGES), "ratio", "device", "load_before"]
    headers = ["images", "pairs", "total s", *(f"{stage} s" for stage in STAGES), "ratio", "device", "load before"]
    summaries = "\n".join(f"- {row['images']} images: {row['summary']}" for row in rows)
    counts = "" if config.counts == ImageTracksCostConfig().counts else " --counts " + " ".join(map(str, config.counts))
    command = "s2camp-bench image-tracks" + (" --quick" if config.quick else counts)
    sections = [setup, markdown_table(rows, columns, headers), "## What each build made", summaries]
    return write_report(config.output_dir, "image-tracks", "Image tracks: the cost of a build", command, sections)
