"""Shared fixtures: tiny synthetic scenes in the mip-NeRF 360 layout (generated once per test session).

The scene module is imported inside the fixtures, so a broken import there fails the tests that use the scene,
not the collection of the whole suite.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    import pycolmap
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

    from s2camp_bench.scene.make_scene import MakeSceneConfig
    from s2camp_ns.method.model import S2CampModelConfig

CUDA_SKIP_REASON = (
    "needs a CUDA device and torch.cuda.is_available() is False here; these tests run on a GPU machine with "
    "`make gpu-check` (docs/GPU-CHECK.md)"
)
"""The one reason a test of this suite may skip: it is marked ``cuda`` and the machine has no CUDA device."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip the tests marked ``cuda`` where there is no CUDA device, with CUDA_SKIP_REASON; nothing else."""
    cuda_items = [item for item in items if item.get_closest_marker("cuda") is not None]
    if not cuda_items:
        return
    import torch

    if torch.cuda.is_available():
        return
    for item in cuda_items:
        item.add_marker(pytest.mark.skip(reason=CUDA_SKIP_REASON))


@pytest.fixture(scope="session", autouse=True)
def user_cache_of_the_session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The user's cache folder (``XDG_CACHE_HOME``: the image tracks' fallback and the re-adjusted SfM points,
    ``track_cache.user_cache_folder``) in a folder of the session, for the tests and the processes they start: the
    suite writes nothing to the user's ~/.cache and reads no entry of another session."""
    patch = pytest.MonkeyPatch()
    patch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("xdg_cache")))
    yield
    patch.undo()


TINY_SCENE = {"num_cameras": 12, "width": 64, "height": 48, "points_per_image": 150, "seed": 0}
"""Config of the session scene: about a second to generate, small enough for CPU training smoke tests."""


@pytest.fixture(scope="session")
def tiny_scene_config(tmp_path_factory: pytest.TempPathFactory) -> MakeSceneConfig:
    from s2camp_bench.scene.make_scene import MakeSceneConfig

    return MakeSceneConfig(output_dir=tmp_path_factory.mktemp("tiny_scene") / "scene", **TINY_SCENE)


@pytest.fixture(scope="session")
def tiny_scene(tiny_scene_config: MakeSceneConfig) -> Path:
    """Directory of a generated 12-camera 64x48 scene (images/, images_2/, sparse/0/, poses_bounds.npy).

    Shared by the whole session: treat it as read-only.
    """
    from s2camp_bench.scene.make_scene import make_scene

    return make_scene(tiny_scene_config)


PARSER_SCENE = {"num_cameras": 10, "width": 50, "height": 38, "supersample": 1, "points_per_image": 30}
"""Config of the data parsers' scene: 50 x 38 so that a quarter-size folder must round (12.5 x 9.5 -> 13 x 10), like
mip-NeRF 360's images_4."""


@pytest.fixture(scope="session")
def generated_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Directory of a generated ``PARSER_SCENE`` scene, shared by the session: read-only (``scene`` to modify)."""
    from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

    return make_scene(MakeSceneConfig(output_dir=tmp_path_factory.mktemp("scene") / "tiny", **PARSER_SCENE))


@pytest.fixture
def scene(generated_scene: Path, tmp_path: Path) -> Path:
    """A private copy of ``generated_scene`` that a test may modify."""
    return Path(shutil.copytree(generated_scene, tmp_path / "scene"))


@pytest.fixture
def given(tiny_scene: Path) -> pycolmap.Reconstruction:
    """The tiny scene's cameras and poses, no points: what the image tracks are asked for."""
    import pycolmap

    truth = pycolmap.Reconstruction(tiny_scene / "sparse" / "0")
    cameras = pycolmap.Reconstruction()
    for camera in truth.cameras.values():
        cameras.add_camera_with_trivial_rig(camera)
    for image in truth.images.values():
        posed = pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id)
        cameras.add_image_with_trivial_frame(posed, image.cam_from_world())
    return cameras


@contextlib.contextmanager
def lpips_offline() -> Iterator[None]:
    """Make nerfacto's LPIPS fail to load, as it does offline without cached AlexNet weights."""
    import torchmetrics.image.lpip as lpip_module

    original = lpip_module.LearnedPerceptualImagePatchSimilarity

    def offline(*args, **kwargs):
        raise OSError("no network (simulated)")

    lpip_module.LearnedPerceptualImagePatchSimilarity = offline
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


def tiny_model_config(
    camera_optimizer: CameraOptimizerConfig,
    num_levels: int = 2,
    log2_hashmap_size: int = 10,
    hidden_dim: int = 8,
    samples_per_ray: int = 8,
    **fields,
) -> S2CampModelConfig:
    """A sized-down nerfacto (S2CampModelConfig) for CPU unit tests: torch hash grids, two 2-level proposal nets."""
    from s2camp_ns.method.model import S2CampModelConfig

    proposal_net = {"hidden_dim": 8, "log2_hashmap_size": 10, "num_levels": 2, "max_res": 32, "use_linear": False}
    return S2CampModelConfig(
        num_levels=num_levels,
        log2_hashmap_size=log2_hashmap_size,
        hidden_dim=hidden_dim,
        hidden_dim_color=hidden_dim,
        num_nerf_samples_per_ray=samples_per_ray,
        num_proposal_samples_per_ray=(samples_per_ray, samples_per_ray),
        proposal_net_args_list=[dict(proposal_net), dict(proposal_net)],
        implementation="torch",
        camera_optimizer=camera_optimizer,
        **fields,
    )


def write_transforms(scene: Path, data: Path, **meta) -> Path:
    """A transforms.json in the folder ``data`` of the COLMAP scene ``scene``'s cameras (global intrinsics and w/h,
    OPENCV), with a copy of its full-size images; ``meta`` overrides top-level keys."""
    import numpy as np
    import pycolmap

    shutil.copytree(scene / "images", data / "images")
    reconstruction = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    frames = []
    for image_id in sorted(reconstruction.images):
        image = reconstruction.images[image_id]
        c2w = np.linalg.inv(np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]]))
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": c2w.tolist()})
    camera = reconstruction.cameras[1]
    f, cx, cy, k1, k2 = camera.params
    content = {"camera_model": "OPENCV", "fl_x": f, "fl_y": f, "cx": cx, "cy": cy, "w": camera.width}
    content.update(h=camera.height, k1=k1, k2=k2, p1=0.0, p2=0.0, frames=frames, **meta)
    (data / "transforms.json").write_text(json.dumps(content))
    return data / "transforms.json"
