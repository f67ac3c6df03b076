"""Data manager whose training rays carry their pixel coordinates, so the camera optimizer can regenerate them.

nerfstudio's ``RayGenerator`` turns sampled ``ray_indices`` [camera, y, x] into rays with fixed intrinsics; the
stock camera optimizer can then only move origins and directions rigidly. ``PixelRayGenerator`` also stores the
continuous pixel centre (u, v) = (x + 0.5, y + 0.5) (OpenCV/COLMAP convention) in
``ray_bundle.metadata[PIXEL_KEY]``; ``S2CampCameraOptimizer.apply_to_raybundle`` rebuilds each ray from it with
the refined intrinsics, distortion and pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from jaxtyping import Int
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.model_components.ray_generators import RayGenerator
from torch import Tensor

from s2camp_ns.camera_optimizer import PIXEL_KEY


class PixelRayGenerator(RayGenerator):
    """nerfstudio's ray generator plus each ray's pixel coordinates in the ray bundle's metadata."""

    def forward(self, ray_indices: Int[Tensor, "num_rays 3"]) -> RayBundle:
        ray_bundle = super().forward(ray_indices)
        rows, cols = ray_indices[:, 1], ray_indices[:, 2]
        pixels = torch.stack([cols, rows], dim=-1).to(ray_bundle.origins.dtype) + 0.5
        if ray_bundle.metadata is None:
            ray_bundle.metadata = {}
        ray_bundle.metadata[PIXEL_KEY] = pixels
        return ray_bundle


@dataclass
class S2CampDataManagerConfig(VanillaDataManagerConfig):
    """nerfstudio's VanillaDataManager whose training rays carry pixel coordinates for intrinsics refinement."""

    _target: type = field(default_factory=lambda: S2CampDataManager)


class S2CampDataManager(VanillaDataManager[InputDataset]):
    """VanillaDataManager with ``PixelRayGenerator`` for the training rays (eval rays are left unchanged)."""

    config: S2CampDataManagerConfig

    def setup_train(self):
        super().setup_train()
        assert self.train_dataset is not None
        self.train_ray_generator = PixelRayGenerator(self.train_dataset.cameras.to(self.device))
