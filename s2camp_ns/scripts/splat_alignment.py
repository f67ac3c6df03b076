"""Test-time alignment's renderer for S2CamP's splat models (``s2camp-splat``, ``s2camp-splat-so3xr3``), and their
held-out views as splatfacto sees them.

The rasterizers differentiate the view matrix, not ``Ks``, so the focal scale enters as in training: the view's own K
goes to the rasterizer with the view matrix [[A R, A t], [0, 1]], A = K^-1 K', K' = K with fx, fy scaled by
exp(log_focal), [R | t] the world-to-camera of c2w exp(twist). Rendering goes through
``S2CampSplatModel.render_view``, never the camera optimizer. Each step renders every view whole, one at a time, and
takes the MSE over all its pixels (a splat render costs the same for any subset): ``rays`` and ``chunk`` do not apply.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.method.splat_model import world_to_camera
from s2camp_ns.scripts.alignment_camera import HeldOutView, twisted_c2w
from s2camp_ns.splat.intrinsics_view import corrected_viewmat, intrinsics_correction, intrinsics_matrix


def base_matrix(intrinsics: Intrinsics) -> Float[Tensor, "1 3 3"]:
    """Pinhole K [1, 3, 3] (float64) of a one-camera ``Intrinsics``; ValueError if it has lens distortion."""
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
    """View matrix [[A R, A t], [0, 1]] (float64) that, rendered with ``base_k``, renders the camera c2w exp(twist)
    with fx, fy scaled by exp(log_focal); differentiable in both."""
    scale = torch.exp(log_focal.double())
    k = base_k.double()
    refined_k = intrinsics_matrix(k[:, 0, 0] * scale, k[:, 1, 1] * scale, k[:, 0, 2], k[:, 1, 2], k[:, 0, 1])
    correction = intrinsics_correction(k, refined_k, check=False)  # both pinhole: built here from a pinhole K
    return corrected_viewmat(world_to_camera(twisted_c2w(c2w_gl, twist)[None]), correction)


class SplatRenderer:
    """Renders held-out views of an ``S2CampSplatModel`` through (twist, log focal), whole images."""

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
        """(predicted, target) colours [h w, 3] of each view (no sampling); differentiable in the variables."""
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
    """(image, OpenGL c2w, pinhole intrinsics) of every evaluation image as splatfacto renders it (``cached_eval``),
    in the reference cameras' frame: poses of the reference cameras (else the given ones); K the undistorted one
    for an undistorted image, else the reference camera's. ValueError for a reference camera with distortion whose
    image was not undistorted."""
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
