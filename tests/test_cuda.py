"""Tests that need a real CUDA device (marker ``cuda``): skipped without one (tests/conftest.py), run by
``make gpu-check`` (docs/GPU-CHECK.md), where every one of them must pass and none may skip.

- the camera optimizer on CUDA: P, ``apply_to_raybundle`` and the backward pass agree with the CPU;
- nerfstudio's own Trainer on CUDA with mixed precision (autocast + GradScaler, as nerfacto trains on a GPU) for
  each method of the plugin, then the evaluation the benchmarks run on the trained pipeline: no "No inf checks
  were recorded for this optimizer" (nerfstudio issue 1684), finite losses, refined cameras, finite PSNR;
- gsplat imports (splatfacto's rasterizer; its CUDA kernels compile on first use, which is not done here).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
from nerfstudio.cameras.rays import RayBundle
from test_camera_optimizer import HEIGHT, NUM_CAMERAS, WIDTH, make_cameras

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.method.rays import PIXEL_KEY

pytestmark = pytest.mark.cuda

CUDA = "cuda"
NUM_RAYS = 512


def _ray_bundle(device: str) -> RayBundle:
    generator = torch.Generator().manual_seed(0)
    pixels = torch.rand(NUM_RAYS, 2, generator=generator) * torch.tensor([WIDTH, HEIGHT])
    camera_indices = torch.randint(0, NUM_CAMERAS, (NUM_RAYS, 1), generator=generator)
    return RayBundle(
        origins=torch.zeros(NUM_RAYS, 3, device=device),
        directions=torch.zeros(NUM_RAYS, 3, device=device),
        pixel_area=torch.ones(NUM_RAYS, 1, device=device),
        camera_indices=camera_indices.to(device),
        metadata={PIXEL_KEY: pixels.to(device), "directions_norm": torch.ones(NUM_RAYS, 1, device=device)},
    )


def _optimizer_step(device: str) -> dict[str, torch.Tensor]:
    """P, the regenerated rays and the latent's gradient of one camera-optimizer step on ``device``."""
    config = S2CampCameraOptimizerConfig(sampling=SamplingConfig(num_points=500), refresh_every=10)
    optimizer = config.setup(num_cameras=NUM_CAMERAS, device=device)
    optimizer.set_train_cameras(make_cameras(k1=-0.05, k2=0.01).to(device))
    with torch.no_grad():
        latent = 1e-2 * torch.randn(optimizer.refiner.whitened_delta.shape, generator=torch.Generator().manual_seed(1))
        optimizer.refiner.whitened_delta.copy_(latent.to(device))
    bundle = _ray_bundle(device)
    optimizer.apply_to_raybundle(bundle)
    target = torch.linspace(-1.0, 1.0, NUM_RAYS * 3).reshape(NUM_RAYS, 3).to(device)
    loss = ((bundle.origins + 2.0 * bundle.directions - target) ** 2).mean()
    loss.backward()
    return {
        "precond": optimizer.refiner.precond.detach(),
        "origins": bundle.origins.detach(),
        "directions": bundle.directions.detach(),
        "grad": optimizer.refiner.whitened_delta.grad.detach(),
        "intrinsics_grad": optimizer.refiner.whitened_intrinsics.grad.detach(),
    }


def test_camera_optimizer_on_cuda_matches_the_cpu() -> None:
    on_cuda = _optimizer_step(CUDA)
    on_cpu = _optimizer_step("cpu")
    assert on_cuda["precond"].device.type == CUDA and on_cuda["precond"].dtype == torch.float64
    for name in ("origins", "directions", "grad", "intrinsics_grad"):
        assert on_cuda[name].device.type == CUDA, name
        assert torch.isfinite(on_cuda[name]).all(), name
    assert on_cuda["grad"].abs().max() > 0 and on_cuda["intrinsics_grad"].abs().max() > 0
    # P is float64 on both devices (eigensolves differ in the last bits); the rays and gradients are float32.
    torch.testing.assert_close(on_cuda["precond"].cpu(), on_cpu["precond"], rtol=1e-6, atol=1e-9)
    for name in ("origins", "directions", "grad", "intrinsics_grad"):
        torch.testing.assert_close(on_cuda[name].cpu(), on_cpu[name], rtol=1e-4, atol=1e-6, msg=name)


@pytest.mark.parametrize("method", ["s2camp", "s2camp-camp", "s2camp-so3xr3"])
def test_training_steps_on_cuda_with_mixed_precision(method: str, tiny_scene: Path, tmp_path: Path) -> None:
    """nerfstudio's Trainer as ``ns-train`` runs it on a GPU (autocast, GradScaler), then the benchmarks' evaluation."""
    from s2camp_bench.evaluation import evaluate_pipeline
    from s2camp_ns.method_config import s2camp_camp_method, s2camp_method, s2camp_so3xr3_method
    from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

    specification = {"s2camp": s2camp_method, "s2camp-camp": s2camp_camp_method, "s2camp-so3xr3": s2camp_so3xr3_method}
    config = copy.deepcopy(specification[method].config)
    config.machine.device_type = CUDA
    config.mixed_precision = True
    config.pipeline.datamanager.data = tiny_scene
    config.pipeline.datamanager.train_num_rays_per_batch = 1024
    config.pipeline.datamanager.dataparser.perturbation.enabled = True
    config.pipeline.model.camera_error_every = 5
    if method == "s2camp":
        config.pipeline.model.camera_optimizer.refresh_every = 5
    config.output_dir = tmp_path
    config.timestamp = "cuda"
    config.max_num_iterations = 20
    config.steps_per_save = 1000
    config.steps_per_eval_batch = config.steps_per_eval_image = config.steps_per_eval_all_images = 0
    config.vis = "tensorboard"

    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()  # raises "No inf checks were recorded for this optimizer" if a GradScaler step finds no grads

    assert trainer.grad_scaler.is_enabled()
    assert math.isfinite(trainer.grad_scaler.get_scale())
    model = trainer.pipeline.model
    camera_parameters = list(model.camera_optimizer.parameters())
    assert camera_parameters and all(p.device.type == CUDA for p in camera_parameters)
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert max(float(p.abs().max()) for p in camera_parameters) > 0, "the cameras were not refined"
    if method == "s2camp":
        assert model.camera_optimizer.refiner.precond.dtype == torch.float64
        assert int(model.camera_optimizer.refiner.num_refreshes) == 1 + 19 // 5  # the initial P and steps 5, 10, 15
    assert model._camera_errors and all(math.isfinite(v) for v in model._camera_errors.values())

    evaluation = evaluate_pipeline(trainer.pipeline, AlignmentConfig(steps=3, rays=64))
    for key in ("psnr", "rot_err", "pos_err", "focal_err", "start_rot_err"):
        assert math.isfinite(evaluation[key]), key


def test_gsplat_imports() -> None:
    import gsplat
    from gsplat import rasterization

    assert callable(rasterization)
    assert gsplat.__version__
