"""Every supported COLMAP camera model against pycolmap, round trips, implicit gradients, validation and layouts."""

from __future__ import annotations

import math

import numpy as np
import pycolmap
import pytest
import torch

from s2camp_ns.core.camera import (
    Intrinsics,
    ParameterLayout,
    pixel_to_ray_direction,
    project,
    tangent_bounds,
    unproject,
    vertical_field_of_view,
)
from s2camp_ns.core.colmap_camera_models import (
    COLMAP_PARAMETERS,
    colmap_model_for,
    colmap_to_values,
    intrinsics_from_colmap,
    values_to_colmap,
)

WIDTH, HEIGHT = 640, 480


def random_colmap_params(model: str, seed: int) -> list[float]:
    """Plausible random parameters of ``model`` (COLMAP order) for a 640 x 480 image: mild distortion, and
    fisheyes that see past 90 degrees."""
    rng = np.random.default_rng(seed)
    fisheye = model == "OPENCV_FISHEYE"
    focal = rng.uniform(140.0, 180.0) if fisheye else rng.uniform(250.0, 700.0)
    draws = {
        "f": focal,
        "fx": focal,
        "fy": focal * rng.uniform(0.97, 1.03),
        "cx": WIDTH / 2 + rng.uniform(-15.0, 15.0),
        "cy": HEIGHT / 2 + rng.uniform(-15.0, 15.0),
        "k": rng.uniform(-0.08, 0.08),
        "k1": rng.uniform(-0.02, 0.08) if fisheye else rng.uniform(-0.08, 0.08),
        "k2": rng.uniform(-0.005, 0.01) if fisheye else rng.uniform(-0.01, 0.01),
        "k3": rng.uniform(-5e-4, 2e-3) if fisheye else rng.uniform(-0.002, 0.002),
        "k4": rng.uniform(0.0, 3e-4) if fisheye else 0.0,
        "k5": 0.0,
        "k6": 0.0,
        "p1": rng.uniform(-0.003, 0.003),
        "p2": rng.uniform(-0.003, 0.003),
    }
    return [float(draws[name]) for name in COLMAP_PARAMETERS[model]]


def _random_pixels(count: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(1, count, 2, generator=generator, dtype=torch.float64) * torch.tensor([WIDTH, HEIGHT.__float__()])


def _relative_error(ours: np.ndarray, reference: np.ndarray) -> float:
    return float((np.abs(ours - reference) / np.maximum(np.abs(reference), 1.0)).max())


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("model", list(COLMAP_PARAMETERS))
def test_project_and_unproject_agree_with_pycolmap(model: str, seed: int) -> None:
    params = random_colmap_params(model, seed)
    intrinsics = intrinsics_from_colmap(model, params, WIDTH, HEIGHT)
    camera = pycolmap.Camera(model=model, width=WIDTH, height=HEIGHT, params=params)
    generator = torch.Generator().manual_seed(100 + seed)
    directions = pixel_to_ray_direction(_random_pixels(400, seed), intrinsics)
    depth = 0.3 + 20.0 * torch.rand(1, 400, 1, generator=generator, dtype=torch.float64)
    points = directions * depth
    # pycolmap (like COLMAP) projects only points in front of the camera; the fisheye sees past 90 degrees.
    front = (points[0, :, 2] > 1e-3 * depth[0, :, 0]).numpy()
    if model == "OPENCV_FISHEYE":
        assert (~front).sum() > 0, "the fisheye test must cover rays beyond 90 degrees"
    pixels, _ = project(points, intrinsics)
    expected = camera.img_from_cam(points[0].numpy()[front])
    assert _relative_error(pixels[0].numpy()[front], expected) < 1e-6
    # Unprojection: tangents (x/z, y/z) of random pixels, against pycolmap's cam_from_img.
    inside = _random_pixels(400, 50 + seed)
    tangents = unproject(inside, intrinsics)[0].numpy()
    reference = camera.cam_from_img(inside[0].numpy())
    if model == "OPENCV_FISHEYE":
        # Tangents exist below 90 degrees only (pycolmap's undistortion does not converge past it): keep pixels
        # whose distorted radius theta_d is below that of theta = 80 degrees (COLMAP's polynomial, written out).
        fx, fy, cx, cy, k1, k2, k3, k4 = params
        theta = math.radians(80.0)
        limit = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
        keep = np.hypot((inside[0, :, 0].numpy() - cx) / fx, (inside[0, :, 1].numpy() - cy) / fy) < limit
        assert keep.sum() > 100
        tangents, reference = tangents[keep], reference[keep]
    assert _relative_error(tangents, reference) < 1e-6


@pytest.mark.parametrize("model", list(COLMAP_PARAMETERS))
def test_pixel_ray_pixel_round_trip(model: str) -> None:
    intrinsics = intrinsics_from_colmap(model, random_colmap_params(model, seed=7), WIDTH, HEIGHT)
    pixels = _random_pixels(3000, seed=8)
    corners = torch.tensor([[[0.0, 0.0], [WIDTH, 0.0], [0.0, HEIGHT], [WIDTH, HEIGHT]]], dtype=torch.float64)
    pixels = torch.cat([pixels, corners], dim=1)
    directions = pixel_to_ray_direction(pixels, intrinsics)
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones_like(directions[..., 0]))
    reprojected, margin = project(directions * 3.0, intrinsics)
    assert (margin > 0).all()
    assert (reprojected - pixels).abs().max() < 1e-4


def test_fisheye_sees_beyond_90_degrees() -> None:
    # 640 px wide at f = 180 px: the corners are 2.2 rad (127 degrees) off the axis.
    intrinsics = intrinsics_from_colmap("OPENCV_FISHEYE", [180.0, 180.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0], 640, 480)
    corner = pixel_to_ray_direction(torch.tensor([[[0.0, 0.0]]], dtype=torch.float64), intrinsics)[0, 0]
    radius = math.hypot(320.0, 240.0) / 180.0  # equidistant: theta = theta_d without distortion
    assert math.isclose(math.acos(float(corner[2])), radius, rel_tol=1e-12)
    assert corner[2] < 0
    # Straight behind and at the camera centre the projection is invalid, not NaN.
    pixels, margin = project(torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]], dtype=torch.float64), intrinsics)
    assert torch.isfinite(pixels).all() and (margin <= 0).all()


def test_full_opencv_rational_part_is_refused() -> None:
    params = random_colmap_params("FULL_OPENCV", seed=1)
    params[9] = 0.01  # k4 of the denominator
    with pytest.raises(ValueError, match=r"FULL_OPENCV.*k4 = 0\.01"):
        colmap_to_values("FULL_OPENCV", params)


def test_unknown_model_and_wrong_parameter_count_are_named() -> None:
    with pytest.raises(ValueError, match="'FOV' is not supported; supported are SIMPLE_PINHOLE"):
        colmap_to_values("FOV", [1.0, 1.0, 1.0, 1.0, 0.1])
    with pytest.raises(ValueError, match=r"OPENCV has 8 parameters .* got 5"):
        colmap_to_values("OPENCV", [1.0] * 5)


@pytest.mark.parametrize("model", list(COLMAP_PARAMETERS))
def test_colmap_parameters_round_trip(model: str) -> None:
    params = random_colmap_params(model, seed=3)
    values = colmap_to_values(model, params)
    projection = "fisheye" if model == "OPENCV_FISHEYE" else "perspective"
    assert values_to_colmap(model, values, projection) == pytest.approx(params, rel=0, abs=0)
    simplest = colmap_model_for(values, projection)
    expected = {
        "SIMPLE_PINHOLE": "RADIAL",
        "PINHOLE": "OPENCV",
        "SIMPLE_RADIAL": "RADIAL",
        "RADIAL": "RADIAL",
        "OPENCV": "OPENCV",
        "FULL_OPENCV": "FULL_OPENCV",
        "OPENCV_FISHEYE": "OPENCV_FISHEYE",
    }[model]
    assert simplest == expected
    # The simplest model is the same camera for pycolmap.
    points = np.array([[0.1, -0.2, 1.0], [0.3, 0.2, 2.0], [-0.25, 0.1, 1.5]])
    original = pycolmap.Camera(model=model, width=WIDTH, height=HEIGHT, params=params)
    rewritten = pycolmap.Camera(
        model=simplest, width=WIDTH, height=HEIGHT, params=values_to_colmap(simplest, values, projection)
    )
    np.testing.assert_allclose(rewritten.img_from_cam(points), original.img_from_cam(points), rtol=1e-12)


def test_values_that_a_colmap_model_cannot_hold_are_refused() -> None:
    values = colmap_to_values("OPENCV", random_colmap_params("OPENCV", seed=4))
    with pytest.raises(ValueError, match="RADIAL needs fx = fy"):
        values_to_colmap("RADIAL", {**values, "fy": values["fx"] * 1.01}, "perspective")
    with pytest.raises(ValueError, match="RADIAL has no p1"):
        values_to_colmap("RADIAL", {**values, "fy": values["fx"]}, "perspective")
    with pytest.raises(ValueError, match=r"k4 = 0\.001 \(a polynomial r\^8 term\)"):
        values_to_colmap("FULL_OPENCV", {**values, "k4": 0.001}, "perspective")
    with pytest.raises(ValueError, match="OPENCV_FISHEYE is a fisheye model"):
        values_to_colmap("OPENCV_FISHEYE", values, "perspective")


@pytest.mark.parametrize(
    ("model", "name"),
    [("OPENCV", "p1"), ("FULL_OPENCV", "k3"), ("OPENCV_FISHEYE", "k2"), ("OPENCV_FISHEYE", "k4"), ("OPENCV", "k2")],
)
def test_undistortion_gradient_matches_finite_differences(model: str, name: str) -> None:
    base = intrinsics_from_colmap(model, random_colmap_params(model, seed=5), WIDTH, HEIGHT)
    pixels = torch.tensor([[[610.0, 455.0], [20.0, 300.0], [330.0, 250.0]]], dtype=torch.float64)
    coefficient = getattr(base, name).clone().requires_grad_(True)
    directions = pixel_to_ray_direction(pixels, Intrinsics(**{**base.__dict__, name: coefficient}))
    (grad,) = torch.autograd.grad(directions.sum(), coefficient)
    step = 1e-7  # k4 multiplies theta^8 (up to ~400 here): larger steps see the curvature
    plus = pixel_to_ray_direction(pixels, Intrinsics(**{**base.__dict__, name: coefficient.detach() + step})).sum()
    minus = pixel_to_ray_direction(pixels, Intrinsics(**{**base.__dict__, name: coefficient.detach() - step})).sum()
    assert torch.isclose(grad[0], (plus - minus) / (2 * step), rtol=1e-6, atol=1e-6)


def test_tangential_fold_inside_the_image_is_refused() -> None:
    with pytest.raises(ValueError, match=r"k1, k2, k3, k4, p1, p2 = \(0, 0, 0, 0, 0\.3, 0\) of camera 0"):
        Intrinsics.create(fx=300.0, fy=300.0, cx=320.0, cy=240.0, width=640, height=480, p1=0.3)


def test_fisheye_fold_inside_the_image_is_refused() -> None:
    with pytest.raises(ValueError, match=r"k1, k2, k3, k4 = \(-0\.3, 0, 0, 0\) of fisheye camera 0"):
        Intrinsics.create(fx=200.0, fy=200.0, cx=320.0, cy=240.0, width=640, height=480, k1=-0.3, model="fisheye")


def test_mild_tangential_and_fisheye_distortion_are_accepted() -> None:
    Intrinsics.create(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480, k1=-0.1, p1=0.003, p2=-0.002)
    Intrinsics.create(fx=180.0, fy=180.0, cx=320.0, cy=240.0, width=640, height=480, k1=0.05, k2=-0.01, model="fisheye")


def test_unknown_projection_is_named() -> None:
    with pytest.raises(ValueError, match="model must be one of 'perspective', 'fisheye', got 'equirectangular'"):
        Intrinsics.create(fx=1.0, fy=1.0, cx=1.0, cy=1.0, width=2, height=2, model="equirectangular")


def test_fisheye_has_no_tangent_box() -> None:
    intrinsics = intrinsics_from_colmap("OPENCV_FISHEYE", random_colmap_params("OPENCV_FISHEYE", 0), WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="perspective camera, got model 'fisheye'"):
        tangent_bounds(intrinsics)


@pytest.mark.parametrize(
    ("camera_model", "distortion"),
    [
        ("PINHOLE", ("k1", "k2")),
        ("RADIAL", ("k1", "k2")),
        ("OPENCV", ("k1", "k2", "p1", "p2")),
        ("FULL_OPENCV", ("k1", "k2", "k3", "p1", "p2")),
        ("OPENCV_FISHEYE", ("k1", "k2", "k3", "k4")),
    ],
)
def test_presets_refine_the_coefficients_of_the_camera_model(camera_model: str, distortion: tuple) -> None:
    intrinsic = ("focal", "cx", "cy", "skew")
    pose = ("rho_x", "rho_y", "rho_z", "omega_x", "omega_y", "omega_z")
    assert ParameterLayout.from_preset("all", camera_model).names == pose + intrinsic + distortion
    assert ParameterLayout.from_preset("pose+intrinsics", camera_model).names == pose + intrinsic
    assert ParameterLayout.from_preset("pose", camera_model).names == pose
    with pytest.raises(ValueError, match="camera_model must be one of"):
        ParameterLayout.from_preset("all", "FOV")


def test_deltas_of_the_paper_twelve_or_all_sixteen_parameters() -> None:
    intrinsics = intrinsics_from_colmap("OPENCV", random_colmap_params("OPENCV", seed=9), WIDTH, HEIGHT)
    twelve = torch.linspace(0.1, 1.2, 12, dtype=torch.float64)[None]
    full = torch.cat([twelve, torch.zeros(1, 4, dtype=torch.float64)], dim=-1)
    for name in ("fx", "cx", "skew", "k2", "p1", "p2"):
        assert torch.equal(getattr(intrinsics.with_delta(twelve), name), getattr(intrinsics.with_delta(full), name))
    with pytest.raises(ValueError, match="delta must have 16 columns .* or the paper's 12, got 13"):
        intrinsics.with_delta(torch.zeros(1, 13, dtype=torch.float64))


def test_vertical_field_of_view_against_closed_forms():
    # Pinhole, centred and off-centre principal point: atan of each half-height over the focal length.
    pinhole = intrinsics_from_colmap("PINHOLE", [300.0, 250.0, 320.0, 240.0], 640, 480)
    off_centre = intrinsics_from_colmap("PINHOLE", [300.0, 250.0, 320.0, 100.0], 640, 480)
    # Equidistant fisheye without distortion: the angle is the image distance over f, past 180 degrees here.
    fisheye = intrinsics_from_colmap("OPENCV_FISHEYE", [110.0, 110.0, 240.0, 240.0, 0.0, 0.0, 0.0, 0.0], 480, 480)
    torch.testing.assert_close(vertical_field_of_view(pinhole), torch.tensor([2 * math.atan(240 / 250)]).double())
    expected = math.atan(100 / 250) + math.atan(380 / 250)
    torch.testing.assert_close(vertical_field_of_view(off_centre), torch.tensor([expected]).double())
    torch.testing.assert_close(vertical_field_of_view(fisheye), torch.tensor([480 / 110]).double())
    assert float(vertical_field_of_view(fisheye)) > math.pi


def test_vertical_field_of_view_undoes_radial_distortion():
    """SIMPLE_RADIAL: the edge's distorted tangent r_d = (h / 2) / f comes from r with r (1 + k1 r^2) = r_d; numpy's
    polynomial roots give r, the field of view is 2 atan(r)."""
    f, k1, height = 200.0, -0.02, 480
    intrinsics = intrinsics_from_colmap("SIMPLE_RADIAL", [f, 320.0, height / 2, k1], 640, height)
    r_d = (height / 2) / f
    roots = np.roots([k1, 0.0, 1.0, -r_d])
    r = min(root.real for root in roots if abs(root.imag) < 1e-12 and root.real > 0)
    assert r != pytest.approx(r_d, rel=1e-3)  # the distortion matters here
    torch.testing.assert_close(vertical_field_of_view(intrinsics), torch.tensor([2 * math.atan(r)]).double())
