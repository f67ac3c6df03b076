"""Device audit without a GPU: every model, camera and ray tensor on "cuda", every op checked (issue 19, item 1).

The CUDA run is emulated by ``tests/fake_cuda.py`` (tensors that say "cuda:0" and carry their values on the CPU;
every op, backward included, checks its arguments' devices with CUDA's rules and raises torch's
``FakeTensorDeviceMismatchError`` on a CPU tensor meeting a CUDA one). torch's own ``FakeTensorMode`` carries no
values, so it stops at the first data-dependent op (``bool(...)`` of the input checks, ``torch.unique``, ``.item()``)
and cannot run the camera optimizer, the data manager or a training step (nor any backward pass on "cuda": the
autograd engine asks for a CUDA context); it is used here for what it can run: the preconditioner's float64 algebra
(Jacobian, Gram matrix, eigensolve) and nerfacto's field forward on "cuda", and as the reference that the emulation's
device rules agree with (``test_fake_cuda_agrees_with_fake_tensor_mode``).

Nothing is replaced by a test double: nerfacto's field (torch hash grids; tiny-cuda-nn is not installed here and
nerfstudio falls back to torch) runs under the emulation with real values, as do the data manager, the pixel
sampler and the optimizers. Each check also compares the values with the same computation on the CPU, so a test
cannot pass by computing something else. What the emulation cannot see: CUDA kernels themselves (tiny-cuda-nn,
gsplat), CUDA generators, pinned memory and NCCL; those are for ``make gpu-check`` on a real GPU.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
from conftest import lpips_offline, tiny_model_config
from fake_cuda import MISMATCH_BASE, fake_cuda, is_fake_cuda, values
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.cameras.rays import RayBundle
from torch._subclasses.fake_tensor import FakeTensorMode

from s2camp_bench.drift import reprojection_drift
from s2camp_ns.camera_optimizer import TRAIN_CAMERA_KEY, S2CampCameraOptimizerConfig
from s2camp_ns.core.alignment import camera_errors
from s2camp_ns.core.camera import Intrinsics, ParameterLayout, opengl_to_opencv
from s2camp_ns.core.jacobian import gram_matrix, projection_jacobian
from s2camp_ns.core.perturbation import perturb_cameras
from s2camp_ns.core.preconditioner import (
    SAMPLERS,
    DampingConfig,
    SamplingConfig,
    compute_preconditioner,
    damped_gram,
    sample_proxy_points,
)
from s2camp_ns.core.proxy_range import proxy_ranges
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras, refined_nerfstudio_cameras
from s2camp_ns.method.rays import PIXEL_KEY, cast_rays

NUM_CAMERAS, WIDTH, HEIGHT = 3, 64, 48
CAMERA_MODELS = {
    "RADIAL": ([-0.05, 0.01, 0.0, 0.0, 0.0, 0.0], CameraType.PERSPECTIVE),
    "OPENCV": ([-0.05, 0.01, 0.0, 0.0, 0.003, -0.001], CameraType.PERSPECTIVE),
    "FULL_OPENCV": ([-0.05, 0.01, 0.002, 0.0, 0.003, -0.001], CameraType.PERSPECTIVE),
    "OPENCV_FISHEYE": ([0.05, -0.01, 0.002, -0.0003, 0.0, 0.0], CameraType.FISHEYE),
}


def on_cuda(tensor) -> bool:
    return is_fake_cuda(tensor) and tensor.device == torch.device("cuda", 0)


def close(a: torch.Tensor, b: torch.Tensor, rtol: float = 1e-6, atol: float = 1e-9) -> None:
    torch.testing.assert_close(values(a).to(values(b).dtype), values(b), rtol=rtol, atol=atol)


# ------------------------------------------------------------------------------------------- the emulation itself
MIXED_OPS = {
    "cuda + cpu": (lambda cuda, cpu: cuda + cpu, True),
    "cuda matmul cpu": (lambda cuda, cpu: cuda[:, None] @ cpu[None, :], True),
    "stack cuda, cpu": (lambda cuda, cpu: torch.stack([cuda, cpu]), True),
    "cuda + cpu scalar": (lambda cuda, cpu: cuda + cpu.sum(), False),
    "cuda indexed by cpu": (lambda cuda, cpu: cuda[cpu.long()], False),
    "copy cpu into cuda": (lambda cuda, cpu: cuda.clone().copy_(cpu), False),
    "cpu moved to cuda": (lambda cuda, cpu: cuda + cpu.to(cuda.device), False),
}


@pytest.mark.parametrize("case", list(MIXED_OPS))
def test_fake_cuda_agrees_with_fake_tensor_mode(case: str):
    """The emulation raises where torch's FakeTensorMode raises (a CPU tensor meeting a CUDA one) and accepts what
    it accepts (CPU scalars, CPU index tensors, cross-device copies)."""
    op, mismatch = MIXED_OPS[case]
    outcomes = []
    for mode in (FakeTensorMode(), fake_cuda()):
        with mode:
            cuda, cpu = torch.ones(3, device="cuda"), torch.zeros(3)
            try:
                result = op(cuda, cpu)
                outcomes.append(str(result.device))
            except MISMATCH_BASE as error:
                outcomes.append("mismatch")
                assert "cuda:0" in str(error) and "cpu" in str(error)
    assert outcomes == (["mismatch"] * 2 if mismatch else ["cuda:0"] * 2)


def test_fake_cuda_refuses_what_cuda_refuses_and_keeps_values():
    with fake_cuda():
        x = torch.arange(4.0, device="cuda")
        assert on_cuda(x) and x.is_cuda and x.tolist() == [0.0, 1.0, 2.0, 3.0] and float(x.sum()) == 6.0
        with pytest.raises(TypeError, match="can't convert cuda:0 device type tensor to numpy"):
            x.numpy()
        with pytest.raises(RuntimeError, match="indices should be either on cpu or on the same device"):
            torch.zeros(4)[torch.tensor([1], device="cuda")]
        with pytest.raises(RuntimeError, match="Expected a 'cuda' device type for generator"):
            torch.rand(3, device="cuda", generator=torch.Generator())
        moved = x.cpu()
        assert not is_fake_cuda(moved) and moved.device.type == "cpu"
        weight = torch.ones(4, requires_grad=True)
        (weight.to("cuda") * x).sum().backward()  # the gradient comes back to the CPU leaf
        assert not is_fake_cuda(weight.grad) and weight.grad.tolist() == [0.0, 1.0, 2.0, 3.0]


def test_fake_tensor_mode_runs_the_preconditioner_algebra_in_float64_on_cuda():
    """torch's FakeTensorMode runs the analytic Jacobian (eq. 4), the Gram matrix (eq. 5) and the eigensolve of
    eq. 20 on "cuda" in float64 (meta kernels exist for all of them); it stops at the finiteness check before the
    square root, which reads values (the emulation runs that part, ``test_camera_optimizer_on_cuda``)."""
    intrinsics = Intrinsics.create(
        fx=torch.tensor([60.0, 62.0]), fy=torch.tensor([61.0, 62.0]), cx=torch.tensor([32.0, 31.0]),
        cy=torch.tensor([24.0, 24.5]), width=torch.tensor([64.0, 64.0]), height=torch.tensor([48.0, 48.0]),
        k1=-0.05, k2=0.01, model="perspective", dtype=torch.float64,
    )  # fmt: skip
    points = sample_proxy_points(intrinsics, SamplingConfig(num_points=64))
    with FakeTensorMode(allow_non_fake_inputs=True):
        cuda_intrinsics = intrinsics.to(device="cuda")
        _, jacobian, mask = projection_jacobian(points.to("cuda"), cuda_intrinsics, ParameterLayout.from_preset("all"))
        sigma, _ = gram_matrix(jacobian, mask, cuda_intrinsics.image_scale())
        eigenvalues, eigenvectors = torch.linalg.eigh(damped_gram(sigma, DampingConfig()))
    for tensor in (jacobian, sigma, eigenvalues, eigenvectors):
        assert tensor.device == torch.device("cuda", 0) and tensor.dtype == torch.float64


def test_nerfacto_field_forward_under_fake_tensor_mode():
    """nerfacto's field (torch hash grids: tiny-cuda-nn is not installed here, nerfstudio's fallback) built and run on
    "cuda" under torch's FakeTensorMode: density and colour on "cuda", float32. Its backward cannot run there (the
    autograd engine looks for a CUDA context); the emulation runs it (``test_training_step_on_cuda``)."""
    from nerfstudio.field_components.spatial_distortions import SceneContraction
    from nerfstudio.fields.nerfacto_field import NerfactoField
    from nerfstudio.model_components.ray_samplers import UniformSampler

    with FakeTensorMode(), torch.device("cuda"):
        field = NerfactoField(
            aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), num_images=3, num_levels=2, log2_hashmap_size=10,
            hidden_dim=8, hidden_dim_color=8, spatial_distortion=SceneContraction(order=float("inf")),
            implementation="torch",
        )  # fmt: skip
        num_rays = 16
        bundle = RayBundle(
            origins=torch.zeros(num_rays, 3),
            directions=torch.nn.functional.normalize(torch.randn(num_rays, 3), dim=-1),
            pixel_area=torch.ones(num_rays, 1),
            camera_indices=torch.zeros(num_rays, 1, dtype=torch.long),
            nears=torch.full((num_rays, 1), 0.05),
            fars=torch.full((num_rays, 1), 2.0),
        )
        outputs = field(UniformSampler(num_samples=4)(bundle))
    assert {p.device for p in field.parameters()} == {torch.device("cuda", 0)}
    assert {name.value for name in outputs} == {"rgb", "density"}
    for output in outputs.values():
        assert output.device == torch.device("cuda", 0) and output.dtype == torch.float32
        assert tuple(output.shape[:2]) == (num_rays, 4)


# -------------------------------------------------------------------------------------------- camera optimizer
def look_at_c2w(position: torch.Tensor) -> torch.Tensor:
    backward = position / position.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), backward)
    right = right / right.norm()
    return torch.cat([torch.stack([right, torch.linalg.cross(backward, right), backward], -1), position[:, None]], -1)


def make_cameras(camera_model: str) -> Cameras:
    distortion, camera_type = CAMERA_MODELS[camera_model]
    angles = torch.linspace(0.0, 2.0 * math.pi, NUM_CAMERAS + 1)[:-1]
    positions = torch.stack([2.0 * angles.cos(), 2.0 * angles.sin(), 0.5 + 0.1 * angles], dim=-1)
    return Cameras(
        camera_to_worlds=torch.stack([look_at_c2w(p) for p in positions]),
        fx=torch.tensor([[60.0], [62.0], [58.0]]),
        fy=torch.tensor([[61.0], [62.0], [59.0]]),
        cx=torch.tensor([[32.0], [31.0], [33.5]]),
        cy=torch.tensor([[24.0], [24.5], [23.0]]),
        width=WIDTH,
        height=HEIGHT,
        distortion_params=torch.tensor(distortion).expand(NUM_CAMERAS, 6).clone(),
        camera_type=camera_type,
    )


def ray_bundle(device: str, num_rays: int = 128) -> RayBundle:
    generator = torch.Generator().manual_seed(0)
    pixels = torch.rand(num_rays, 2, generator=generator) * torch.tensor([WIDTH, HEIGHT])
    camera_indices = torch.randint(0, NUM_CAMERAS, (num_rays, 1), generator=generator)
    return RayBundle(
        origins=torch.zeros(num_rays, 3, device=device),
        directions=torch.zeros(num_rays, 3, device=device),
        pixel_area=torch.ones(num_rays, 1, device=device),
        camera_indices=camera_indices.to(device),
        metadata={PIXEL_KEY: pixels.to(device), "directions_norm": torch.ones(num_rays, 1, device=device)},
    )


def scene_points(device: str) -> torch.Tensor:
    return (0.5 * torch.randn(300, 3, generator=torch.Generator().manual_seed(1))).to(device)


def optimizer_run(device: str, camera_model: str, intrinsics: str, sampler: str) -> dict[str, torch.Tensor]:
    """The camera optimizer's life on ``device``: P, a training step, a refresh, refined cameras, a checkpoint."""
    sampling = SamplingConfig(num_points=64, sampler=sampler)
    config = S2CampCameraOptimizerConfig(intrinsics=intrinsics, refresh_every=10, sampling=sampling)
    optimizer = config.setup(num_cameras=NUM_CAMERAS, device=device)
    cameras = make_cameras(camera_model).to(device)
    optimizer.set_train_cameras(cameras, points=None if sampler == "camp-random" else scene_points(device))
    initial_p = optimizer.refiner.precond.clone()
    adam = torch.optim.Adam(list(optimizer.parameters()), lr=1e-3)
    bundle = ray_bundle(device)
    optimizer.apply_to_raybundle(bundle)
    loss = (bundle.directions * torch.linspace(-1.0, 1.0, 3, device=device)).sum() + bundle.origins.square().sum()
    loss.backward()
    gradients = torch.cat([p.grad.reshape(-1) for p in optimizer.parameters()])
    adam.step()
    optimizer.refiner.refresh(10, adam)  # P at the refined intrinsics, latent and Adam's moments re-expressed
    rays = cast_rays(
        optimizer.refiner,
        torch.tensor([0, 2, 1], device=device),
        torch.tensor([[0.5, 0.5], [40.0, 20.0], [63.5, 47.5]], device=device),
    )
    origins, directions, norms = rays.origins, rays.directions, rays.directions_norm
    refined = refined_nerfstudio_cameras(optimizer.refiner, cameras)
    camera = cameras[1:2]
    camera.metadata = {"cam_idx": 1}
    corrected = optimizer.apply_to_camera(camera)
    state = {key: value.cpu() for key, value in optimizer.state_dict().items()}  # a checkpoint, as torch.save has it
    resumed = config.setup(num_cameras=NUM_CAMERAS, device=device)
    # Loaded before the cameras are known, the layout announced first as the model does from the dataparser (the
    # order that needs no second P computation: the saved P is checked against the cameras and kept).
    resumed.refiner.set_camera_model(camera_model)
    resumed.load_state_dict(state)
    resumed.set_train_cameras(cameras, points=None if sampler == "camp-random" else scene_points(device))
    assert not resumed.refiner.preconditioner_is_stale
    return {
        "initial_p": initial_p,
        "p": optimizer.refiner.precond,
        "p_inv": optimizer.refiner.precond_inv,
        "gram": optimizer.refiner.gram,
        "proxy_range": optimizer.refiner.proxy_range,
        "gradients": gradients,
        "latent": optimizer.refiner.whitened_delta.detach(),
        "ray_origins": bundle.origins.detach(),
        "ray_directions": bundle.directions.detach(),
        "origins": origins.detach(),
        "directions": directions.detach(),
        "norms": norms.detach(),
        "refined_c2w": refined.camera_to_worlds,
        "refined_fx": refined.fx,
        "refined_distortion": refined.distortion_params,
        "corrected": corrected.detach(),
        "resumed_rays": cast_rays(
            resumed.refiner, torch.tensor([0, 2], device=device), torch.ones(2, 2, device=device)
        ).directions.detach(),
        "resumed_p": resumed.refiner.precond,
    }


FLOAT64_ISLANDS = ("initial_p", "p", "p_inv", "gram", "proxy_range")


OPTIMIZER_CASES = [
    ("RADIAL", "per-camera", "frolov"),
    ("OPENCV", "per-image", "camp-random"),
    ("FULL_OPENCV", "per-camera", "camp-random"),
    ("OPENCV_FISHEYE", "per-image", "frolov"),
]


@pytest.mark.parametrize(("camera_model", "intrinsics", "sampler"), OPTIMIZER_CASES)
def test_camera_optimizer_on_cuda(camera_model: str, intrinsics: str, sampler: str):
    """Every tensor of the run lands on "cuda" (P, P^-1, Sigma and the proxy range in float64), and every value is
    the CPU run's: P computation and refresh, ray regeneration and its gradients, Adam, refined cameras, the
    viewer's correction and a checkpoint saved on the CPU loaded back onto "cuda".

    Every camera model, both intrinsics modes and both kinds of point sets (the lattice with the proxy range from
    the scene's points, CamP's random sampler with its fixed range) each appear once: the emulation costs about six
    times the CPU run, and the tangential models' Newton undistortion is the costliest part.
    ``test_preconditioner_of_cuda_intrinsics_for_every_sampler`` covers the other point sets."""
    expected = optimizer_run("cpu", camera_model, intrinsics, sampler)
    with fake_cuda() as mode:
        got = optimizer_run("cuda", camera_model, intrinsics, sampler)
    assert mode.count("_linalg_eigh", "cuda", torch.float64) > 0, "the refresh's eigensolve ran on the device"
    for name, tensor in got.items():
        assert on_cuda(tensor), f"{name} is not on cuda: {type(tensor).__name__} on {tensor.device}"
        if name in FLOAT64_ISLANDS:
            assert tensor.dtype == torch.float64, name
        close(tensor, expected[name])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a real CUDA device (make gpu-check)")
@pytest.mark.parametrize(("camera_model", "intrinsics", "sampler"), OPTIMIZER_CASES)
def test_camera_optimizer_on_real_cuda(camera_model: str, intrinsics: str, sampler: str):
    """The emulated run of ``test_camera_optimizer_on_cuda`` on a real GPU: every tensor on CUDA, the values the
    CPU's up to the kernels' rounding (float32 sums over the rays in another order: 1e-4 relative; not yet run on a
    GPU, so the bound is an estimate)."""
    expected = optimizer_run("cpu", camera_model, intrinsics, sampler)
    got = optimizer_run("cuda", camera_model, intrinsics, sampler)
    for name, tensor in got.items():
        assert tensor.device.type == "cuda", name
        if name in FLOAT64_ISLANDS:
            assert tensor.dtype == torch.float64, name
        torch.testing.assert_close(tensor.cpu().to(expected[name].dtype), expected[name], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_preconditioner_of_cuda_intrinsics_for_every_sampler(sampler: str):
    """``compute_preconditioner`` of intrinsics on "cuda" (what a refresh passes): float64 on "cuda", the CPU's
    values; the proxy ranges from the scene, per camera."""
    intrinsics = Intrinsics.create(
        fx=torch.tensor([60.0, 62.0, 60.0]), fy=torch.tensor([61.0, 62.0, 61.0]), cx=torch.tensor([32.0, 31.0, 32.0]),
        cy=torch.tensor([24.0, 24.5, 24.0]), width=torch.full((3,), 64.0), height=torch.full((3,), 48.0),
        k1=-0.05, k2=0.01, model="perspective", dtype=torch.float64,
    )  # fmt: skip
    sampling = SamplingConfig(num_points=64, sampler=sampler)
    ranges = None if sampler == "camp-random" else torch.tensor([[0.3, 1.5], [0.5, 1.7], [0.3, 1.5]])
    expected = compute_preconditioner(intrinsics, sampling=sampling, ranges=ranges)
    with fake_cuda():
        got = compute_preconditioner(
            intrinsics.to(device="cuda"), sampling=sampling, ranges=None if ranges is None else ranges.to("cuda")
        )
    for name in ("matrix", "inverse", "gram"):
        tensor = getattr(got, name)
        assert on_cuda(tensor) and tensor.dtype == torch.float64, name
        close(tensor, getattr(expected, name))


def test_proxy_ranges_of_cuda_cameras_and_points():
    """``core.proxy_range.proxy_ranges`` called with everything on "cuda" (a framework-agnostic caller): every field
    of the result on the cameras' device, the CPU's values."""
    cameras = make_cameras("RADIAL")
    c2w, intrinsics = opengl_to_opencv(cameras.camera_to_worlds.double()), intrinsics_from_cameras(cameras)
    points, groups = scene_points("cpu").double(), torch.tensor([0, 0, 1])
    expected = proxy_ranges(points, c2w, intrinsics, groups)
    with fake_cuda():
        got = proxy_ranges(points.to("cuda"), c2w.to("cuda"), intrinsics.to(device="cuda"), groups.to("cuda"))
        stacked = got.stacked()
    for name in ("t_near", "t_far", "num_points", "fallback"):
        assert on_cuda(getattr(got, name)), name
        close(getattr(got, name), getattr(expected, name))
    assert on_cuda(stacked) and stacked.dtype == torch.float64 and not bool(values(got.fallback).any())


def test_track_reprojection_and_track_prior_on_cuda():
    """``core.tracks`` with points, cameras and observations on "cuda", and the camera optimizer's track prior
    (``set_track_prior`` from CPU values, ``apply_track_prior`` on the cuda latents): the CPU's values."""
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
    from s2camp_ns.core.tracks import Tracks, track_reprojection_rms

    cameras = make_cameras("RADIAL")
    c2w, intrinsics = opengl_to_opencv(cameras.camera_to_worlds.double()), intrinsics_from_cameras(cameras)
    points = scene_points("cpu").double()[:8]
    image = torch.arange(24) % 3
    point = torch.arange(24) % 8
    pixels = torch.rand(24, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 40.0
    expected = track_reprojection_rms(Tracks(points, image, point, pixels), c2w, intrinsics)
    config = S2CampCameraOptimizerConfig(track_prior=True)

    def prior_step(device: str) -> torch.Tensor:
        optimizer = config.setup(num_cameras=3, device=device)
        optimizer.set_train_cameras(cameras.to(device))
        with torch.no_grad():
            optimizer.refiner.whitened_delta.fill_(1.0)
        optimizer.set_track_prior(expected)  # the data parser's CPU tensor
        optimizer.refiner.apply_track_prior(1e-3)
        return optimizer.refiner.whitened_delta.detach()

    reference = prior_step("cpu")
    with fake_cuda():
        tracks = Tracks(points.to("cuda"), image.to("cuda"), point.to("cuda"), pixels.to("cuda"))
        got = track_reprojection_rms(tracks, c2w.to("cuda"), intrinsics.to(device="cuda"))
        latent = prior_step("cuda")
    assert on_cuda(got) and on_cuda(latent)
    close(got, expected)
    close(latent, reference)
    assert float(values(latent).max()) < 1.0  # the prior did shrink the latent


# ------------------------------------------------------------------------------------ core: evaluation helpers
def test_perturbation_camera_errors_and_drift_on_cuda():
    cameras = make_cameras("RADIAL")
    c2w, fx = opengl_to_opencv(cameras.camera_to_worlds.double()), cameras.fx.reshape(-1).double()
    intrinsics = Intrinsics.create(
        fx=fx, fy=fx, cx=torch.full((3,), 32.0), cy=torch.full((3,), 24.0), width=torch.full((3,), 64.0),
        height=torch.full((3,), 48.0), model="perspective", dtype=torch.float64,
    )  # fmt: skip
    points = scene_points("cpu").double()
    expected = perturb_cameras(c2w, fx)
    expected_errors = camera_errors(expected.c2w, c2w, expected.fx, fx)
    expected_drift = reprojection_drift(points, c2w, intrinsics, expected.c2w, intrinsics)
    with fake_cuda():
        got = perturb_cameras(c2w.to("cuda"), fx.to("cuda"))
        errors = camera_errors(got.c2w, c2w.to("cuda"), got.fx, fx.to("cuda"))
        drift = reprojection_drift(
            points.to("cuda"), c2w.to("cuda"), intrinsics.to(device="cuda"), got.c2w, intrinsics.to(device="cuda")
        )
    assert on_cuda(got.c2w) and on_cuda(got.fx)
    close(got.c2w, expected.c2w)
    assert errors == pytest.approx(expected_errors, rel=1e-9, abs=1e-12)
    assert drift.rms_px == pytest.approx(expected_drift.rms_px, rel=1e-9) and drift.pairs == expected_drift.pairs


# ------------------------------------------------------------------------------------- the nerfstudio pipeline
def pipeline_config(scene: Path):
    from s2camp_ns.method_config import s2camp_method

    config = copy.deepcopy(s2camp_method.config)
    datamanager = config.pipeline.datamanager
    datamanager.data = scene
    datamanager.dataparser.data = scene
    datamanager.dataparser.perturbation.enabled = True  # reference cameras: camera errors, frusta, alignment
    datamanager.dataparser.downscale_factor = 2  # 32 x 24 images: the full-image renders stay cheap
    datamanager.train_num_rays_per_batch = datamanager.eval_num_rays_per_batch = 64
    config.pipeline.model = tiny_model_config(
        S2CampCameraOptimizerConfig(sampling=SamplingConfig(num_points=64), refresh_every=1),
        samples_per_ray=4,
        camera_error_every=1,
    )
    return config


@pytest.fixture(scope="module")
def cuda_pipeline(tiny_scene: Path):
    """The S2CamP pipeline (data manager, dataparser with perturbed cameras, sized-down nerfacto) built on "cuda",
    and its trainer optimizers."""
    from nerfstudio.engine.optimizers import Optimizers

    from s2camp_ns.method.trainer import with_run_length

    config = pipeline_config(tiny_scene)
    with lpips_offline(), fake_cuda():
        pipeline = config.pipeline.setup(device="cuda", test_mode="val")
        optimizers = Optimizers(with_run_length(config.optimizers, 100), pipeline.get_param_groups())
    return pipeline, optimizers


def test_training_step_on_cuda(cuda_pipeline):
    """``next_train`` (rays and their pixels on "cuda"), the model's outputs, losses and metrics, backward, the
    optimizers' step and the training callbacks (refresh of P, camera errors) all on "cuda"."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes

    pipeline, optimizers = cuda_pipeline
    model = pipeline.model
    with fake_cuda() as mode:
        callbacks = model.get_training_callbacks(TrainingCallbackAttributes(optimizers, None, pipeline, None))
        ray_bundle, batch = pipeline.datamanager.next_train(1)
        assert on_cuda(ray_bundle.origins) and on_cuda(ray_bundle.metadata[PIXEL_KEY])
        pixels, indices = values(ray_bundle.metadata[PIXEL_KEY]), batch["indices"].cpu()
        torch.testing.assert_close(pixels, indices[:, [2, 1]].float() + 0.5)  # each ray's own pixel centre
        outputs = model(ray_bundle)
        metrics = model.get_metrics_dict(outputs, batch)
        loss_dict = model.get_loss_dict(outputs, batch, metrics)
        optimizers.zero_grad_all()
        sum(loss_dict.values()).backward()
        latent_before = values(model.camera_optimizer.refiner.whitened_delta).clone()
        optimizers.optimizer_step_all()
        optimizers.scheduler_step_all(1)
        for callback in callbacks:
            callback.run_callback_at_location(1, callback.where_to_run[0])
    assert on_cuda(outputs["rgb"]) and on_cuda(metrics["psnr"])
    assert all(on_cuda(loss) and math.isfinite(float(loss)) for loss in loss_dict.values())
    for group, parameters in model.get_param_groups().items():
        assert all(on_cuda(p) and (p.grad is None or on_cuda(p.grad)) for p in parameters), group
    camera_optimizer = model.camera_optimizer
    assert not torch.equal(values(camera_optimizer.refiner.whitened_delta), latent_before), "Adam moved the cameras"
    assert int(camera_optimizer.refiner.last_refresh_step) == 1 and on_cuda(camera_optimizer.refiner.precond)
    assert mode.count("_linalg_eigh", "cuda", torch.float64) > 0
    assert model._camera_errors["camera_errors/aligned"] == 1.0


def test_global_batch_sampling_on_cuda(cuda_pipeline, monkeypatch):
    """The data manager's global batch sampling (docs/SCALING.md) with the model on "cuda": the rays and their pixels
    on "cuda", each ray's pixel the one the sampler drew. The CUDA generator state that ``fork_rng`` saves on a GPU
    does not exist here, so the fork keeps the CPU's generator only (the sampler draws on the images' device, the
    CPU)."""
    pipeline, _ = cuda_pipeline
    datamanager = pipeline.datamanager
    fork_rng = torch.random.fork_rng
    monkeypatch.setattr(torch.random, "fork_rng", lambda devices=(), **kwargs: fork_rng(devices=[], **kwargs))
    monkeypatch.setattr(datamanager.config, "global_batch_sampling", True)
    with fake_cuda():
        ray_bundle, batch = datamanager.next_train(2)
    assert on_cuda(ray_bundle.origins) and on_cuda(ray_bundle.metadata[PIXEL_KEY])
    assert batch["indices"].shape[0] == ray_bundle.origins.shape[0] == datamanager.config.train_num_rays_per_batch
    torch.testing.assert_close(values(ray_bundle.metadata[PIXEL_KEY]), batch["indices"][:, [2, 1]].float() + 0.5)


def test_viewer_panel_rendering_and_test_time_alignment_on_cuda(cuda_pipeline):
    """The viewer panel's values and frusta, rendering a refined training camera, the test-time alignment of the
    held-out views, and the refined cameras exported as a COLMAP model, from a model on "cuda"."""
    from s2camp_ns.data.colmap_writer import nerfstudio_to_reconstruction
    from s2camp_ns.scripts.export_cameras import refined_training_cameras
    from s2camp_ns.scripts.test_time_alignment import AlignmentConfig, evaluate_held_out_views

    pipeline, _ = cuda_pipeline
    model = pipeline.model
    outputs = pipeline.datamanager.train_dataparser_outputs
    with fake_cuda():
        panel = model.S2CamP.panel_values(step=3)
        frusta = {which: model.camera_frusta(which) for which in ("refined", "initial", "reference")}
        drawn = {which: model.S2CamP._frustum_params(frusta[which], [0, 2]) for which in frusta}  # numpy for viser
        camera = pipeline.datamanager.train_dataset.cameras[0:1].to("cuda")
        camera.metadata = {TRAIN_CAMERA_KEY: 0}
        model.eval()  # as nerfstudio's evaluation and viewer render
        try:
            rendered = model.get_outputs_for_camera(camera)
            image = rendered["rgb"]
            metrics, _ = model.get_image_metrics_and_images(rendered, {"image": torch.rand(*image.shape)})
        finally:
            model.train()
        aligned = evaluate_held_out_views(pipeline, AlignmentConfig(steps=2, rays=16, chunk=1024))
        refined = refined_training_cameras(pipeline)
        reconstruction = nerfstudio_to_reconstruction(
            refined, outputs.dataparser_transform, outputs.dataparser_scale, outputs.metadata["image_names"]
        )
    assert panel["b_errors"] == "mean / max" and panel["g_condition_sigma"] != "n/a"
    assert all(f is not None for f in frusta.values())
    assert all(positions.shape == (2, 3) and math.isfinite(positions.sum()) for positions, *_ in drawn.values())
    assert on_cuda(image) and image.shape[-1] == 3
    assert math.isfinite(metrics["psnr"]) and "lpips" not in metrics  # LPIPS offline here
    assert len(aligned) == len(pipeline.datamanager.eval_dataset)
    assert all(math.isfinite(view.psnr) for view in aligned)
    assert refined.device == pipeline.datamanager.train_dataset.cameras.device  # Cameras come back where they were
    refined_fx = values(model.camera_optimizer.refiner.refined_intrinsics().fx)
    torch.testing.assert_close(refined.fx.cpu(), refined_fx[:, None].float())
    assert reconstruction.num_images() == model.camera_optimizer.num_cameras
