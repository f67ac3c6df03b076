"""Building and training an S2CamP run changes no module of nerfstudio or of a dependency: another method
in the same process sees them as they were (the plugin extends nerfstudio through its entry points and subclasses).

A fresh process imports the modules a run touches, records every public attribute of every loaded third-party module and
the environment's PATH, builds ``s2camp`` and ``s2camp-splat`` trainers on the tiny scene as ``ns-train`` does (data
parser, pipeline, model, camera optimizer; LPIPS offline, so the splat model takes its path without it), trains a step
each, and compares. The check can fail: a patch made in the child is found.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, os, sys
from pathlib import Path

import mediapy, torchmetrics.image.lpip  # noqa: F401  the modules earlier versions changed
import nerfstudio.cameras.camera_paths, nerfstudio.cameras.camera_utils  # noqa: F401
import nerfstudio.data.dataparsers.colmap_dataparser, nerfstudio.models.splatfacto, nerfstudio.utils.eval_utils  # noqa
import nerfstudio.scripts.render  # noqa: F401

OURS = ("s2camp_ns", "s2camp_bench", "__main__")


def snapshot() -> dict:
    state = {"environment": dict(os.environ)}
    for name, module in list(sys.modules.items()):
        if module is None or name.startswith(OURS) or name == "builtins":
            continue
        try:
            attributes = dict(vars(module))
        except TypeError:
            continue
        # Public names: a library's private state (a lazily made console, a name generator) is its own to change.
        state[name] = {key: id(value) for key, value in attributes.items() if not key.startswith("_")}
    return state


before = snapshot()
if sys.argv[2] == "patch":  # the check's own test: what a patch looks like
    nerfstudio.cameras.camera_utils.get_interpolated_poses_many = print
    os.environ["PATH"] = "/nowhere" + os.pathsep + os.environ["PATH"]
else:
    from s2camp_bench.step_cost import build_trainer, training_step

    def offline(*args, **kwargs):
        raise OSError("no network (simulated)")

    lpips, torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity = (
        torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity, offline
    )
    for method in ("s2camp", "s2camp-splat"):
        trainer = build_trainer(method, Path(sys.argv[1]), Path(sys.argv[3]), "per-camera", rays_per_batch=64)
        training_step(trainer, 0)
    torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity = lpips
after = snapshot()
changed = sorted(
    f"{name}.{key}"
    for name, attributes in before.items()
    for key, value in attributes.items()
    if name in after and after[name].get(key, value) != value and (name != "environment" or key == "PATH")
)
print(json.dumps(changed))
"""


def _changes(scene: Path, work: Path, mode: str) -> list[str]:
    result = subprocess.run(
        [sys.executable, "-c", CHILD, str(scene), mode, str(work)], capture_output=True, text=True, timeout=900
    )
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_a_run_changes_no_module_of_nerfstudio_or_a_dependency(tiny_scene: Path, tmp_path: Path) -> None:
    assert _changes(tiny_scene, tmp_path, "train") == []


def test_the_check_finds_a_patch(tiny_scene: Path, tmp_path: Path) -> None:
    changes = _changes(tiny_scene, tmp_path, "patch")
    assert "nerfstudio.cameras.camera_utils.get_interpolated_poses_many" in changes
    assert "environment.PATH" in changes
