"""The camera work of a training step is made for launch-bound devices: no host read, one graph.

- The op counter (``benchmarks/s2camp_bench/op_count.py``) finds the ops that synchronise a CUDA device, so the checks
  below can fail: ``.item()``, ``bool(t)``, ``torch.unique``, ``nonzero``, boolean masks, ``masked_select``; views are
  told apart from launches; the optimizers' CPU step counts are no syncs.
- Everything S2CamP runs in a training step (the rays cast through the refined cameras forward and backward, the
  track prior's proximal step, the common rotation removed, the refresh schedule, the metrics on a step that does not
  log them, the loss terms) synchronises nothing, for every camera model and both intrinsics layouts.
- The camera functions of both models (nerfacto's ray cast, splatfacto's view matrix) trace into one graph with
  ``torch.compile(fullgraph=True)`` and a backend that needs no compiler (``aot_eager``), forward and backward, and
  give the eager values and gradients, so CUDA graphs or compilation can be offered on a GPU.
"""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.cameras.rays import RayBundle

from s2camp_bench.op_count import OpCounter
from s2camp_ns.camera_optimizer import S2CampCameraOptimizer, S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.method.rays import PIXEL_KEY, cast_rays
from s2camp_ns.method.splat_model import refined_view_matrix
from s2camp_ns.splat.intrinsics_view import intrinsics_matrix

NUM_IMAGES, WIDTH, HEIGHT = 4, 64, 48
DISTORTION = {
    "PINHOLE": ([0.0] * 6, CameraType.PERSPECTIVE),
    "RADIAL": ([-0.05, 0.01, 0.0, 0.0, 0.0, 0.0], CameraType.PERSPECTIVE),
    "OPENCV": ([-0.05, 0.01, 0.0, 0.0, 0.003, -0.001], CameraType.PERSPECTIVE),
    "OPENCV_FISHEYE": ([0.05, -0.01, 0.002, -0.0003, 0.0, 0.0], CameraType.FISHEYE),
}


def cameras(model: str) -> Cameras:
    angles = torch.linspace(0.0, 2.0 * math.pi, NUM_IMAGES + 1)[:-1]
    c2w = []
    for angle in angles:
        position = torch.tensor([2.0 * math.cos(angle), 2.0 * math.sin(angle), 0.5])
        backward = position / position.norm()
        right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), backward)
        right = right / right.norm()
        rotation = torch.stack([right, torch.linalg.cross(backward, right), backward], -1)
        c2w.append(torch.cat([rotation, position[:, None]], -1))
    distortion, camera_type = DISTORTION[model]
    return Cameras(
        camera_to_worlds=torch.stack(c2w),
        fx=torch.full((NUM_IMAGES, 1), 50.0),
        fy=torch.full((NUM_IMAGES, 1), 51.0),
        cx=torch.full((NUM_IMAGES, 1), 32.0),
        cy=torch.full((NUM_IMAGES, 1), 24.0),
        width=WIDTH,
        height=HEIGHT,
        distortion_params=torch.tensor(distortion).expand(NUM_IMAGES, 6).clone(),
        camera_type=camera_type,
    )


def optimizer(model: str, intrinsics: str, parameters: str = "all") -> S2CampCameraOptimizer:
    """A refining camera optimizer with a track prior on every image and a nonzero latent."""
    config = S2CampCameraOptimizerConfig(
        intrinsics=intrinsics, parameters=parameters, sampling=SamplingConfig(num_points=64)
    )
    camera_optimizer = config.setup(num_cameras=NUM_IMAGES, device="cpu")
    camera_optimizer.set_train_cameras(cameras(model))
    camera_optimizer.set_track_prior(torch.full((NUM_IMAGES,), 0.3), track_observations=torch.full((NUM_IMAGES,), 50.0))
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for latent in camera_optimizer.parameters():
            latent.copy_(1e-3 * torch.randn(latent.shape, generator=generator))
    return camera_optimizer


def pixel_bundle(num_rays: int = 128) -> RayBundle:
    generator = torch.Generator().manual_seed(1)
    pixels = torch.rand(num_rays, 2, generator=generator) * torch.tensor([WIDTH, HEIGHT])
    nan = torch.full((num_rays, 3), float("nan"))
    indices = torch.randint(0, NUM_IMAGES, (num_rays, 1), generator=generator)
    return RayBundle(nan, nan, nan[:, :1], indices, metadata={PIXEL_KEY: pixels})


def test_the_counter_finds_host_reads_and_tells_views_from_launches():
    values = torch.arange(6.0)
    step = torch.tensor(3.0)
    counter = OpCounter(frozenset({step.data_ptr()}))
    with counter:
        counter.phase("reads")
        float(values.sum())
        bool((values > 2).any())
        torch.unique(values)
        values.nonzero()
        values[values > 2]
        torch.masked_select(values, values > 2)
        torch.repeat_interleave(torch.tensor([1, 2]))
        counter.phase("no reads")
        values.view(2, 3)[:, 1].unsqueeze(0)
        values[torch.tensor([0, 2])]
        torch.repeat_interleave(values, torch.tensor([1] * 6), output_size=6)
        step.item()  # a CPU-resident count, as Adam's: no device synchronisation
    reads, quiet = counter.counts["reads"], counter.counts["no reads"]
    expected = {"_local_scalar_dense": 2, "_unique2": 1, "nonzero": 1, "index": 1, "masked_select": 1}
    assert reads.syncs == {**expected, "repeat_interleave": 1}
    assert quiet.num_syncs == 0, quiet.syncs
    # view, select, unsqueeze, and the two lift_fresh of torch.tensor (an alias of the new tensor) launch nothing.
    assert quiet.views == 5 and quiet.launches == quiet.total - 5, quiet.ops


@pytest.mark.parametrize("model", list(DISTORTION))
@pytest.mark.parametrize("intrinsics", ["per-camera", "per-image"])
def test_a_training_steps_camera_work_reads_nothing_on_the_host(model: str, intrinsics: str):
    camera_optimizer = optimizer(model, intrinsics)
    bundle = pixel_bundle()
    counter = OpCounter()
    with counter:
        camera_optimizer.metrics_due = False  # a step that does not log
        camera_optimizer.apply_to_raybundle(bundle)
        loss = bundle.directions.square().sum() + bundle.origins.sum() + bundle.metadata["directions_norm"].sum()
        losses = {"rgb_loss": loss}
        camera_optimizer.get_loss_dict(losses)
        metrics: dict = {}
        camera_optimizer.get_metrics_dict(metrics)
        sum(losses.values()).backward()
        camera_optimizer.refiner.apply_track_prior(1e-3)
        camera_optimizer.refiner.remove_common_motion()
        assert not camera_optimizer.refresh_due(13)
    total = counter.total()
    assert total.num_syncs == 0, total.syncs
    assert metrics == {} and torch.isfinite(bundle.directions).all()
    for latent in camera_optimizer.parameters():
        assert latent.grad is not None and bool(latent.grad.abs().sum() > 0)


def test_an_image_without_distortion_gets_no_undistortion():
    """PINHOLE cameras refined without distortion (``pose+intrinsics``): no Newton iteration runs; with the
    distortion refined ("all", k1 and k2 from zero), a bounded few do."""
    fixed, refined = optimizer("PINHOLE", "per-camera", "pose+intrinsics"), optimizer("PINHOLE", "per-camera")
    assert fixed.refiner.distortion_terms == () and fixed.refiner.newton_iterations == 0
    assert refined.refiner.distortion_terms == ("k1", "k2") and 1 <= refined.refiner.newton_iterations <= 3
    counts = {}
    for name, camera_optimizer in (("fixed", fixed), ("refined", refined)):
        counter = OpCounter()
        with counter, torch.no_grad():
            camera_optimizer.apply_to_raybundle(pixel_bundle())
        counts[name] = counter.total()
    assert counts["fixed"].ops["div"] < counts["refined"].ops["div"]  # Newton divides g by g' every iteration
    assert counts["fixed"].launches + 20 < counts["refined"].launches


@pytest.mark.parametrize(("model", "intrinsics"), [("RADIAL", "per-camera"), ("OPENCV", "per-image"),
                                                   ("OPENCV_FISHEYE", "per-camera")])  # fmt: skip
def test_the_ray_cast_captures_as_one_graph_forward_and_backward(model: str, intrinsics: str):
    camera_optimizer = optimizer(model, intrinsics)
    refiner = camera_optimizer.refiner
    bundle = pixel_bundle()
    indices, pixels = bundle.camera_indices[:, 0], bundle.metadata[PIXEL_KEY]

    def camera_function(indices: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
        rays = cast_rays(refiner, indices, pixels)
        return torch.cat([rays.origins, rays.directions, rays.directions_norm, rays.pixel_area], dim=-1)

    results = []
    for function in (camera_function, torch.compile(camera_function, fullgraph=True, backend="aot_eager")):
        for latent in camera_optimizer.parameters():
            latent.grad = None
        out = function(indices, pixels)
        (out * torch.linspace(-1.0, 1.0, out.shape[-1])).sum().backward()
        results.append((out.detach(), [latent.grad.clone() for latent in camera_optimizer.parameters()]))
    (eager, eager_grads), (compiled, compiled_grads) = results
    torch.testing.assert_close(compiled, eager, rtol=1e-6, atol=1e-7)
    for mine, reference in zip(compiled_grads, eager_grads, strict=True):
        torch.testing.assert_close(mine, reference, rtol=1e-5, atol=1e-9)


def test_the_splat_view_matrix_captures_as_one_graph_forward_and_backward():
    camera_optimizer = optimizer("PINHOLE", "per-camera", "pose+intrinsics")
    refiner = camera_optimizer.refiner
    base_k = intrinsics_matrix(*(torch.tensor([value], dtype=torch.float64) for value in (50.0, 51.0, 32.0, 24.0)),
                               torch.zeros(1, dtype=torch.float64))  # fmt: skip
    image = torch.tensor([2])

    def camera_function(image: torch.Tensor) -> torch.Tensor:
        return refined_view_matrix(refiner, image, base_k)

    counter = OpCounter()
    with counter:
        camera_function(image).sum().backward()
    assert counter.total().num_syncs == 0, counter.total().syncs
    results = []
    for function in (camera_function, torch.compile(camera_function, fullgraph=True, backend="aot_eager")):
        for latent in camera_optimizer.parameters():
            latent.grad = None
        out = function(image)
        (out * torch.arange(16.0, dtype=out.dtype).reshape(1, 4, 4)).sum().backward()
        results.append((out.detach(), [latent.grad.clone() for latent in camera_optimizer.parameters()]))
    (eager, eager_grads), (compiled, compiled_grads) = results
    torch.testing.assert_close(compiled, eager, rtol=1e-12, atol=1e-12)
    for mine, reference in zip(compiled_grads, eager_grads, strict=True):
        torch.testing.assert_close(mine, reference, rtol=1e-10, atol=1e-12)
        assert bool(mine.abs().sum() > 0)
