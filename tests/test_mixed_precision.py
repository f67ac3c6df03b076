"""The camera part of a training step under autocast, as nerfacto runs on CUDA (issue 19, item 2).

nerfstudio's trainer runs the whole forward pass (``pipeline.get_train_loss_dict``, hence ``apply_to_raybundle``)
inside ``torch.autocast`` when ``mixed_precision`` is on (S2CamP's methods turn it on, as nerfacto does); on CUDA
that is float16 and tiny-cuda-nn's MLPs run in half precision. Here the same autocast runs on the CPU, in float16
(CPU autocast supports it in torch 2.14) and bfloat16.

The field is a small test double, ``HalfPrecisionField``: random Fourier features and a two-layer MLP whose matmuls
autocast lowers to 16 bits, volume-rendered along each ray. It stands in for nerfacto's field because at
initialisation nerfacto's field is nearly constant in space, so the camera gradient (which comes only from the
field's spatial variation) is almost all rounding noise and no tolerance can be stated: measured with the sized-down
nerfacto of the other tests at initialisation, the camera gradients' relative error against float32 was 0.24
(float16) and 1.1 (bfloat16). The double has the spatial structure of a fitted field, fixed by its seed.
"""

from __future__ import annotations

import pytest
import torch
from nerfstudio.cameras.rays import RayBundle
from test_device_audit import HEIGHT, NUM_CAMERAS, WIDTH, make_cameras, scene_points
from torch import nn

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.method.rays import PIXEL_KEY

TOLERANCE = {torch.float16: 2e-2, torch.bfloat16: 1e-1}
"""Largest accepted relative error ||g_amp - g_32|| / ||g_32|| of each camera latent's gradient (pose and shared
intrinsics latents). Measured on this set-up, 512 rays: float16 0.0055 / 0.0045 (per-camera: pose / intrinsics
latent) and 0.0044 (per-image), bfloat16 0.035 / 0.048 and 0.045; the bounds leave 3.6x and 2.1x of margin."""


class HalfPrecisionField(nn.Module):
    """Colour of rays through a fixed random field: Fourier features of 16 samples per ray, an MLP (3 -> 64 -> 4:
    density, RGB) and nerfstudio's volume rendering weights. Under autocast the feature projection and the MLP's
    linear layers run in 16 bits, as tiny-cuda-nn's MLPs do on CUDA."""

    def __init__(self, seed: int = 0) -> None:
        super().__init__()
        generator = torch.Generator().manual_seed(seed)
        self.register_buffer("frequencies", 2.0 * torch.randn(3, 32, generator=generator))
        self.mlp = nn.Sequential(nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, 4))
        with torch.no_grad():
            for parameter in self.mlp.parameters():
                parameter.copy_(0.5 * torch.randn(parameter.shape, generator=generator))

    def forward(self, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        distances = torch.linspace(0.5, 3.0, 16, device=origins.device)
        points = origins[:, None, :] + distances[None, :, None] * directions[:, None, :]
        projected = points @ self.frequencies
        output = self.mlp(torch.cat([projected.sin(), projected.cos()], dim=-1)).float()
        density, rgb = nn.functional.softplus(output[..., 0]), torch.sigmoid(output[..., 1:])
        alpha = 1.0 - torch.exp(-density * (distances[1] - distances[0]))
        transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]], dim=-1), -1)
        return ((alpha * transmittance)[..., None] * rgb).sum(dim=1)


def camera_step(dtype: torch.dtype | None, intrinsics: str, device: str = "cpu"):
    """One training step's camera part: rays regenerated through the refined cameras, the field double, an MSE loss
    (nerfacto's), backward; under autocast at ``dtype`` (None: float32). Returns the optimizer, the rays and the
    camera latents' gradients."""
    torch.manual_seed(0)
    config = S2CampCameraOptimizerConfig(intrinsics=intrinsics, sampling=SamplingConfig(num_points=64))
    optimizer = config.setup(num_cameras=NUM_CAMERAS, device=device)
    optimizer.set_train_cameras(make_cameras("OPENCV").to(device), points=scene_points(device))
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():  # a camera away from its start, as during training
        for parameter in optimizer.parameters():
            parameter.copy_(1e-3 * torch.randn(parameter.shape, generator=generator).to(device))
    num_rays = 512
    pixels = torch.rand(num_rays, 2, generator=generator) * torch.tensor([WIDTH, HEIGHT])
    bundle = RayBundle(
        origins=torch.zeros(num_rays, 3, device=device),
        directions=torch.zeros(num_rays, 3, device=device),
        pixel_area=torch.ones(num_rays, 1, device=device),
        camera_indices=torch.randint(0, NUM_CAMERAS, (num_rays, 1), generator=generator).to(device),
        metadata={PIXEL_KEY: pixels.to(device), "directions_norm": torch.ones(num_rays, 1, device=device)},
    )
    target = torch.rand(num_rays, 3, generator=generator).to(device)
    field = HalfPrecisionField().to(device)
    with torch.autocast(device, dtype=dtype or torch.float16, enabled=dtype is not None):
        optimizer.apply_to_raybundle(bundle)
        rgb = field(bundle.origins, bundle.directions)
        loss = nn.functional.mse_loss(rgb, target)
    loss.backward()
    gradients = {name: parameter.grad for name, parameter in optimizer.named_parameters()}
    return optimizer, bundle, gradients, rgb


@pytest.mark.parametrize("intrinsics", ["per-camera", "per-image"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16], ids=["float16", "bfloat16"])
def test_camera_gradients_under_autocast_are_finite_and_close_to_float32(dtype: torch.dtype, intrinsics: str):
    optimizer32, bundle32, gradients32, rgb32 = camera_step(None, intrinsics)
    optimizer, bundle, gradients, rgb = camera_step(dtype, intrinsics)
    assert rgb.dtype == torch.float32 and not torch.equal(rgb, rgb32), "the field did run in 16 bits"
    # The camera part itself runs with autocast disabled: the rays are float32 and bit-identical.
    assert bundle.origins.dtype == bundle.directions.dtype == torch.float32
    assert torch.equal(bundle.origins, bundle32.origins) and torch.equal(bundle.directions, bundle32.directions)
    assert set(gradients) == set(gradients32) and len(gradients) == 2  # the pose and the intrinsics latent
    for name, gradient in gradients.items():
        assert gradient.dtype == torch.float32 and bool(torch.isfinite(gradient).all()), name
        reference = gradients32[name]
        assert float(reference.norm()) > 0.0, name
        error = float((gradient - reference).norm() / reference.norm())
        assert error < TOLERANCE[dtype], f"{name}: relative error {error:.3g} against float32"
    # The float64 islands: a refresh under autocast (P, P^-1, Sigma, the latent re-expressed) computes the bits of
    # a refresh without it, in float64; autocast never lowers float64 ops.
    with torch.autocast("cpu", dtype=dtype):
        optimizer.refiner.refresh(step=1)
    optimizer32.refiner.refresh(step=1)
    assert int(optimizer.refiner.last_refresh_step) == 1, "the refresh ran"
    for name in ("precond", "precond_inv", "gram", "proxy_range"):
        buffer = getattr(optimizer.refiner, name)
        assert buffer.dtype == torch.float64 and torch.equal(buffer, getattr(optimizer32.refiner, name)), name
    with torch.autocast("cpu", dtype=dtype):
        deltas = optimizer.refiner.deltas()
    assert deltas.dtype == torch.float64 and torch.equal(deltas, optimizer32.refiner.deltas())


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a real CUDA device (make gpu-check)")
def test_camera_gradients_under_cuda_autocast_are_close_to_float32():
    """nerfacto's own setting on a GPU: float16 autocast on CUDA, against the float32 run on the same GPU."""
    _, _, gradients32, _ = camera_step(None, "per-camera", device="cuda")
    optimizer, _, gradients, _ = camera_step(torch.float16, "per-camera", device="cuda")
    for name, gradient in gradients.items():
        assert bool(torch.isfinite(gradient).all()), name
        error = float((gradient - gradients32[name]).norm() / gradients32[name].norm())
        assert error < TOLERANCE[torch.float16], f"{name}: relative error {error:.3g} against float32"
    assert optimizer.refiner.precond.dtype == optimizer.refiner.gram.dtype == torch.float64
