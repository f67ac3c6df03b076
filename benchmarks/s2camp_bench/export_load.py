"""``s2camp-bench export-load``: wall time of ``s2camp-export-cameras`` on a trained run, loading it from the run's
anchor tracks (``anchor_tracks.pt``: no track work) against loading it with the track work (the run without the
file, as a run of an earlier version loads once: built as for training, the data parser makes the tracks and the
anchors are fitted).

Per scene (generated, ``SCENES``): ``ns-train s2camp`` for ``iterations`` steps (not timed: it builds the tracks and
their caches), then in fresh processes, as a user runs them: the export with the file, the export without it (the
file is then written again) and the export with it once more. A row records each command's wall time, the
tracks' size, the exported scene's and its points' reprojection error against the anchors'.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap

from s2camp_bench.report import markdown_table
from s2camp_bench.scene.make_scene import MakeSceneConfig
from s2camp_ns.core.anchor_tracks import ANCHOR_TRACKS_FILE, AnchorTracks

from . import train_commands
from .common import DEFAULT_OUTPUT_DIR, generated_scene, in_work_folder, log, write_report

SCENES = {
    "generated (demo size)": MakeSceneConfig(num_cameras=24, width=160, height=120, seed=0),
    "300 images": MakeSceneConfig(num_cameras=300, width=640, height=480, points_per_image=20, supersample=1, seed=0),
}
"""The scenes (COLMAP layout with SfM tracks; the tracks are these, re-adjusted, keypoints refined). The generator's
points are seen from far around the ring: 20 per image give the 300-image scene about 2,000 observations per image,
a real SfM model's density."""
QUICK_SCENE = MakeSceneConfig(num_cameras=12, width=64, height=48, points_per_image=150, seed=0)
"""``--quick``'s scene (the tests' tiny one), exported once with and once without the file."""


@dataclass
class ExportLoadConfig:
    """Export wall time with and without the run's anchor tracks (module docstring)."""

    iterations: int = 2
    """Training steps of each run (the load's cost does not depend on them)."""
    quick: bool = False
    """Small run for CI: a 12-image scene, exported twice."""
    work_dir: Path | None = None
    """Scenes, runs and exports (a temporary folder by default, removed after)."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    write: bool = True
    json: bool = False

    def command(self) -> str:
        return "s2camp-bench export-load" + (" --quick" if self.quick else "")


def run(config: ExportLoadConfig) -> list[dict]:
    return in_work_folder(config.work_dir, "s2camp-export-load-", lambda root: _run(config, root))


def _timed(command: list[str]) -> tuple[float, str]:
    began = time.perf_counter()
    environment = {**train_commands.training_environment(), "COLUMNS": "200"}
    result = subprocess.run(command, capture_output=True, text=True, env=environment)
    if result.returncode != 0:
        raise RuntimeError(f"{command[0]} exited with {result.returncode}:\n{result.stderr[-4000:]}")
    return time.perf_counter() - began, result.stdout + result.stderr


def _exported_rms(reconstruction: pycolmap.Reconstruction) -> float:
    """Reprojection RMS (px) of every track element of the exported model, by pycolmap's camera models."""
    squared = []
    for point in reconstruction.points3D.values():
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            projected = reconstruction.cameras[image.camera_id].img_from_cam(image.cam_from_world() * point.xyz)
            squared.append(float(((projected - image.points2D[element.point2D_idx].xy) ** 2).sum()))
    return float(np.sqrt(np.mean(squared)))


def _anchor_rms(anchor: AnchorTracks) -> float:
    """The anchor fit's RMS (px) over the same observations (its per-image RMS pooled by count)."""
    count = np.bincount(anchor.tracks.image.numpy(), minlength=anchor.num_images)
    return float(np.sqrt((np.nan_to_num(anchor.rms_px.numpy()) ** 2 * count).sum() / count.sum()))


def _run(config: ExportLoadConfig, root: Path) -> list[dict]:
    rows = []
    export = str(Path(sys.executable).with_name("s2camp-export-cameras"))
    scenes = {"quick (12 images)": QUICK_SCENE} if config.quick else SCENES
    cases = ("with file", "with track work") if config.quick else ("with file", "with track work", "with file again")
    for name, scene_config in scenes.items():
        scene = generated_scene(replace(scene_config, output_dir=root / "scenes" / name.split()[0]))
        log(f"export-load: training s2camp on {name} ({config.iterations} steps, tracks built once)")
        command = train_commands.ns_train_arguments("s2camp", scene, root / "runs", name.split()[0], "run",
                                                    config.iterations, 1000, 256)  # fmt: skip
        train_seconds, _ = _timed([*command, "--vis", "tensorboard"])
        run_dir = root / "runs" / name.split()[0] / "s2camp" / "run"
        anchor = AnchorTracks.load(run_dir / ANCHOR_TRACKS_FILE)
        seconds = {}
        for case in cases:
            if case == "with track work":
                (run_dir / ANCHOR_TRACKS_FILE).unlink()
            output = root / "exports" / name.split()[0] / case.replace(" ", "-")
            shutil.rmtree(output, ignore_errors=True)
            log(f"export-load: {name}, {case}")
            seconds[case], said = _timed([export, "--load-config", str(run_dir / "config.yml"), "--output-dir",
                                          str(output)])  # fmt: skip
            if case != "with track work" and "Levenberg" in said:
                raise RuntimeError(f"the export of {run_dir} {case} fitted the anchors:\n{said[-2000:]}")
        exported = pycolmap.Reconstruction(str(output / "sparse" / "0"))
        rows.append({
            "scene": name, "images": anchor.num_images, "observations": int(anchor.tracks.image.shape[0]),
            "points": exported.num_points3D(), "train_seconds": train_seconds,
            "exported_rms_px": _exported_rms(exported), "anchor_rms_px": _anchor_rms(anchor),
            "export_seconds_with_file": seconds["with file"],
            "export_seconds_with_track_work": seconds["with track work"],
            "export_seconds_with_file_again": seconds.get("with file again", float("nan")),
            "ratio": seconds["with track work"] / seconds["with file"],
        })  # fmt: skip
        log(f"export-load: {json.dumps(rows[-1])}")
    return rows


def report(rows: list[dict], config: ExportLoadConfig) -> Path:
    columns = ["scene", "images", "observations", "points", "export_seconds_with_track_work",
               "export_seconds_with_file", "export_seconds_with_file_again", "ratio", "anchor_rms_px",
               "exported_rms_px"]  # fmt: skip
    headers = ["scene", "training images", "track observations", "exported points",
               "export, loading with track work (s)", "export, loading the run's anchor tracks (s)", "again (s)",
               "track work / anchor tracks", "reprojection RMS at the anchors (px)",
               "exported, in the refined cameras (px)"]  # fmt: skip
    sections = [
        "Wall time of `s2camp-export-cameras` in a fresh process (Python and nerfstudio's imports included) on a "
        "run of `ns-train s2camp`: loading it with the track work (the run without its file, as a run of an "
        "earlier version loads once: built as for training, the data parser makes the tracks, their re-adjustment "
        "read from its cache, and the anchors are fitted) against loading the run's "
        f"`{ANCHOR_TRACKS_FILE}` (no track work). The export itself (re-triangulation, colours, files) is in both. "
        "The exported points' reprojection RMS in the exported cameras (pycolmap's projection) beside the anchor "
        "fit's over the same observations.",
        markdown_table(rows, columns, headers),
    ]
    return write_report(config.output_dir, "export-load", "Loading a trained run for export", config.command(),
                        sections)  # fmt: skip
