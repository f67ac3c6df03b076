"""Which line the camera optimizer's warnings name (their ``stacklevel``): the stale-checkpoint warning and the
pose-only warning for rays without pixel coordinates.

Kept out of the mutation run's test selection (``[tool.mutmut]`` in pyproject.toml): mutmut's trampolines add
frames to every call, so under mutmut a warning names a trampoline whatever its stacklevel (docs/mutation-testing.md).
"""

from __future__ import annotations

import inspect

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.cameras.rays import RayBundle

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer, S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.core.refiner import CameraRefiner


def _cameras(fx: float) -> Cameras:
    c2w = torch.zeros(2, 3, 4)
    c2w[:, :, :3] = torch.eye(3)
    c2w[:, :, 3] = torch.tensor([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0]])
    return Cameras(
        camera_to_worlds=c2w, fx=fx, fy=fx, cx=32.0, cy=24.0, width=64, height=48, camera_type=CameraType.PERSPECTIVE
    )


def _optimizer() -> S2CampCameraOptimizer:
    sampling = SamplingConfig(num_points=64, sampler="camp-random")
    config = S2CampCameraOptimizerConfig(sampling=sampling, intrinsics="per-image")
    return config.setup(num_cameras=2, device="cpu")


def _assert_names_a_line_of(record: pytest.WarningsRecorder, function) -> None:
    lines, first = inspect.getsourcelines(function)
    assert record[0].filename == inspect.getsourcefile(function)
    assert first <= record[0].lineno < first + len(lines)


def test_a_stale_checkpoint_warning_names_the_loading_line():
    """Loaded after the cameras: the warning names the refiner's ``_load_from_state_dict`` (stacklevel 2), not the
    check itself (stacklevel 1) nor torch's loader that called it (stacklevel 3)."""
    saved = _optimizer()
    saved.set_train_cameras(_cameras(60.0))
    resumed = _optimizer()
    resumed.set_train_cameras(_cameras(63.0))
    with pytest.warns(UserWarning, match="differ from those its P was computed for") as record:
        resumed.load_state_dict(saved.state_dict())
    _assert_names_a_line_of(record, CameraRefiner._load_from_state_dict)


def test_a_checkpoint_loaded_before_the_cameras_warns_from_set_train_cameras():
    saved = _optimizer()
    saved.set_train_cameras(_cameras(60.0))
    resumed = _optimizer()
    resumed.load_state_dict(saved.state_dict())
    with pytest.warns(UserWarning, match="differ from those its P was computed for") as record:
        resumed.set_train_cameras(_cameras(63.0))
    _assert_names_a_line_of(record, S2CampCameraOptimizer.set_train_cameras)


def test_the_pose_only_warning_names_the_line_in_apply_to_raybundle():
    """Rays without pixel coordinates: the warning names ``apply_to_raybundle``, not its caller."""
    optimizer = _optimizer()
    optimizer.set_train_cameras(_cameras(60.0))
    bundle = RayBundle(
        origins=torch.zeros(4, 3),
        directions=torch.tensor([[0.0, 0.0, -1.0]]).expand(4, 3).clone(),
        pixel_area=torch.ones(4, 1),
        camera_indices=torch.zeros(4, 1, dtype=torch.long),
        metadata={},
    )
    with pytest.warns(UserWarning, match="carries no") as record:
        optimizer.apply_to_raybundle(bundle)
    _assert_names_a_line_of(record, S2CampCameraOptimizer.apply_to_raybundle)
