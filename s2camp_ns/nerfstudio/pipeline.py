"""nerfstudio's VanillaPipeline that hands the training cameras to the S2CamP camera optimizer.

The model is built before any camera is known to it (nerfstudio passes only num_train_data), but the
preconditioner and the ray regeneration need the base cameras; the pipeline owns both data manager and model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch.cuda.amp.grad_scaler import GradScaler

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer


@dataclass
class S2CampPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline that gives the S2CamP camera optimizer its training cameras."""

    _target: type = field(default_factory=lambda: S2CampPipeline)


class S2CampPipeline(VanillaPipeline):
    """VanillaPipeline + ``camera_optimizer.set_train_cameras`` (before any checkpoint is loaded)."""

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
        super().__init__(config, device, test_mode, world_size, local_rank, grad_scaler)
        assert self.datamanager.train_dataset is not None
        cameras = self.datamanager.train_dataset.cameras
        if hasattr(self.model, "set_train_cameras"):
            self.model.set_train_cameras(cameras)
        elif isinstance(getattr(self.model, "camera_optimizer", None), S2CampCameraOptimizer):
            self.model.camera_optimizer.set_train_cameras(cameras)
