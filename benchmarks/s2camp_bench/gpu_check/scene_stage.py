"""The scene the GPU check and the regime command train on, and its image tracks, made before any training.

    python -m s2camp_bench.gpu_check.scene_stage SCENE_DIR    # build the image tracks' cache entry

The scene is generated once and reused by a later command with the same settings (``scene_is_current``). The image
tracks of its perturbed training cameras (``s2camp-data --perturbation.enabled True``: tracks made from the images
with the perturbed cameras, cached in the scene folder) are built in a process of their own, so that every training
run finds them cached and the runs that start side by side do not build them at once.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

from .processes import Deadline, failure, run_logged
from .records import StageResult

STAGE = "scene"


def scene_is_current(scene: MakeSceneConfig, scene_dir: Path) -> bool:
    """Whether ``scene_dir`` holds a finished scene generated with exactly ``scene`` (then it is reused)."""
    info_path = scene_dir / "scene_info.json"
    if not info_path.is_file():
        return False
    wanted = dataclasses.asdict(replace(scene, output_dir=scene_dir))
    wanted = {key: (str(value) if isinstance(value, Path) else value) for key, value in wanted.items()}
    stored = json.loads(info_path.read_text())["config"]
    return json.loads(json.dumps(wanted)) == stored


def generate_scene(scene: MakeSceneConfig, scene_dir: Path) -> tuple[bool, str]:
    """Generate ``scene`` into ``scene_dir``, or reuse the one there with the same settings; (done, what happened)."""
    what = f"{scene.num_cameras} images {scene.width}x{scene.height}"
    if scene_is_current(scene, scene_dir):
        return True, f"{what}, reused from {scene_dir}"
    began = time.perf_counter()
    try:
        make_scene(replace(scene, output_dir=scene_dir))
    except (ValueError, RuntimeError) as error:
        return False, f"s2camp-make-scene failed: {error}"
    return True, f"{what}, generated in {time.perf_counter() - began:.0f} s"


def prepare_scene(scene: MakeSceneConfig, scene_dir: Path, log_path: Path, deadline: Deadline) -> StageResult:
    """The scene (generated or reused) and its image tracks' cache entry (``build_tracks`` in a process of its own,
    stopped at the deadline)."""
    began = time.perf_counter()
    done, detail = generate_scene(scene, scene_dir)
    if not done:
        return StageResult(STAGE, False, detail, time.perf_counter() - began)
    tracks_began = time.perf_counter()
    timeout_s = deadline.remaining()
    status = run_logged([sys.executable, "-m", __spec__.name, str(scene_dir)], log_path, timeout_s)
    seconds = time.perf_counter() - began
    if status != 0:
        return StageResult(STAGE, False, f"{detail}; {failure('image tracks', status, log_path, timeout_s)}", seconds)
    tracks = f"image tracks ready in {time.perf_counter() - tracks_began:.0f} s"
    return StageResult(STAGE, True, f"{detail}; {tracks}", seconds)


def build_tracks(scene_dir: Path) -> None:
    """Parse the scene's training split as every run of the check does (CamP's perturbation on, image tracks
    "auto"): a missing cache entry of the image tracks is built and written into the scene folder."""
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
