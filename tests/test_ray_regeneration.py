"""Training rays regenerated from pixel coordinates agree with nerfstudio's rays, and intrinsics move them."""

from __future__ import annotations

import math

import pytest
import torch
from latents import set_latent_column, write_latent
from nerfstudio.cameras.cameras import Cameras, CameraType

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer, S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.data.camera_conversion import refined_nerfstudio_cameras
from s2camp_ns.method.datamanager import PixelRayGenerator
from s2camp_ns.method.rays import PIXEL_KEY, cast_rays, train_camera_raybundle

NUM_CAMERAS = 2
WIDTH, HEIGHT = 80, 60


def make_cameras(
    k1: float,
    k2: float,
    k3: float = 0.0,
    k4: float = 0.0,
    p1: float = 0.0,
    p2: float = 0.0,
    camera_type: CameraType = CameraType.PERSPECTIVE,
    focal_scale: float = 1.0,
) -> Cameras:
    """Two cameras with nerfstudio distortion_params [k1, k2, k3, k4, p1, p2] (its own meaning)."""
    angle = torch.tensor([0.3, -0.4])
    rotation = torch.zeros(NUM_CAMERAS, 3, 3)
    rotation[:, 0, 0], rotation[:, 0, 2] = angle.cos(), angle.sin()
    rotation[:, 1, 1] = 1.0
    rotation[:, 2, 0], rotation[:, 2, 2] = -angle.sin(), angle.cos()
    c2w = torch.cat([rotation, torch.tensor([[0.5, -0.2, 1.0], [-0.3, 0.4, 2.0]])[:, :, None]], dim=-1)
    distortion = torch.tensor([k1, k2, k3, k4, p1, p2]).expand(NUM_CAMERAS, 6).clone()
    return Cameras(
        camera_to_worlds=c2w,
        fx=torch.tensor([[70.0], [75.0]]) * focal_scale,
        fy=torch.tensor([[71.0], [74.0]]) * focal_scale,
        cx=torch.tensor([[40.0], [41.5]]),
        cy=torch.tensor([[30.0], [29.0]]),
        width=WIDTH,
        height=HEIGHT,
        distortion_params=distortion,
        camera_type=camera_type,
    )


def all_ray_indices() -> torch.Tensor:
    c, y, x = torch.meshgrid(torch.arange(NUM_CAMERAS), torch.arange(HEIGHT), torch.arange(WIDTH), indexing="ij")
    return torch.stack([c, y, x], dim=-1).reshape(-1, 3)


def make_optimizer(cameras: Cameras, **overrides) -> S2CampCameraOptimizer:
    config = S2CampCameraOptimizerConfig(
        **{"sampling": SamplingConfig(num_points=32, sampler="camp-random"), "intrinsics": "per-image", **overrides}
    )
    optimizer = config.setup(num_cameras=NUM_CAMERAS, device="cpu")
    optimizer.set_train_cameras(cameras)
    return optimizer


def test_pixel_ray_generator_carries_pixel_centres():
    cameras = make_cameras(0.0, 0.0)
    indices = torch.tensor([[0, 0, 0], [1, 5, 7], [0, HEIGHT - 1, WIDTH - 1]])
    bundle = PixelRayGenerator(cameras)(indices)
    expected = torch.tensor([[0.5, 0.5], [7.5, 5.5], [WIDTH - 0.5, HEIGHT - 0.5]])
    torch.testing.assert_close(bundle.metadata[PIXEL_KEY], expected)


OPENCV = dict(k1=-0.12, k2=0.03, p1=0.004, p2=-0.003)
FULL_OPENCV = dict(k1=-0.1, k2=0.02, k3=-0.002, p1=-0.002, p2=0.003)
FISHEYE = dict(k1=0.03, k2=-0.01, k3=0.002, k4=-0.0003, camera_type=CameraType.FISHEYE)
WIDE_FISHEYE = dict(FISHEYE, focal_scale=0.42)  # corners about 96 degrees off the axis
CAMERA_MODELS = {
    "pinhole": dict(k1=0.0, k2=0.0),
    "radial_barrel": dict(k1=-0.12, k2=0.03),
    "radial_pincushion": dict(k1=0.08, k2=0.01),
    "opencv": OPENCV,
    "full_opencv": FULL_OPENCV,
    "fisheye": FISHEYE,
    "wide_fisheye": WIDE_FISHEYE,
}


@pytest.mark.parametrize("model", list(CAMERA_MODELS))
def test_zero_delta_rays_equal_nerfstudio_rays(model: str):
    """With zero deltas, regenerated rays reproduce nerfstudio's (including its undistortion) to ~1e-5: nerfstudio's
    distortion_params mean for S2CamP what they mean for nerfstudio's own renderer."""
    cameras = make_cameras(**CAMERA_MODELS[model])
    stock = PixelRayGenerator(cameras)(all_ray_indices())
    bundle = PixelRayGenerator(cameras)(all_ray_indices())
    optimizer = make_optimizer(cameras)
    optimizer.apply_to_raybundle(bundle)
    torch.testing.assert_close(bundle.origins, stock.origins, atol=1e-6, rtol=0)
    torch.testing.assert_close(bundle.directions, stock.directions, atol=1e-5, rtol=0)
    torch.testing.assert_close(
        bundle.metadata["directions_norm"], stock.metadata["directions_norm"], atol=1e-5, rtol=1e-5
    )


def test_pixel_area_follows_the_refined_focal_length():
    """Cone footprints: with the focal length refined from (fx, fy) to (fx + d, fy + d), every ray's pixel_area is
    the solid angle of a pixel at the refined camera's principal point, 1 / ((fx + d)(fy + d)), which there equals
    the one nerfstudio computes for a camera with the refined focal lengths."""
    cameras = make_cameras(0.0, 0.0)
    d = 6.0  # pixels, raw focal delta (P = I)
    optimizer = make_optimizer(cameras, precondition=False)
    set_latent_column(optimizer.refiner, 6, d)
    bundle = PixelRayGenerator(cameras)(all_ray_indices())
    optimizer.apply_to_raybundle(bundle)
    per_camera = torch.tensor([1.0 / (76.0 * 77.0), 1.0 / (81.0 * 80.0)])
    torch.testing.assert_close(bundle.pixel_area, per_camera[all_ray_indices()[:, 0]][:, None], rtol=1e-6, atol=0)
    refocused = make_cameras(0.0, 0.0)
    refocused.fx, refocused.fy = refocused.fx + d, refocused.fy + d
    centre = torch.tensor([[0, 30, 40]])  # camera 0's principal point (40, 30) is this pixel's corner
    at_centre = PixelRayGenerator(cameras)(centre)
    optimizer.apply_to_raybundle(at_centre)
    torch.testing.assert_close(at_centre.pixel_area, PixelRayGenerator(refocused)(centre).pixel_area, rtol=1e-3, atol=0)


@pytest.mark.parametrize(
    "column, value",
    [(6, 3.0), (7, 1.5), (8, -1.5), (9, 0.8), (10, 0.05), (11, 0.02), (3, 0.01), (0, 0.02)],
)
def test_each_parameter_moves_the_rays(column: int, value: float):
    cameras = make_cameras(-0.05, 0.0)
    optimizer = make_optimizer(cameras, precondition=False)
    reference = PixelRayGenerator(cameras)(all_ray_indices())
    optimizer.apply_to_raybundle(reference)
    set_latent_column(optimizer.refiner, column, value)
    bundle = PixelRayGenerator(cameras)(all_ray_indices())
    optimizer.apply_to_raybundle(bundle)
    moved = (bundle.directions - reference.directions).norm(dim=-1).amax()
    moved = moved + (bundle.origins - reference.origins).norm(dim=-1).amax()
    assert moved > 1e-4


@pytest.mark.parametrize("model", ["radial", "opencv", "full_opencv", "fisheye", "wide_fisheye"])
def test_refined_nerfstudio_cameras_match_regenerated_rays(model: str):
    """Eval-style rendering through refine_cameras (nerfstudio's own ray generation) equals the training rays: the
    refined distortion goes back in nerfstudio's meaning."""
    cameras = make_cameras(**(CAMERA_MODELS[model] if model != "radial" else dict(k1=-0.05, k2=0.01)))
    # Raw deltas (P = I) so that skew, which nerfstudio's Cameras cannot express, stays exactly zero.
    optimizer = make_optimizer(cameras, precondition=False)
    full = torch.tensor([0.02, -0.01, 0.03, 0.01, -0.02, 0.015, 2.0, 1.0, -1.5, 0.0, 0.02, -0.005])
    full = torch.cat([full, torch.tensor([0.001, 0.0001, 0.001, -0.0005])])  # k3, k4, p1, p2
    raw = full[list(optimizer.refiner.layout.indices)]
    assert optimizer.refiner.layout.num_params == {"radial": 12, "opencv": 14, "full_opencv": 15}.get(model, 14)
    write_latent(optimizer.refiner, raw.expand(NUM_CAMERAS, raw.shape[0]) * torch.tensor([[1.0], [-0.5]]))
    refined = refined_nerfstudio_cameras(optimizer.refiner, cameras)
    stock = PixelRayGenerator(refined)(all_ray_indices())
    bundle = PixelRayGenerator(cameras)(all_ray_indices())
    with torch.no_grad():
        optimizer.apply_to_raybundle(bundle)
    torch.testing.assert_close(bundle.origins, stock.origins, atol=1e-5, rtol=0)
    torch.testing.assert_close(bundle.directions, stock.directions, atol=1e-4, rtol=0)


def test_train_camera_raybundle_matches_training_rays():
    cameras = make_cameras(-0.05, 0.01)
    optimizer = make_optimizer(cameras)
    with torch.no_grad():
        for latent in optimizer.parameters():
            latent.normal_(0.0, 0.05, generator=torch.Generator().manual_seed(1))
    image = train_camera_raybundle(optimizer.refiner, 1)
    assert image.origins.shape == (HEIGHT, WIDTH, 3)
    bundle = PixelRayGenerator(cameras)(all_ray_indices())
    with torch.no_grad():
        optimizer.apply_to_raybundle(bundle)
    per_camera = bundle.directions.reshape(NUM_CAMERAS, HEIGHT, WIDTH, 3)[1]
    torch.testing.assert_close(image.directions, per_camera)
    assert math.isclose(float(image.directions.norm(dim=-1).mean()), 1.0, rel_tol=1e-5)


@pytest.mark.parametrize("intrinsics", ["per-image", "per-camera"])
def test_cast_rays_are_every_camera_refined_then_indexed_per_ray(intrinsics: str):
    """A step refines every camera once and gathers each ray's: the rays and gradients of the camera-by-camera
    reference, and exact zeros for the cameras no ray came from."""
    cameras = make_cameras(-0.05, 0.01)
    optimizer = make_optimizer(cameras, intrinsics=intrinsics)
    latents = list(optimizer.parameters())
    assert len(latents) == 2  # the pose per image, the intrinsics per physical camera or per image
    with torch.no_grad():
        for latent in latents:
            latent.copy_(torch.linspace(-2e-3, 3e-3, latent.numel()).reshape(latent.shape))
    camera_indices = torch.tensor([1, 1, 1, 1])  # camera 0 is not in this batch
    pixels = torch.tensor([[3.5, 4.5], [40.0, 30.0], [79.5, 0.5], [10.25, 55.75]])

    rays = cast_rays(optimizer.refiner, camera_indices, pixels, dtype=torch.float64)
    origins, directions, norms = rays.origins, rays.directions, rays.directions_norm
    (origins.sum() + directions.sum() + norms.sum()).backward()
    batch_gradients = [latent.grad.clone() for latent in latents]
    for latent in latents:
        latent.grad = None

    # Reference: every camera refined, then indexed per ray.
    from s2camp_ns.core.camera import pixel_to_ray_direction

    deltas = optimizer.refiner.deltas()
    intrinsics = optimizer.refiner.refined_intrinsics(deltas)[camera_indices]
    c2w = optimizer.refiner.refined_c2w(deltas)[camera_indices]
    directions_cam = pixel_to_ray_direction(pixels.to(torch.float64)[:, None, :], intrinsics)[:, 0]
    expected_directions = (c2w[:, :, :3] @ directions_cam[:, :, None])[..., 0]
    expected_origins = c2w[:, :, 3]
    (expected_origins.sum() + expected_directions.sum() + (1.0 / directions_cam[:, 2:3]).sum()).backward()

    torch.testing.assert_close(origins, expected_origins, rtol=0, atol=1e-12)
    torch.testing.assert_close(directions, expected_directions, rtol=0, atol=1e-12)
    for batch_gradient, latent in zip(batch_gradients, latents, strict=True):
        torch.testing.assert_close(batch_gradient, latent.grad, rtol=1e-10, atol=0)
        # Camera 0 (its own physical camera: other intrinsics) is in no ray of the batch.
        assert torch.equal(batch_gradient[0], torch.zeros_like(batch_gradient[0]))
        assert bool((batch_gradient[1] != 0).any())
