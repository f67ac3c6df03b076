"""``ns-render interpolate`` on runs whose pose source holds a single camera (the eval split of a scene of at most
eight images).

nerfstudio's ``get_interpolated_poses_many`` stacks ``--interpolation-steps`` poses per pair of consecutive cameras,
so with one camera it fails with numpy's "need at least one array to stack". ``interpolated_poses_many`` holds that
camera for ``--interpolation-steps`` frames instead, and refuses no camera or fewer than one step naming the
``ns-render`` option; two cameras or more go to nerfstudio's function. ``S2CampPipeline`` calls ``install``.
"""

from __future__ import annotations

import operator

import torch
from jaxtyping import Float
from nerfstudio.cameras import camera_paths, camera_utils
from torch import Tensor

_INSTALLED = "_s2camp_single_camera_path"
"""Marks the function ``install`` puts in place (a second install is a no-op)."""
_ORIGINAL = "_s2camp_nerfstudio_get_interpolated_poses_many"
"""Where ``install`` keeps nerfstudio's function, on nerfstudio's module (a reload of this one cannot lose it)."""


def interpolated_poses_many(
    poses: Float[Tensor, "num_poses 3 4"],
    Ks: Float[Tensor, "num_poses 3 3"],
    steps_per_transition: int = 10,
    order_poses: bool = False,
) -> tuple[Float[Tensor, "num_frames 3 4"], Float[Tensor, "num_frames 3 3"]]:
    """nerfstudio's ``get_interpolated_poses_many`` (same arguments, float32 CPU results), also for one pose: that
    pose and its K repeated ``steps_per_transition`` times, with a note. ValueError for no pose or < 1 step."""
    try:
        steps = None if isinstance(steps_per_transition, bool) else operator.index(steps_per_transition)
    except TypeError:
        steps = None
    if steps is None or steps < 1:
        raise ValueError(
            "the camera path needs at least 1 frame per camera: ns-render interpolate --interpolation-steps must be "
            f"an integer >= 1, got {steps_per_transition!r}"
        )
    count = int(poses.shape[0])
    if count == 0:
        raise ValueError(
            "no camera to interpolate: the pose source of ns-render interpolate (--pose-source eval or train) holds "
            "no camera; use the other one, or change the split (the data parser's eval_mode / eval_interval)"
        )
    if count > 1:
        nerfstudio = getattr(camera_utils, _ORIGINAL, camera_utils.get_interpolated_poses_many)
        return nerfstudio(poses, Ks, steps_per_transition=steps, order_poses=order_poses)
    _note_single_camera(steps)
    pose = poses[0].detach().to(device="cpu", dtype=torch.float32)
    k = Ks[0].detach().to(device="cpu", dtype=torch.float32)
    return pose.expand(steps, 3, 4).clone(), k.expand(steps, 3, 3).clone()


setattr(interpolated_poses_many, _INSTALLED, True)


def _note_single_camera(steps: int) -> None:
    from nerfstudio.utils.rich_utils import CONSOLE

    CONSOLE.print(
        "[bold yellow]ns-render interpolate: the pose source holds a single camera (with eval_mode interval, the "
        "eval split of a scene of at most eval_interval images), so the video holds that view for the "
        f"{steps} frames of --interpolation-steps. --pose-source train moves through the training cameras; a smaller "
        "s2camp-data --eval-interval at training time holds out more views."
    )


def install() -> bool:
    """Put ``interpolated_poses_many`` in nerfstudio's place (``camera_utils``, ``camera_paths``); False if done."""
    if getattr(camera_paths.get_interpolated_poses_many, _INSTALLED, False):
        return False
    if not hasattr(camera_utils, _ORIGINAL):
        setattr(camera_utils, _ORIGINAL, camera_utils.get_interpolated_poses_many)
    camera_utils.get_interpolated_poses_many = interpolated_poses_many
    camera_paths.get_interpolated_poses_many = interpolated_poses_many
    return True


__all__ = ["install", "interpolated_poses_many"]
