"""nerfstudio's normalization of a scene's cameras undone: from the normalized frame nerfstudio trains in back to the
world the cameras were given in (COLMAP's, or a transforms.json's).

nerfstudio maps an original-world pose to ``T @ c2w`` (T = ``dataparser_transform`` as 4x4, which includes the COLMAP
world axis swap), multiplies the centre by ``dataparser_scale`` and keeps OpenGL camera axes; the original world keeps
COLMAP's OpenCV axes. Tracks, exports and reference models live in the original world.
"""

from __future__ import annotations

import torch

from s2camp_ns.core.camera import opengl_to_opencv


def c2w_to_colmap_world(
    c2w_normalized: torch.Tensor, dataparser_transform: torch.Tensor, dataparser_scale: float
) -> torch.Tensor:
    """Undo nerfstudio's normalization: normalized OpenGL c2w [N, 3, 4] -> original-world OpenCV c2w (float64).

    nerfstudio maps an original-world pose to ``T @ c2w`` (T = dataparser_transform as 4x4, which includes the
    COLMAP world axis swap) and then multiplies the centre by the scale; this inverts both and flips the camera axes.
    """
    c2w = c2w_normalized.detach().double().cpu().clone()
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :4] = dataparser_transform.detach().double().cpu()
    c2w[:, :, 3] = c2w[:, :, 3] / float(dataparser_scale)
    c2w4 = torch.cat([c2w, torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(c2w.shape[0], 1, 4)], dim=1)
    original = torch.linalg.inv(transform) @ c2w4
    return opengl_to_opencv(original[:, :3, :4])


__all__ = ["c2w_to_colmap_world"]
