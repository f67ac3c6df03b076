"""nerfstudio's VanillaPipeline that hands the training cameras to the S2CamP camera optimizer and owns DDP.

The model is built before any camera is known to it (nerfstudio passes only num_train_data), but the
preconditioner and the ray regeneration need the base cameras; the pipeline owns both data manager and model.

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

from dataclasses import dataclass, field
from typing import Literal

import torch
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE
from torch.cuda.amp.grad_scaler import GradScaler
from torch.nn.parallel import DistributedDataParallel

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer


@dataclass
class S2CampPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline that gives the S2CamP camera optimizer its training cameras."""

    _target: type = field(default_factory=lambda: S2CampPipeline)


class S2CampPipeline(VanillaPipeline):
    """VanillaPipeline + ``camera_optimizer.set_train_cameras`` with the scene's points (before any checkpoint is
    loaded) + its own DDP."""

    def __init__(
        self,
        config: S2CampPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: GradScaler | None = None,
    ):
        if str(device).startswith("cpu") and not torch.cuda.is_available():
            CONSOLE.print("[bold yellow]CUDA is not available: training on the CPU (expect about 1 s per iteration).")
        # world_size=1 keeps VanillaPipeline from wrapping the model (see the module docstring); its data manager
        # uses the world size only for the number of image-loading workers.
        super().__init__(config, device, test_mode, 1, local_rank, grad_scaler)
        assert self.datamanager.train_dataset is not None
        cameras = self.datamanager.train_dataset.cameras
        distorted = cameras.distortion_params is not None and bool((cameras.distortion_params != 0).any())
        if distorted and hasattr(type(self.datamanager), "cached_train"):
            # A full-image data manager (splatfacto's) undistorts the images when it first caches them and writes
            # the undistorted K into the training cameras; the camera optimizer must start from those.
            _ = self.datamanager.cached_train
        # The dataparser's sparse points (normalized world, as the cameras) choose the proxy range per camera.
        metadata = getattr(self.datamanager.train_dataset, "metadata", None) or {}
        points = metadata.get("points3D_xyz")
        # Each camera's reprojection error against the SfM tracks scales the optimizer's track prior.
        track_rms = metadata.get("track_rms_px")
        if hasattr(self.model, "set_train_cameras"):
            self.model.set_train_cameras(cameras, points=points, track_rms_px=track_rms)
        elif isinstance(getattr(self.model, "camera_optimizer", None), S2CampCameraOptimizer):
            self.model.camera_optimizer.set_train_cameras(cameras, points=points)
            self.model.camera_optimizer.set_track_prior(track_rms)
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
