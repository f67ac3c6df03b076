"""A stock ``nerfacto`` pipeline seen through the interface S2CamP's evaluation reads.

The evaluation of the benchmarks (``s2camp_bench.evaluation.evaluate_pipeline``: camera errors, held-out
views after test-time alignment) asks the model for its training cameras as given (``_train_cameras``), the
unperturbed ones (``reference_cameras``) and the refined ones (``refined_train_cameras``); ``S2CampModel`` has them.
Stock nerfacto trained on ``s2camp-data`` has the same information elsewhere: the cameras in its data manager, the
unperturbed ones in the data parser's metadata, the refinement in its camera optimizer. This wrapper only
re-exposes it; rendering is the wrapped model's own.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


class StockNerfactoModel(torch.nn.Module):
    """A nerfstudio ``NerfactoModel`` (stock camera optimizer) with S2CampModel's camera interface for evaluation."""

    uses_s2camp_optimizer = False

    def __init__(self, model, datamanager) -> None:
        super().__init__()
        self.model = model
        self._train_cameras = datamanager.train_dataset.cameras.to("cpu")
        self._metadata = datamanager.train_dataparser_outputs.metadata or {}

    @property
    def device(self) -> torch.device:
        return self.model.device

    @property
    def lpips(self):
        return getattr(self.model, "lpips", None)

    def forward(self, ray_bundle):
        return self.model(ray_bundle)

    def reference_cameras(self):
        """The data parser's unperturbed training cameras (``s2camp-data --perturbation.enabled True``), if any."""
        reference = self._metadata.get("reference_cameras")
        if reference is None or reference.shape[0] != self._train_cameras.shape[0]:
            return None
        return reference

    @torch.no_grad()
    def refined_train_cameras(self) -> tuple[Float[Tensor, "n 3 4"], Float[Tensor, " n"]]:
        """OpenGL c2w (float64, CPU) of the training cameras after nerfstudio's pose refinement, by nerfstudio's own
        ``CameraOptimizer.apply_to_camera``, and their fx (the stock optimizer leaves intrinsics alone)."""
        cameras = self._train_cameras
        refined = []
        for index in range(cameras.shape[0]):
            camera = cameras[index : index + 1]
            camera.metadata = {"cam_idx": index}
            refined.append(self.model.camera_optimizer.apply_to_camera(camera).to(device="cpu", dtype=torch.float64))
        return torch.cat(refined), cameras.fx.reshape(-1).to(torch.float64)


class StockNerfactoPipeline:
    """The pipeline attributes the evaluation reads: the wrapped model and the data manager."""

    def __init__(self, pipeline) -> None:
        self.datamanager = pipeline.datamanager
        self.model = StockNerfactoModel(pipeline.model, pipeline.datamanager)
