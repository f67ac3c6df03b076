"""nerfstudio's VanillaPipeline that hands the training cameras to the S2CamP camera optimizer and owns DDP.

The model is built before any camera is known to it (nerfstudio passes only num_train_data), but the
preconditioner and the ray regeneration need the base cameras; the pipeline owns both data manager and model. Where a
full-image data manager (splatfacto's) undistorted the training images, the model gets the pinhole cameras it wrote
and the tracks' keypoints moved into those images (``undistorted_tracks``).

With several processes (``--machine.num-devices``) the pipeline wraps the model in DDP itself instead of
VanillaPipeline, for two reasons (docs/SCALING.md):

- ``broadcast_buffers=False``: DDP would otherwise send rank 0's buffers to every rank before each forward,
  among them P, P^-1 and Sigma (3 x N x K x K float64, 10 MB per step for 3000 cameras). P is computed on every
  rank from the same refined intrinsics with the same deterministic proxy points, so every rank already holds the
  same bits (tests/test_distributed.py asserts it); nerfacto's own buffers are constants (aabb, sizes). Worse, the
  broadcast would hand rank 0's P to ranks that did not re-express their latent with it.
- ``device_ids`` only on CUDA: nerfstudio passes ``device_ids=[local_rank]`` to DDP and to ``dist.barrier``, which
  a CPU module and the gloo backend reject, so multi-process training on the CPU (the tests) needs this.

The launcher stays nerfstudio's on CUDA; ``s2camp_ns.nerfstudio.distributed`` has the CPU one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from jaxtyping import Float
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor
from torch.cuda.amp.grad_scaler import GradScaler
from torch.nn.parallel import DistributedDataParallel

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer
from s2camp_ns.nerfstudio import bundled_ffmpeg, render_path
from s2camp_ns.nerfstudio.camera_conversion import intrinsics_from_cameras
from s2camp_ns.nerfstudio.camera_fields import has_distortion, replace_cameras
from s2camp_ns.nerfstudio.datamanager import PixelRayGenerator
from s2camp_ns.nerfstudio.undistorted_tracks import undistorted_track_evidence

CAMERA_COUNT_KEYS = (
    "camera_optimizer.refiner.precond",  # S2CamP's P, one per training camera [N, K, K]
    "camera_optimizer.precond",  # the same, in checkpoints written before the refiner became a submodule
    "camera_optimizer.pose_adjustment",  # nerfstudio's SO3xR3 / SE3 deltas [N, 6] (s2camp-so3xr3)
    "field.embedding_appearance.embedding.weight",  # nerfacto's appearance code per training image [N, d]
)
"""Pipeline state-dict entries (after any ``_model.`` / ``module.`` prefix) whose first dimension is the number of
training cameras, in the order they are looked up."""


class CheckpointCamerasError(ValueError):
    """A checkpoint trained on another number of training cameras than the data at hand."""


def checkpoint_camera_count(state: Mapping[str, Any]) -> int | None:
    """Number of training cameras a pipeline state dict was trained on (``CAMERA_COUNT_KEYS``), None if it holds none
    of those entries."""
    for suffix in CAMERA_COUNT_KEYS:
        for key, value in state.items():
            if (key == suffix or key.endswith("." + suffix)) and hasattr(value, "shape"):
                return int(value.shape[0])
    return None


def check_checkpoint_cameras(state: Mapping[str, Any], num_train_cameras: int, data: Path | None = None) -> None:
    """Refuse a checkpoint of another scene (or split) before torch does: its per-camera tensors cannot be loaded
    onto this data's cameras, and torch's error is a list of size mismatches that never says why."""
    saved = checkpoint_camera_count(state)
    if saved is None or saved == num_train_cameras:
        return
    where = f" ({data})" if data is not None else ""
    raise CheckpointCamerasError(
        f"the checkpoint was trained on {saved} training cameras, but the data{where} has {num_train_cameras}: it is "
        "a checkpoint of another scene or of another train/eval split (eval_mode, eval_interval); load a checkpoint "
        "of this scene and split, or train without --load-dir / --load-checkpoint"
    )


def undistortion_scale(datamanager) -> tuple[Float[Tensor, "n 1"], Float[Tensor, "n 1"]]:
    """fx and fy of each training camera after a full-image data manager undistorted its image, over the
    dataparser's (1 where an image was left alone): the argument of ``S2CampSplatModel.set_undistortion_scale``."""
    seen, given = datamanager.train_dataset.cameras, datamanager.train_dataparser_outputs.cameras
    return seen.fx / given.fx, seen.fy / given.fy


@dataclass
class S2CampPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline that gives the S2CamP camera optimizer its training cameras."""

    _target: type = field(default_factory=lambda: S2CampPipeline)


class S2CampPipeline(VanillaPipeline):
    """VanillaPipeline + ``camera_optimizer.set_train_cameras`` with the scene's points (before any checkpoint is
    loaded) + its own DDP + a checkpoint of another scene refused by name (``check_checkpoint_cameras``) + the camera
    path of ``ns-render interpolate`` defined for a pose source of one camera (``render_path.install``) + an ffmpeg
    for ``ns-render`` where the machine has none (``bundled_ffmpeg.use_bundled_ffmpeg``)."""

    def __init__(
        self,
        config: S2CampPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: GradScaler | None = None,
    ):
        # eval_setup (ns-render) builds this pipeline before the render checks for ffmpeg and computes its path.
        render_path.install()
        bundled_ffmpeg.use_bundled_ffmpeg()
        if str(device).startswith("cpu") and not torch.cuda.is_available():
            CONSOLE.print("[bold yellow]CUDA is not available: training on the CPU (expect about 1 s per iteration).")
        # world_size=1 keeps VanillaPipeline from wrapping the model (see the module docstring); its data manager
        # uses the world size only for the number of image-loading workers.
        super().__init__(config, device, test_mode, 1, local_rank, grad_scaler)
        assert self.datamanager.train_dataset is not None
        cameras = self.datamanager.train_dataset.cameras
        # The dataparser's sparse points (normalized world, as the cameras) choose the proxy range per camera.
        metadata = getattr(self.datamanager.train_dataset, "metadata", None) or {}
        points = metadata.get("points3D_xyz")
        # The SfM tracks give the optimizer's track prior its anchor and scale.
        tracks = {"track_rms_px": metadata.get("track_rms_px"), "track_evidence": metadata.get("track_evidence")}
        if has_distortion(cameras) and hasattr(type(self.datamanager), "cached_train"):
            # A full-image data manager (splatfacto's) undistorts the images when it first caches them and writes
            # the undistorted K into the training cameras; the camera optimizer must start from those, and the
            # tracks' keypoints move into the undistorted images with them.
            given = intrinsics_from_cameras(self.datamanager.train_dataparser_outputs.cameras)
            _ = self.datamanager.cached_train
            if hasattr(self.model, "set_undistortion_scale"):
                self.model.set_undistortion_scale(*undistortion_scale(self.datamanager))
            cameras = replace_cameras(cameras, distortion_params=None)
            if tracks["track_evidence"] is not None:
                tracks["track_evidence"] = undistorted_track_evidence(
                    tracks["track_evidence"], given, intrinsics_from_cameras(cameras)
                )
        if hasattr(self.model, "set_train_cameras"):
            self.model.set_train_cameras(cameras, points=points, **tracks)
        elif isinstance(getattr(self.model, "camera_optimizer", None), S2CampCameraOptimizer):
            self.model.camera_optimizer.set_train_cameras(cameras, points=points)
            self.model.camera_optimizer.set_track_prior(tracks["track_rms_px"], tracks["track_evidence"])
        # The S2CamP camera optimizer casts the training rays itself, through the refined cameras.
        camera_optimizer = getattr(self.model, "camera_optimizer", None)
        generator = getattr(self.datamanager, "train_ray_generator", None)
        refining = isinstance(camera_optimizer, S2CampCameraOptimizer) and camera_optimizer.enabled
        if refining and isinstance(generator, PixelRayGenerator):
            generator.cast_by_model = True
        self.world_size = world_size
        if world_size > 1:
            on_cuda = torch.device(device).type == "cuda"
            # DDP's constructor sends rank 0's parameters to every rank (each rank initialised the field with its
            # own seed); from then on only gradients are averaged, in backward.
            self._model = DistributedDataParallel(
                self._model,
                device_ids=[local_rank] if on_cuda else None,
                find_unused_parameters=True,
                broadcast_buffers=False,
            )
            comms.synchronize()

    def load_pipeline(self, loaded_state: dict[str, Any], step: int) -> None:
        """VanillaPipeline's loading (training ``--load-dir``, and ``eval_setup`` of ns-render, ns-eval, s2camp-eval)
        after checking the checkpoint has as many training cameras as the data."""
        data = getattr(self.datamanager.config, "data", None) or getattr(
            getattr(self.datamanager.config, "dataparser", None), "data", None
        )
        check_checkpoint_cameras(loaded_state, self.model.num_train_data, data)
        super().load_pipeline(loaded_state, step)
