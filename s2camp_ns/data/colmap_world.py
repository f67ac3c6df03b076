"""nerfstudio's normalization of a scene's cameras undone, back to the world they were given in (COLMAP's, or a
transforms.json's), where tracks, exports and reference models live."""

from __future__ import annotations

import torch

from s2camp_ns.core.camera import opengl_to_opencv


def c2w_to_colmap_world(
    c2w_normalized: torch.Tensor, dataparser_transform: torch.Tensor, dataparser_scale: float
) -> torch.Tensor:
    """Normalized OpenGL c2w [N, 3, 4] -> original-world OpenCV c2w [N, 3, 4] (float64), inverting nerfstudio's
    ``T @ c2w`` (T = ``dataparser_transform`` as 4x4) and the centre's scale by ``dataparser_scale``."""
    c2w = c2w_normalized.detach().double().cpu().clone()
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :4] = dataparser_transform.detach().double().cpu()
    c2w[:, :, 3] = c2w[:, :, 3] / float(dataparser_scale)
    c2w4 = torch.cat([c2w, torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(c2w.shape[0], 1, 4)], dim=1)
    original = torch.linalg.inv(transform) @ c2w4
    return opengl_to_opencv(original[:, :3, :4])


__all__ = ["c2w_to_colmap_world"]
