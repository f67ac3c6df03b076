"""The scene the GPU check and the regime command train on, and its image tracks, made before any training.

    python -m s2camp_bench.gpu_check.scene_stage SCENE_DIR    # build the image tracks' cache entry

The scene is generated once and reused by a later command with the same settings (``common.generated_scene``). The
image tracks of its perturbed training cameras (``s2camp-data --perturbation.enabled True``: tracks made from the
images with the perturbed cameras, cached in the scene folder) are built in a process of their own, so that every
training run finds them cached and no timed run builds them.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig

from .processes import Deadline, failure, run_logged
from .records import StageResult

STAGE = "scene"


def prepare_scene(scene: MakeSceneConfig, scene_dir: Path, log_path: Path, deadline: Deadline) -> StageResult:
    """The scene (generated or reused) and its image tracks' cache entry (``build_tracks`` in a process of its own,
    stopped at the deadline)."""
    from s2camp_bench.common import generated_scene

    began = time.perf_counter()
    what = f"{scene.num_cameras} images {scene.width}x{scene.height}"
    try:
        generated_scene(replace(scene, output_dir=scene_dir))
    except (ValueError, RuntimeError) as error:
        return StageResult(STAGE, False, f"s2camp-make-scene failed: {error}", time.perf_counter() - began)
    made = time.perf_counter()
    timeout_s = deadline.remaining()
    status = run_logged([sys.executable, "-m", __spec__.name, str(scene_dir)], log_path, timeout_s)
    seconds = time.perf_counter() - began
    detail = f"{what} in {made - began:.0f} s"
    if status != 0:
        return StageResult(STAGE, False, f"{detail}; {failure('image tracks', status, log_path, timeout_s)}", seconds)
    return StageResult(STAGE, True, f"{detail}; image tracks ready in {time.perf_counter() - made:.0f} s", seconds)


def build_tracks(scene_dir: Path) -> None:
    """Parse the scene's training split as every run does (CamP's perturbation on, image tracks "auto"): a missing
    cache entry of the image tracks is built and written into the scene folder."""
    from s2camp_ns.core.perturbation import PerturbationConfig
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    parser = S2CampDataParserConfig(data=scene_dir, perturbation=PerturbationConfig(enabled=True)).setup()
    outputs = parser.get_dataparser_outputs("train")
    if outputs.metadata.get("track_evidence") is None:
        raise SystemExit(f"no image tracks were made for {scene_dir}: the track prior would have no evidence")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(f"usage: python -m {__spec__.name} SCENE_DIR, got {sys.argv[1:]}")
    build_tracks(Path(sys.argv[1]))
