"""Test-time alignment's renderer for S2CamP's splat model (``S2CampSplatModel``: ``s2camp-splat`` and the
``s2camp-splat-so3xr3`` baseline), and the held-out views as splatfacto sees them.

A splat model renders whole images from a view matrix, and its rasterizers (gsplat; the reference rasterizer
follows its contract) differentiate the view matrix, not the intrinsics ``Ks``. The focal scale therefore enters
as training's intrinsics do (docs/SPLAT.md): the view's own K goes to the rasterizer and the view matrix
is [[A R, A t], [0, 1]] with A = K^-1 K', K' = K with fx, fy scaled by exp(log_focal), [R | t] the world-to-camera
of c2w exp(twist). The render goes through ``S2CampSplatModel.render_view``, never through the model's camera
optimizer: held-out cameras are not training cameras.

Loss sample: every Adam step renders each held-out view whole and takes the MSE over all its pixels. A splat
render costs the same whatever subset of its pixels enters the loss, so a random subset (the ray path's
``rays``) would only add noise; ``AlignmentConfig.rays`` and ``chunk`` do not apply here. Views are rendered one at
a time (one camera per rasterization, as splatfacto renders), their losses summed as in the ray path.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.nerfstudio.alignment_camera import HeldOutView, twisted_c2w
from s2camp_ns.nerfstudio.splat_model import world_to_camera
from s2camp_ns.splat.intrinsics_view import corrected_viewmat, intrinsics_correction, intrinsics_matrix


def base_matrix(intrinsics: Intrinsics) -> Float[Tensor, "1 3 3"]:
    """The pinhole K [1, 3, 3] (float64) of a one-camera ``Intrinsics``; ValueError if it has lens distortion
    (splatfacto renders pinhole cameras on undistorted images)."""
    distortion = torch.stack([getattr(intrinsics, name) for name in ("k1", "k2", "k3", "k4", "p1", "p2")])
    if intrinsics.is_fisheye or bool((distortion != 0).any()):
        raise ValueError(
            "a held-out view of a splat model must be a pinhole camera without distortion (splatfacto renders "
            f"undistorted images), got model {intrinsics.model!r} with distortion {distortion.flatten().tolist()}"
        )
    as64 = intrinsics.to(dtype=torch.float64)
    return intrinsics_matrix(as64.fx, as64.fy, as64.cx, as64.cy, as64.skew).reshape(1, 3, 3)


def aligned_view_matrix(
    c2w_gl: Float[Tensor, "3 4"],
    base_k: Float[Tensor, "1 3 3"],
    twist: Float[Tensor, 6],
    log_focal: Float[Tensor, ""],
) -> Float[Tensor, "1 4 4"]:
    """World-to-camera matrix [[A R, A t], [0, 1]] (float64) that, rendered with ``base_k``, renders the camera
    c2w exp(twist) with fx, fy scaled by exp(log_focal) (docs/SPLAT.md); differentiable in both."""
    scale = torch.exp(log_focal.double())
    k = base_k.double()
    refined_k = intrinsics_matrix(k[:, 0, 0] * scale, k[:, 1, 1] * scale, k[:, 0, 2], k[:, 1, 2], k[:, 0, 1])
    correction = intrinsics_correction(k, refined_k, check=False)  # both pinhole: built here from a pinhole K
    return corrected_viewmat(world_to_camera(twisted_c2w(c2w_gl, twist)[None]), correction)


class SplatRenderer:
    """Renders held-out views of an ``S2CampSplatModel`` through (twist, log focal): whole images (module
    docstring)."""

    def __init__(self, model) -> None:
        self.model = model

    def _render(self, view: HeldOutView, width: int, height: int, twist: Tensor, log_focal: Tensor) -> Tensor:
        base_k = base_matrix(view.intrinsics)
        viewmat = aligned_view_matrix(view.c2w_gl, base_k, twist, log_focal)
        return self.model.render_view(viewmat, base_k, width, height)["rgb"].reshape(height, width, 3)

    def step_colours(
        self,
        views: list[HeldOutView],
        targets: list[Float[Tensor, "h w 3"]],
        twists: list[Tensor],
        log_focals: list[Tensor],
        generators: list[torch.Generator],
    ) -> list[tuple[Tensor, Tensor]]:
        """(predicted, target) colours [h w, 3] of every pixel of each view (``generators`` unused: no sampling);
        differentiable in the twists and log focal scales."""
        del generators
        pairs = []
        for view, target, twist, log_focal in zip(views, targets, twists, log_focals, strict=True):
            predicted = self._render(view, target.shape[1], target.shape[0], twist, log_focal)
            pairs.append((predicted.float().cpu().reshape(-1, 3), target.reshape(-1, 3)))
        return pairs

    @torch.no_grad()
    def image(self, view: HeldOutView, width: int, height: int, twist: Tensor, log_focal: Tensor) -> Tensor:
        """The full image [height, width, 3] (float32, CPU) through the view's camera moved by (twist, log_focal)."""
        return self._render(view, width, height, twist, log_focal).float().cpu()


def splat_held_out_views(datamanager) -> list[tuple[Tensor, Float[Tensor, "3 4"], Intrinsics]]:
    """(image, OpenGL c2w, pinhole intrinsics) of every evaluation image as splatfacto renders it, in the frame of
    the reference cameras (before ``test_time_alignment``'s similarity map).

    Images: the data manager's cached evaluation images (``cached_eval``; its first use undistorts them and rewrites
    the evaluation cameras' K to the undistorted pinhole one, as ``ns-eval`` of splatfacto sees them). Poses: the
    evaluation split's reference cameras where the dataparser provides them (true cameras that
    differ from the input's), else the evaluation cameras. Intrinsics: an image the data manager undistorted is
    described by its undistorted K (a reference camera's K describes the distorted original), any other by the
    reference camera's K; a reference camera with distortion whose image was not undistorted cannot be rendered by
    a pinhole splat model and is refused.
    """
    images = [entry["image"] for entry in datamanager.cached_eval]
    dataset = datamanager.eval_dataset
    given = dataset.cameras
    reference = (getattr(dataset, "metadata", None) or {}).get("reference_cameras")
    if reference is None or reference.shape[0] != len(dataset):
        reference = given
    views = []
    for index, image in enumerate(images):
        undistorted = given.distortion_params is not None and bool((given.distortion_params[index] != 0).any())
        source = given if undistorted else reference
        reference_distortion = reference.distortion_params
        if not undistorted and reference_distortion is not None and bool((reference_distortion[index] != 0).any()):
            raise ValueError(
                f"evaluation image {index}: its reference camera has distortion "
                f"{reference_distortion[index].tolist()} but the image was not undistorted (its given camera has "
                "none); a splat model renders pinhole cameras only, allowed is no distortion"
            )
        intrinsics = Intrinsics.create(
            fx=float(source.fx[index]),
            fy=float(source.fy[index]),
            cx=float(source.cx[index]),
            cy=float(source.cy[index]),
            width=int(given.width[index]),
            height=int(given.height[index]),
        )
        views.append((image, reference.camera_to_worlds[index].cpu(), intrinsics))
    return views
