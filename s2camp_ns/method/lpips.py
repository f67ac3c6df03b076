"""LPIPS where its weights cannot be loaded (offline, AlexNet's weights not in torch's cache).

torchmetrics' LPIPS loads torchvision's AlexNet weights when it is built and fails without them. An S2CamP model is
then built without the metric (``lpips`` None, one warning, ``warn_lpips_unavailable``) and ``OptionalLpips`` leaves
``lpips`` out of the image metrics; PSNR and SSIM are computed as usual.
"""

from __future__ import annotations

import torch
from nerfstudio.utils.rich_utils import CONSOLE

_WARNED = False


def warn_lpips_unavailable(error: BaseException) -> None:
    """Say once per process that LPIPS is left out, and why."""
    global _WARNED
    if not _WARNED:
        CONSOLE.print(
            "[bold yellow]LPIPS unavailable: weights not cached and could not be downloaded "
            f"({type(error).__name__}: {error}). PSNR and SSIM are still computed; lpips is omitted from the "
            "metrics. Cache the AlexNet weights (torch hub) to enable it."
        )
        _WARNED = True


class OptionalLpips:
    """Image metrics of a nerfstudio model whose ``lpips`` may be None (before the model class in the bases)."""

    @property
    def lpips_available(self) -> bool:
        return self.lpips is not None

    def get_image_metrics_and_images(
        self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]
    ) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
        if self.lpips_available:
            return super().get_image_metrics_and_images(outputs, batch)
        # nerfacto and splatfacto always call self.lpips: a stand-in for the call, its key dropped.
        self.lpips = lambda *args: torch.tensor(float("nan"))
        try:
            metrics_dict, images_dict = super().get_image_metrics_and_images(outputs, batch)
        finally:
            self.lpips = None
        metrics_dict.pop("lpips", None)
        return metrics_dict, images_dict


__all__ = ["OptionalLpips", "warn_lpips_unavailable"]
