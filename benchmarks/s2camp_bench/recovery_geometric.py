"""Tier 1 of the camera-recovery benchmark: first-order refinement of perturbed cameras on reprojection error.

The scene's 3D points are projected by the true cameras (with their radial distortion); the cameras are perturbed
with CamP's protocol (distortion zeroed) and refined by Adam on the mean squared reprojection error, pixels divided
by max(W, H). Nothing but the parameterization differs between the variants, so this isolates the conditioning
that the preconditioner is meant to fix:

- ``none``: no refinement (the perturbed cameras);
- ``so3xr3``: nerfstudio's stock pose optimizer (SO3xR3 pose adjustment right-multiplied on c2w, its L2 penalties,
  nerfacto's camera learning rate 1e-3 decaying to 1e-4);
- ``raw``: the 12 raw deltas, same optimizer and schedule as ``s2camp``;
- ``camp``: whitened deltas, P from 5000 CamP random points, computed once (averaged over seeds);
- ``s2camp``: whitened deltas, P from 500 deterministic lattice points, refreshed on schedule, intrinsics per image;
- ``s2camp-once``: as ``s2camp`` with P computed once;
- ``s2camp-per-camera``: as ``s2camp``, but one set of intrinsics shared by all cameras (the generated scenes have
  one physical camera; its start is the mean of the perturbed per-image intrinsics) and the pose per image,
  preconditioned with the block-triangular factor of ``s2camp_ns.core.shared_intrinsics``.

Rows carry ``intrinsics``: "per-camera" for ``s2camp-per-camera``, "per-image" for every other variant (the
baselines refine or keep intrinsics per image).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap
import torch

from s2camp_ns.core.alignment import camera_errors
from s2camp_ns.core.camera import (
    TENSOR_FIELDS,
    Intrinsics,
    ParameterLayout,
    apply_local_transform,
    in_image,
    project,
    se3_exp,
)
from s2camp_ns.core.perturbation import PerturbationConfig, perturb_cameras
from s2camp_ns.core.preconditioner import (
    CAMP_SAMPLING,
    DampingConfig,
    Preconditioner,
    SamplingConfig,
    compute_preconditioner,
    reexpress_latent,
)
from s2camp_ns.core.shared_intrinsics import (
    compute_shared_preconditioner,
    deltas_from_latents,
    reexpress_latents,
)

VARIANTS = ("none", "so3xr3", "raw", "camp", "s2camp", "s2camp-once", "s2camp-per-camera")
SHARED_VARIANTS = ("s2camp-per-camera",)


@dataclass
class GeometricScene:
    """True cameras (OpenCV c2w, normalized scene units), their intrinsics and the scene's 3D points."""

    name: str
    c2w: torch.Tensor
    intrinsics: Intrinsics
    points: torch.Tensor


@dataclass
class GeometricConfig:
    """Optimizer settings of tier 1."""

    iterations: int = 1000
    lr: float = 1e-3
    """Initial learning rate of the camera parameters (whitened units for the preconditioned variants)."""
    lr_final: float = 1e-4
    """Learning rate reached by exponential decay at the last iteration."""
    so3xr3_lr: float = 1e-3
    so3xr3_lr_final: float = 1e-4
    refresh_every: int = 100
    """Refresh interval of P for ``s2camp``, in iterations."""
    camp_seeds: tuple[int, ...] = (0, 1, 2)
    perturbation_seed: int = 0
    log_every: int = 10
    max_points: int = 2000
    """Scene points used (an evenly strided subset when the scene has more)."""
    thresholds: dict[str, float] = field(default_factory=lambda: {"rot_err": 1e-3, "pos_err": 1e-3, "focal_err": 1.0})
    """Error levels for the iterations-to-threshold columns (rad, scene units, pixels)."""
    sampling: SamplingConfig = SamplingConfig()
    damping: DampingConfig = DampingConfig()


def load_scene(path: Path, name: str, max_points: int | None = None) -> GeometricScene:
    """Cameras and points of a COLMAP model under ``path/sparse/0``, normalized like nerfstudio's data parser
    (centred on the mean camera centre, scaled so the largest centre coordinate is 1)."""
    reconstruction = pycolmap.Reconstruction(str(path / "sparse" / "0"))
    images = sorted(reconstruction.images.values(), key=lambda image: image.name)
    c2w, params = [], []
    for image in images:
        cam_from_world = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        matrix = np.asarray(cam_from_world.matrix())
        rotation = matrix[:, :3].T
        c2w.append(np.concatenate([rotation, -rotation @ matrix[:, 3:]], axis=1))
        camera = reconstruction.cameras[image.camera_id]
        extra = [camera.params[i] for i in camera.extra_params_idxs()]
        k1 = extra[0] if extra else 0.0
        k2 = extra[1] if len(extra) > 1 and camera.model.name in ("RADIAL", "OPENCV") else 0.0
        fx, fy = camera.focal_length_x, camera.focal_length_y
        cx, cy = camera.principal_point_x, camera.principal_point_y
        params.append((fx, fy, cx, cy, camera.width, camera.height, k1, k2))
    c2w_t = torch.tensor(np.stack(c2w), dtype=torch.float64)
    centre = c2w_t[:, :, 3].mean(dim=0)
    scale = 1.0 / float((c2w_t[:, :, 3] - centre).abs().max())
    c2w_t[:, :, 3] = (c2w_t[:, :, 3] - centre) * scale
    points = torch.tensor(np.stack([p.xyz for p in reconstruction.points3D.values()]), dtype=torch.float64)
    points = (points - centre) * scale
    if max_points is not None and points.shape[0] > max_points:
        points = points[torch.linspace(0, points.shape[0] - 1, max_points).long()]
    p = torch.tensor(params, dtype=torch.float64)
    intrinsics = Intrinsics.create(
        fx=p[:, 0], fy=p[:, 1], cx=p[:, 2], cy=p[:, 3], width=p[:, 4], height=p[:, 5], k1=p[:, 6], k2=p[:, 7]
    )
    return GeometricScene(name=name, c2w=c2w_t, intrinsics=intrinsics, points=points)


def world_to_camera(points: torch.Tensor, c2w: torch.Tensor) -> torch.Tensor:
    """Camera-frame coordinates [N, P, 3] of world points [P, 3] for OpenCV c2w [N, 3, 4]."""
    return torch.einsum("nji,npj->npi", c2w[:, :, :3], points[None] - c2w[:, None, :, 3])


class Refinement:
    """One variant's parameterization of the camera deltas, its optimizer and learning-rate schedule."""

    def __init__(self, variant: str, start: Intrinsics, num_cameras: int, config: GeometricConfig, seed: int = 0):
        self.variant = variant
        self.config = config
        self.layout = ParameterLayout.from_preset("pose" if variant == "so3xr3" else "all")
        k = self.layout.num_params
        self.shared = variant in SHARED_VARIANTS
        self.latent = torch.zeros(num_cameras, 6 if self.shared else k, dtype=torch.float64, requires_grad=True)
        self.preconditioner: Preconditioner | None = None
        self.camera_of_image = torch.zeros(num_cameras, dtype=torch.long)
        if self.shared:
            self.sampling = config.sampling
            self.shared_latent = torch.zeros(1, k - 6, dtype=torch.float64, requires_grad=True)
            self.factor = compute_shared_preconditioner(start[0], self.layout, self.sampling, config.damping)
        if variant in ("camp", "s2camp", "s2camp-once"):
            sampling = config.sampling
            if variant == "camp":
                sampling = replace(CAMP_SAMPLING, seed=seed)
            self.sampling = sampling
            self.preconditioner = compute_preconditioner(start, self.layout, sampling, config.damping)
        lr, lr_final = (
            (config.so3xr3_lr, config.so3xr3_lr_final) if variant == "so3xr3" else (config.lr, config.lr_final)
        )
        parameters = [self.latent, self.shared_latent] if self.shared else [self.latent]
        self.optimizer = torch.optim.Adam(parameters, lr=lr, betas=(0.9, 0.99), eps=1e-15)
        gamma = (lr_final / lr) ** (1.0 / max(config.iterations, 1))
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma)

    def deltas(self) -> torch.Tensor:
        """Full 12-column camera deltas phi (paper eq. 15: phi = P^-1 phi_hat for the whitened variants)."""
        latent = self.latent
        if self.shared:
            return deltas_from_latents(latent, self.shared_latent, self.camera_of_image, self.factor.inverse)
        if self.preconditioner is not None:
            latent = (self.preconditioner.inverse @ latent[..., None])[..., 0]
        return self.layout.expand(latent)

    def regularizer(self) -> torch.Tensor:
        if self.variant != "so3xr3":
            return self.latent.new_zeros(())
        # nerfstudio's CameraOptimizer defaults: trans_l2_penalty 1e-2, rot_l2_penalty 1e-3 (on the norms).
        return 1e-2 * self.latent[:, :3].norm(dim=-1).mean() + 1e-3 * self.latent[:, 3:].norm(dim=-1).mean()

    def maybe_refresh(self, iteration: int, current: Intrinsics) -> None:
        every = self.config.refresh_every
        if self.variant not in ("s2camp", *SHARED_VARIANTS) or every <= 0 or iteration == 0 or iteration % every:
            return
        if self.shared:
            new_factor = compute_shared_preconditioner(
                current[0].detach(), self.layout, self.sampling, self.config.damping
            )
            state = self.optimizer.state
            reexpress_latents(
                self.latent.data, self.shared_latent.data, self.camera_of_image, self.factor.matrix,
                self.factor.inverse, new_factor.matrix, new_factor.inverse, state.get(self.latent),
                state.get(self.shared_latent),
            )  # fmt: skip
            self.factor = new_factor
            return
        new = compute_preconditioner(current.detach(), self.layout, self.sampling, self.config.damping)
        reexpress_latent(self.latent, self.preconditioner, new, self.optimizer.state.get(self.latent))
        self.preconditioner = new


def local_transform(deltas: torch.Tensor, variant: str) -> torch.Tensor:
    """T with c2w' = c2w T: exp(xi) for the se(3) twist, [exp(omega) | rho] for nerfstudio's SO3xR3."""
    if variant != "so3xr3":
        return se3_exp(deltas[:, :6])
    rotation = se3_exp(torch.cat([torch.zeros_like(deltas[:, :3]), deltas[:, 3:6]], dim=-1))[:, :, :3]
    return torch.cat([rotation, deltas[:, :3, None]], dim=-1)


def refined_geometric_cameras(
    base_c2w: torch.Tensor, base: Intrinsics, deltas: torch.Tensor, variant: str
) -> tuple[torch.Tensor, Intrinsics]:
    """c2w' = c2w T (see ``local_transform``) and Phi' = Phi + dPhi."""
    transform = local_transform(deltas, variant)
    rotation = base_c2w[:, :, :3] @ transform[:, :, :3]
    translation = base_c2w[:, :, 3:] + base_c2w[:, :, :3] @ transform[:, :, 3:]
    return torch.cat([rotation, translation], dim=-1), base.with_delta(deltas)


def reprojection_loss(
    base_points_cam: torch.Tensor,
    base: Intrinsics,
    deltas: torch.Tensor,
    variant: str,
    observed: torch.Tensor,
    visible: torch.Tensor,
) -> torch.Tensor:
    """Mean squared reprojection error, pixels divided by max(W, H), over the visible observations."""
    points_cam = apply_local_transform(base_points_cam, local_transform(deltas, variant))
    pixels, _ = project(points_cam, base.with_delta(deltas))
    residual = (pixels - observed) / base.image_scale()[:, None, None]
    return (residual.pow(2).sum(dim=-1) * visible).sum() / visible.sum()


def errors(c2w: torch.Tensor, intrinsics: Intrinsics, scene: GeometricScene) -> dict[str, float]:
    """Aligned pose errors and focal error (the issue's metrics), plus principal-point and k1 errors, which show
    where a camera that reprojects well can still be wrong (principal point trades against rotation)."""
    result = camera_errors(c2w.detach(), scene.c2w, intrinsics.fx.detach(), scene.intrinsics.fx, align=True)
    truth = scene.intrinsics
    pp = torch.stack([intrinsics.cx.detach() - truth.cx, intrinsics.cy.detach() - truth.cy], dim=-1).norm(dim=-1)
    return {
        "rot_err": result["rot_err_mean"],
        "pos_err": result["pos_err_mean"],
        "focal_err": result["focal_err_mean"],
        "pp_err": float(pp.mean()),
        "k1_err": float((intrinsics.k1.detach() - truth.k1).abs().mean()),
    }


def perturbed_start(scene: GeometricScene, seed: int) -> tuple[torch.Tensor, Intrinsics]:
    perturbed = perturb_cameras(
        scene.c2w, scene.intrinsics.fx, scene.intrinsics.fy, PerturbationConfig(enabled=True), seed=seed
    )
    start = Intrinsics.create(
        fx=perturbed.fx,
        fy=perturbed.fy,
        cx=scene.intrinsics.cx,
        cy=scene.intrinsics.cy,
        width=scene.intrinsics.width,
        height=scene.intrinsics.height,
    )
    return perturbed.c2w, start


def run_variant(scene: GeometricScene, variant: str, config: GeometricConfig, seed: int = 0) -> dict:
    """Refine the perturbed cameras of ``scene`` with ``variant``; return final errors and the error history."""
    observed, depth = project(world_to_camera(scene.points, scene.c2w), scene.intrinsics)
    visible = in_image(observed, depth, scene.intrinsics).to(torch.float64)
    base_c2w, start = perturbed_start(scene, config.perturbation_seed)
    base_points_cam = world_to_camera(scene.points, base_c2w)
    history = [{"iteration": 0, **errors(base_c2w, start, scene)}]
    if variant in SHARED_VARIANTS:  # one physical camera: its intrinsics start at the mean of the given ones
        start = Intrinsics(*[value.mean().expand_as(value).clone() for value in astuple_intrinsics(start)])
    if variant == "none":
        return {"history": history, "final": history[-1], "sec_per_iter": 0.0}
    refinement = Refinement(variant, start, scene.c2w.shape[0], config, seed=seed)
    began = time.perf_counter()
    for iteration in range(1, config.iterations + 1):
        deltas = refinement.deltas()
        loss = reprojection_loss(base_points_cam, start, deltas, variant, observed, visible)
        refinement.optimizer.zero_grad(set_to_none=True)
        (loss + refinement.regularizer()).backward()
        refinement.optimizer.step()
        refinement.scheduler.step()
        if iteration % config.log_every == 0 or iteration == config.iterations:
            with torch.no_grad():
                c2w, intrinsics = refined_geometric_cameras(base_c2w, start, refinement.deltas(), variant)
            history.append({"iteration": iteration, "loss": loss.item(), **errors(c2w, intrinsics, scene)})
        if variant in ("s2camp", *SHARED_VARIANTS):
            with torch.no_grad():
                _, current = refined_geometric_cameras(base_c2w, start, refinement.deltas(), variant)
            refinement.maybe_refresh(iteration, current)
    seconds = time.perf_counter() - began
    return {"history": history, "final": history[-1], "sec_per_iter": seconds / config.iterations}


def astuple_intrinsics(intrinsics: Intrinsics) -> tuple[torch.Tensor, ...]:
    """The per-camera tensor fields, in the positional order of ``Intrinsics`` (its projection tag left out)."""
    return tuple(getattr(intrinsics, name) for name in TENSOR_FIELDS)


def iterations_to(history: list[dict], key: str, threshold: float) -> float:
    """First logged iteration whose error is below ``threshold`` (nan if never)."""
    return next((float(h["iteration"]) for h in history if h[key] <= threshold), math.nan)
