"""Data manager whose training rays carry their pixel coordinates, so the camera optimizer can cast them.

``PixelRayGenerator`` stores each ray's pixel centre (u, v) = (x + 0.5, y + 0.5) (OpenCV/COLMAP convention) in
``ray_bundle.metadata[PIXEL_KEY]``. Where the model's camera optimizer casts the rays itself (S2CamP's, refining;
told so by the pipeline) the generator casts nothing, so a ray is cast once per step, through the refined cameras.

With several processes each rank draws its own rays (seed ``machine.seed`` + rank); ``global_batch_sampling`` makes a
step's rays independent of the number of ranks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from jaxtyping import Int
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.model_components.ray_generators import RayGenerator
from nerfstudio.utils import comms
from torch import Tensor

from s2camp_ns.method.rays import PIXEL_KEY


class PixelRayGenerator(RayGenerator):
    """nerfstudio's ray generator plus each ray's pixel coordinates [R, 2] in the ray bundle's metadata.

    ``cast_by_model``: the bundle carries camera indices and pixels only, its origins, directions and pixel areas NaN
    until the model's camera optimizer casts them.
    """

    cast_by_model: bool = False

    def forward(self, ray_indices: Int[Tensor, "num_rays 3"]) -> RayBundle:
        # The indices are on the cached images' device; the pixels go with the rays, on the model's device.
        device = self.image_coords.device
        rows, cols = ray_indices[:, 1], ray_indices[:, 2]
        pixels = torch.stack([cols, rows], dim=-1).to(device=device, dtype=torch.float32) + 0.5
        if self.cast_by_model:
            unset = torch.full((ray_indices.shape[0], 3), float("nan"), device=device)
            camera_indices = ray_indices[:, :1].to(device)
            return RayBundle(unset, unset, unset[:, :1], camera_indices, metadata={PIXEL_KEY: pixels})
        ray_bundle = super().forward(ray_indices)
        if ray_bundle.metadata is None:
            ray_bundle.metadata = {}
        ray_bundle.metadata[PIXEL_KEY] = pixels.to(ray_bundle.origins.dtype)
        return ray_bundle


@dataclass
class S2CampDataManagerConfig(VanillaDataManagerConfig):
    """nerfstudio's VanillaDataManager whose training rays carry pixel coordinates for intrinsics refinement."""

    _target: type = field(default_factory=lambda: S2CampDataManager)
    global_batch_sampling: bool = False
    """Every rank draws the step's whole batch (rays per batch x ranks) from a seed of ``global_batch_seed`` and the
    step and keeps its slice, so the rays do not depend on the number of ranks; needs
    train-num-images-to-sample-from -1. Off: each rank draws its own batch (nerfstudio's behaviour)."""
    global_batch_seed: int = 0
    """Seed of the global batch sampling (combined with the step)."""


class S2CampDataManager(VanillaDataManager[InputDataset]):
    """VanillaDataManager with ``PixelRayGenerator`` for the training rays (eval rays are left unchanged)."""

    config: S2CampDataManagerConfig

    def setup_train(self):
        if self.config.global_batch_sampling and self.config.train_num_images_to_sample_from != -1:
            raise ValueError(
                "train_num_images_to_sample_from must be -1 (every image cached) with global_batch_sampling, got "
                f"{self.config.train_num_images_to_sample_from}: ranks caching different images draw different rays"
            )
        super().setup_train()
        assert self.train_dataset is not None
        self.train_ray_generator = PixelRayGenerator(self.train_dataset.cameras.to(self.device))
        self._ordered_source: Any = None
        self._ordered_batch: dict | None = None

    def next_train(self, step: int) -> tuple[RayBundle, dict]:
        if not self.config.global_batch_sampling:
            return super().next_train(step)
        self.train_count += 1
        image_batch = self._in_image_order(next(self.iter_train_image_dataloader))
        sampler = self.train_pixel_sampler
        assert sampler is not None
        ranks, rank = comms.get_world_size(), comms.get_rank()
        per_rank = sampler.num_rays_per_batch
        device = torch.device(self.device)
        sampler.set_num_rays_per_batch(per_rank * ranks)
        try:
            with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
                torch.manual_seed(hash((self.config.global_batch_seed, step)) & 0x7FFF_FFFF_FFFF_FFFF)
                batch = sampler.sample(image_batch)
        finally:
            sampler.set_num_rays_per_batch(per_rank)
        total = per_rank * ranks
        part = slice(rank * per_rank, (rank + 1) * per_rank)
        batch = {
            key: value[part] if isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == total else value
            for key, value in batch.items()
        }
        return self.train_ray_generator(batch["indices"]), batch

    def _in_image_order(self, image_batch: dict) -> dict:
        """The cached images sorted by image index: nerfstudio caches them in an order drawn per rank."""
        if image_batch is self._ordered_source and self._ordered_batch is not None:
            return self._ordered_batch
        image_idx = image_batch["image_idx"]
        order = torch.argsort(image_idx.cpu())
        count = image_idx.shape[0]
        ordered = {}
        for key, value in image_batch.items():
            if isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == count:
                ordered[key] = value[order.to(value.device)]
            elif isinstance(value, list) and len(value) == count:
                ordered[key] = [value[int(i)] for i in order]
            else:
                ordered[key] = value
        self._ordered_source, self._ordered_batch = image_batch, ordered
        return ordered
