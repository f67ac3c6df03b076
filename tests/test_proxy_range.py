"""core.proxy_range: each physical camera's contracted proxy range from the scene's points (small synthetic scenes).

Expected values are computed by hand here (numpy quantiles, the contraction 2 - 1/d written out, the radial law's
inverse CDF written out), never with the module under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.proxy_range import (
    DEFAULT_T_FAR,
    DEFAULT_T_NEAR,
    ProxyRangeConfig,
    clamp_range,
    fit_radial_law,
    proxy_ranges,
    visible_distances,
)

CAMERA = Intrinsics.create(fx=50.0, fy=50.0, cx=50.0, cy=40.0, width=100, height=80)
"""A 100 x 80 pinhole camera: 90 degrees across, tangents |x / z| < 1, |y / z| < 0.8 inside the image."""
IDENTITY = torch.eye(4, dtype=torch.float64)[:3][None]
"""OpenCV camera-to-world of a camera at the origin looking along +z."""
ONE_CAMERA = torch.zeros(1, dtype=torch.long)


def cameras(count: int) -> Intrinsics:
    return Intrinsics.create(fx=torch.full((count,), 50.0), fy=50.0, cx=50.0, cy=40.0, width=100, height=80)


SPAN = ProxyRangeConfig(rule="span")
"""The range is the contracted quartiles: hand-computable."""


def contracted(d: float) -> float:
    """Paper eq. 10, written out."""
    return d if d <= 1.0 else 2.0 - 1.0 / d


def on_axis(distances) -> torch.Tensor:
    d = torch.as_tensor(distances, dtype=torch.float64)
    return torch.stack([torch.zeros_like(d), torch.zeros_like(d), d], dim=-1)


def in_view(distances, seed: int = 0) -> torch.Tensor:
    """Points at the given distances from the origin, in random directions inside CAMERA's image."""
    generator = torch.Generator().manual_seed(seed)
    d = torch.as_tensor(distances, dtype=torch.float64)
    tangents = (torch.rand(d.shape[0], 2, generator=generator, dtype=torch.float64) * 2 - 1) * torch.tensor(
        [0.9, 0.7], dtype=torch.float64
    )
    direction = torch.cat([tangents, torch.ones(d.shape[0], 1, dtype=torch.float64)], dim=-1)
    return direction / direction.norm(dim=-1, keepdim=True) * d[:, None]


DISTANCES = [0.5 + 0.1 * k for k in range(21)]  # 0.5 ... 2.5


def test_span_rule_gives_the_contracted_quartiles() -> None:
    # 21 sorted distances: the 25% quantile is the 6th (index 5 = 1.0), the 75% the 16th (index 15 = 2.0).
    ranges = proxy_ranges(in_view(DISTANCES), IDENTITY, CAMERA, ONE_CAMERA, SPAN)
    torch.testing.assert_close(ranges.t_near, torch.tensor([1.0], dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close(ranges.t_far, torch.tensor([1.5], dtype=torch.float64), rtol=0, atol=1e-12)
    assert ranges.num_points.tolist() == [21] and ranges.fallback.tolist() == [False]
    assert ranges.t_near.dtype == torch.float64


def test_span_rule_interpolates_between_order_statistics() -> None:
    config = ProxyRangeConfig(rule="span", low_quantile=0.05, high_quantile=0.93)
    ranges = proxy_ranges(in_view(DISTANCES, seed=3), IDENTITY, CAMERA, ONE_CAMERA, config)
    low, high = np.percentile(np.asarray(DISTANCES), [5.0, 93.0])  # numpy's linear interpolation
    assert ranges.t_near.item() == pytest.approx(contracted(low), abs=1e-12)
    assert ranges.t_far.item() == pytest.approx(contracted(high), abs=1e-12)


def test_points_behind_the_camera_or_outside_the_image_are_ignored() -> None:
    seen = in_view(DISTANCES)
    behind = -seen[:8] * 3.0  # mirrored through the centre: z < 0
    outside = torch.tensor([[2.0, 0.0, 1.0], [0.0, 1.5, 1.0], [-3.0, 0.1, 0.5], [0.5, 0.9, 1.0]], dtype=torch.float64)
    clean = proxy_ranges(seen, IDENTITY, CAMERA, ONE_CAMERA, SPAN)
    mixed = proxy_ranges(torch.cat([behind, seen[:10], outside, seen[10:]]), IDENTITY, CAMERA, ONE_CAMERA, SPAN)
    assert torch.equal(mixed.t_near, clean.t_near) and torch.equal(mixed.t_far, clean.t_far)
    assert mixed.num_points.tolist() == [21]
    # The distances the camera sees are exactly those of the in-view points, in their order.
    (distances,) = visible_distances(torch.cat([behind, seen, outside]), IDENTITY, CAMERA)
    torch.testing.assert_close(distances, torch.tensor(DISTANCES, dtype=torch.float64), rtol=0, atol=1e-12)


def test_camera_pose_is_applied() -> None:
    """The same scene seen by a camera moved and turned: the distances are measured from its centre."""
    angle = 0.7
    rotation = torch.tensor(
        [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]],
        dtype=torch.float64,
    )
    centre = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
    c2w = torch.cat([rotation, centre[:, None]], dim=-1)[None]
    world = in_view(DISTANCES) @ rotation.T + centre
    ranges = proxy_ranges(world, c2w, CAMERA, ONE_CAMERA, SPAN)
    assert ranges.t_near.item() == pytest.approx(1.0, abs=1e-12)
    assert ranges.t_far.item() == pytest.approx(1.5, abs=1e-12)


def test_images_of_one_physical_camera_are_pooled() -> None:
    """Two images of camera 0 look in opposite directions and see different points: one range from their union;
    a third image (camera 1) sees only the far ones."""
    near_points = in_view([0.5 + 0.05 * k for k in range(30)], seed=1)
    far_points = -in_view([1.5 + 0.1 * k for k in range(30)], seed=2)  # behind camera 0's first image
    flipped = torch.tensor([[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]], dtype=torch.float64)
    c2w = torch.stack([IDENTITY[0], flipped, flipped])
    intrinsics = cameras(3)
    ranges = proxy_ranges(torch.cat([near_points, far_points]), c2w, intrinsics, torch.tensor([0, 0, 1]), SPAN)
    union = [0.5 + 0.05 * k for k in range(30)] + [1.5 + 0.1 * k for k in range(30)]
    low, high = np.percentile(np.asarray(union), [25.0, 75.0])
    far_low, far_high = np.percentile(np.asarray([1.5 + 0.1 * k for k in range(30)]), [25.0, 75.0])
    # Camera 1's quartiles (1.551, 1.728) are closer than the minimum width 0.2: widened about their middle.
    middle = (contracted(far_low) + contracted(far_high)) / 2.0
    torch.testing.assert_close(
        ranges.t_near, torch.tensor([contracted(low), middle - 0.1], dtype=torch.float64), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(
        ranges.t_far, torch.tensor([contracted(high), middle + 0.1], dtype=torch.float64), rtol=0, atol=1e-12
    )
    assert ranges.num_points.tolist() == [60, 30]


def radial_law_distances(t0: float, t1: float, count: int, radial: str) -> np.ndarray:
    """Euclidean distances of the proxy radial law on [t0, t1] at ``count`` evenly spread quantiles: the inverse CDF
    of paper eq. 12 ("volume": cube root) or a uniform contracted radius ("ray"), then d = 1 / (2 - t) beyond 1."""
    u = (np.arange(count) + 0.5) / count
    t = (t0**3 + u * (t1**3 - t0**3)) ** (1.0 / 3.0) if radial == "volume" else t0 + u * (t1 - t0)
    return np.where(t <= 1.0, t, 1.0 / (2.0 - np.minimum(t, 1.999)))


@pytest.mark.parametrize(("t0", "t1", "radial"), [(0.3, 1.2, "volume"), (0.5, 1.7, "ray"), (0.6, 1.5, "volume")])
def test_moment_rule_recovers_the_range_of_points_laid_out_as_the_proxy_law(t0: float, t1: float, radial: str) -> None:
    """Content distributed exactly as the proxy points of (t0, t1): its E[1/d] and E[1/d^2] are those of (t0, t1),
    which lies on the search grid, so the rule returns it."""
    points = on_axis(radial_law_distances(t0, t1, 4000, radial))
    config = ProxyRangeConfig(clip_quantile=0.0)
    ranges = proxy_ranges(points, IDENTITY, CAMERA, ONE_CAMERA, config, radial=radial)
    assert (ranges.t_near.item(), ranges.t_far.item()) == (pytest.approx(t0, abs=1e-12), pytest.approx(t1, abs=1e-12))


def test_moment_rule_ignores_a_few_points_at_the_lens() -> None:
    """1% stray points at d = 0.01 (a mismatched track): clipped at the 2% quantile they barely move the range;
    unclipped, their 1/d^2 = 10^4 drags the range onto the camera."""
    clean = on_axis(radial_law_distances(0.5, 1.5, 4000, "volume"))
    stray = torch.cat([clean, on_axis([0.01] * 40)])
    reference = proxy_ranges(clean, IDENTITY, CAMERA, ONE_CAMERA)
    robust = proxy_ranges(stray, IDENTITY, CAMERA, ONE_CAMERA)
    assert abs(robust.t_near.item() - reference.t_near.item()) <= 0.05
    assert abs(robust.t_far.item() - reference.t_far.item()) <= 0.05
    unclipped = proxy_ranges(stray, IDENTITY, CAMERA, ONE_CAMERA, ProxyRangeConfig(clip_quantile=0.0))
    assert unclipped.t_far.item() < 0.5 < reference.t_near.item()


def test_fit_rule_matches_the_radial_cdf_at_both_quantiles() -> None:
    low, high = torch.tensor(1.2, dtype=torch.float64), torch.tensor(1.5, dtype=torch.float64)
    t0, t1 = fit_radial_law(low, high, 0.25, 0.75, "volume")
    cdf = lambda t: (t**3 - t0**3) / (t1**3 - t0**3)  # noqa: E731  (paper eq. 11)
    assert float(cdf(low)) == pytest.approx(0.25, abs=1e-12) and float(cdf(high)) == pytest.approx(0.75, abs=1e-12)
    assert 0.0 < float(t0) < 1.2 and float(t1) > 1.5
    # "ray": uniform in t, so t0 = 1.2 - 0.25 * 0.6 and t1 = 1.2 + 0.75 * 0.6.
    t0, t1 = fit_radial_law(low, high, 0.25, 0.75, "ray")
    assert float(t0) == pytest.approx(1.05, abs=1e-12) and float(t1) == pytest.approx(1.65, abs=1e-12)
    # Content spread towards the camera: the fitted t0^3 = 0.8^3 - 0.25 (1.4^3 - 0.8^3) / 0.5 < 0 becomes t0 = 0.
    t0, t1 = fit_radial_law(torch.tensor(0.8), torch.tensor(1.4), 0.25, 0.75, "volume")
    assert float(t0) == 0.0 and float(t1) == pytest.approx((0.8**3 + 0.75 * (1.4**3 - 0.8**3) / 0.5) ** (1 / 3))


def test_no_points_or_too_few_fall_back_to_the_fixed_range() -> None:
    for points in (None, torch.zeros(0, 3, dtype=torch.float64)):
        ranges = proxy_ranges(points, IDENTITY, CAMERA, ONE_CAMERA)
        assert (ranges.t_near.item(), ranges.t_far.item()) == (DEFAULT_T_NEAR, DEFAULT_T_FAR) == (0.4, 1.5)
        assert ranges.fallback.tolist() == [True] and ranges.num_points.tolist() == [0]
    # Camera 0 sees 19 points (< min_points 20), camera 1 all 21: only camera 0 falls back.
    flipped = torch.tensor([[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]], dtype=torch.float64)
    intrinsics = cameras(2)
    points = torch.cat([in_view(DISTANCES[:19]), -in_view(DISTANCES)])
    ranges = proxy_ranges(points, torch.stack([IDENTITY[0], flipped]), intrinsics, torch.tensor([0, 1]), SPAN)
    assert ranges.fallback.tolist() == [True, False] and ranges.num_points.tolist() == [19, 21]
    assert (ranges.t_near[0].item(), ranges.t_far[0].item()) == (0.4, 1.5)
    assert ranges.t_near[1].item() == pytest.approx(1.0, abs=1e-12)


def test_explicit_ends_override_the_chosen_ones() -> None:
    points = in_view(DISTANCES)
    only_far = proxy_ranges(points, IDENTITY, CAMERA, ONE_CAMERA, SPAN, t_far=1.8)
    assert only_far.t_far.item() == 1.8 and only_far.t_near.item() == pytest.approx(1.0, abs=1e-12)
    only_near = proxy_ranges(points, IDENTITY, CAMERA, ONE_CAMERA, SPAN, t_near=0.2)
    assert only_near.t_near.item() == 0.2 and only_near.t_far.item() == pytest.approx(1.5, abs=1e-12)
    # The chosen end yields so that the range keeps its minimum width of 0.2.
    squeezed = proxy_ranges(points, IDENTITY, CAMERA, ONE_CAMERA, SPAN, t_far=1.1)
    assert squeezed.t_near.item() == pytest.approx(0.9, abs=1e-12) and squeezed.t_far.item() == 1.1
    both = proxy_ranges(points, IDENTITY, CAMERA, ONE_CAMERA, SPAN, t_near=0.05, t_far=1.95)
    assert (both.t_near.item(), both.t_far.item()) == (0.05, 1.95)
    # Without points an explicit end is kept too.
    assert proxy_ranges(None, IDENTITY, CAMERA, ONE_CAMERA, t_far=1.8).t_far.item() == 1.8


def test_clamping_keeps_the_range_valid() -> None:
    config = ProxyRangeConfig()
    near, far = clamp_range(
        torch.tensor([0.05, 1.95, 0.7, 0.0], dtype=torch.float64),
        torch.tensor([0.1, 1.999, 0.75, 1.9999], dtype=torch.float64),
        config,
    )
    # (0.05, 0.1): near raised to 0.1, width 0 grown to 0.2 about 0.1, shifted up -> (0.1, 0.3).
    # (1.95, 1.999): far cut to 1.99, width 0.04 grown to 0.2, shifted down -> (1.79, 1.99).
    # (0.7, 0.75): grown about the middle -> (0.625, 0.825). (0, 1.9999): clamped to (0.1, 1.99).
    torch.testing.assert_close(near, torch.tensor([0.1, 1.79, 0.625, 0.1], dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close(far, torch.tensor([0.3, 1.99, 0.825, 1.99], dtype=torch.float64), rtol=0, atol=1e-12)


def test_same_input_same_bits() -> None:
    points = in_view([0.3 + 0.013 * k for k in range(500)], seed=9)
    first = proxy_ranges(points, IDENTITY, CAMERA, ONE_CAMERA)
    second = proxy_ranges(points.clone(), IDENTITY.clone(), CAMERA, ONE_CAMERA)
    assert torch.equal(first.stacked(), second.stacked())


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"config": ProxyRangeConfig(rule="median")}, "^rule must be one of"),  # type: ignore[arg-type]
        ({"config": ProxyRangeConfig(low_quantile=0.8, high_quantile=0.8)}, r"^high_quantile must lie in \(0.8, 1\]"),
        ({"config": ProxyRangeConfig(clip_quantile=0.5)}, r"^clip_quantile must lie in \[0, 0.5\)"),
        ({"config": ProxyRangeConfig(min_points=0)}, r"^min_points must be an integer in \[1, inf\)"),
        ({"t_near": 1.9}, r"^t_near must lie in \[0, 1.79\]"),
        ({"t_near": 0.5, "t_far": 0.5}, r"^t_far must lie in \(0.5, 2\)"),
        ({"points": torch.zeros(4, 2)}, r"^points must have shape \[M, 3\]"),
        ({"points": torch.full((4, 3), float("nan"))}, "^points must be finite"),
        ({"camera_of_image": torch.tensor([0, 1])}, "^camera_of_image must hold 1 ids"),
    ],
)
def test_bad_input_is_named(kwargs: dict, message: str) -> None:
    arguments = {"points": in_view(DISTANCES), "camera_of_image": ONE_CAMERA, **kwargs}
    with pytest.raises(ValueError, match=message):
        proxy_ranges(arguments.pop("points"), IDENTITY, CAMERA, arguments.pop("camera_of_image"), **arguments)


# ------------------------------------------------------------------------------------- through the pipeline


def _visible_distances_by_hand(scene, names: list[str]) -> np.ndarray:
    """Distances (in the scene's own units) of the scene's sparse points from the centres of the images ``names``
    that see them: in front and inside the image by pycolmap's own projection (distortion included)."""
    import json

    import pycolmap

    reconstruction = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    xyz = np.stack([point.xyz for point in reconstruction.points3D.values()])
    info = json.loads((scene / "scene_info.json").read_text())
    camera = reconstruction.cameras[1]
    out = []
    for image in info["images"]:
        if image["name"] not in names:
            continue
        pose = np.asarray(image["cam_from_world"])
        in_camera = xyz @ pose[:, :3].T + pose[:, 3]
        front = in_camera[:, 2] > 0
        pixels = np.asarray(camera.img_from_cam(in_camera[front]))
        inside = (pixels[:, 0] >= 0) & (pixels[:, 0] <= camera.width) & (pixels[:, 1] >= 0)
        inside &= pixels[:, 1] <= camera.height
        out.append(np.linalg.norm(in_camera[front][inside], axis=1))
    return np.concatenate(out)


def _tiny_pipeline(scene, sampling):
    from conftest import lpips_offline, tiny_model_config

    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
    from s2camp_ns.data.dataparser import S2CampDataParserConfig
    from s2camp_ns.method.datamanager import S2CampDataManagerConfig
    from s2camp_ns.method.pipeline import S2CampPipelineConfig

    model = tiny_model_config(S2CampCameraOptimizerConfig(sampling=sampling))
    config = S2CampPipelineConfig(
        datamanager=S2CampDataManagerConfig(
            dataparser=S2CampDataParserConfig(data=scene), train_num_rays_per_batch=64, eval_num_rays_per_batch=64
        ),
        model=model,
    )
    with lpips_offline():
        return config.setup(device="cpu", test_mode="val")


def test_pipeline_gives_the_optimizer_the_scenes_points(tiny_scene) -> None:
    """ns-train's path: data parser (normalized world), pipeline, model, camera optimizer. With the "span" rule the
    chosen range is the contracted quartiles of what the training images see, computed here from the scene's own
    COLMAP model and pycolmap's projection, scaled by the data parser's normalization."""
    from s2camp_ns.core.preconditioner import SamplingConfig

    pipeline = _tiny_pipeline(tiny_scene, SamplingConfig(num_points=64, auto_range=SPAN))
    optimizer = pipeline.model.camera_optimizer
    outputs = pipeline.datamanager.train_dataparser_outputs
    names = [path.name for path in outputs.image_filenames]
    distances = _visible_distances_by_hand(tiny_scene, names) * float(outputs.dataparser_scale)
    low, high = (contracted(d) for d in np.percentile(distances, [25.0, 75.0]))
    assert optimizer.refiner.num_physical_cameras == 1 and optimizer.refiner.proxy_ranges.num_points.tolist() == [
        len(distances)
    ]
    expected = torch.tensor([[low, high]], dtype=torch.float64).expand(len(names), 2)
    # nerfstudio hands over float32 points and cameras: agreement to float32 rounding, not to the last bit.
    torch.testing.assert_close(optimizer.refiner.proxy_range, expected, rtol=0, atol=1e-6)
    assert torch.equal(optimizer.refiner.precond_proxy_range, optimizer.refiner.proxy_range)


def test_pipeline_default_range_comes_from_the_scene_and_an_explicit_one_wins(tiny_scene) -> None:
    from s2camp_ns.core.preconditioner import SamplingConfig

    chosen = _tiny_pipeline(tiny_scene, SamplingConfig(num_points=64)).model.camera_optimizer
    near, far = chosen.refiner.proxy_range[0].tolist()
    assert not chosen.refiner.proxy_ranges.fallback.any() and (near, far) != (0.4, 1.5)
    assert bool((chosen.refiner.proxy_range == chosen.refiner.proxy_range[0]).all())  # one physical camera: one range
    # Both ends on the 0.01 grid of the moment rule.
    assert round(near * 100) == pytest.approx(near * 100, abs=1e-9) and round(far * 100) == pytest.approx(far * 100)
    fixed = _tiny_pipeline(tiny_scene, SamplingConfig(num_points=64, t_far=1.8)).model.camera_optimizer
    assert fixed.refiner.proxy_range[:, 1].tolist() == [1.8] * fixed.num_cameras


def test_large_scenes_are_thinned_deterministically() -> None:
    """max_points keeps every k-th point (k = ceil(M / max_points)); max_images keeps evenly spread images."""
    config = ProxyRangeConfig(rule="span", max_points=7, min_points=1)
    ranges = proxy_ranges(in_view(DISTANCES), IDENTITY, CAMERA, ONE_CAMERA, config)
    kept = np.asarray(DISTANCES[::3])  # 21 points, k = 3: 7 kept
    low, high = np.percentile(kept, [25.0, 75.0])
    assert ranges.num_points.tolist() == [7]
    assert (ranges.t_near.item(), ranges.t_far.item()) == (
        pytest.approx(contracted(low), abs=1e-12),
        pytest.approx(contracted(high), abs=1e-12),
    )
    # Three images of one camera, max_images 2: images 0 and 1 (k * 3 // 2 for k = 0, 1); image 2 looks the other
    # way at points nobody else sees, and is left out.
    flipped = torch.tensor([[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]], dtype=torch.float64)
    c2w = torch.stack([IDENTITY[0], IDENTITY[0], flipped])
    points = torch.cat([in_view(DISTANCES), -in_view([5.0] * 30)])
    config = ProxyRangeConfig(rule="span", max_images=2)
    thinned = proxy_ranges(points, c2w, cameras(3), torch.zeros(3, dtype=torch.long), config)
    assert thinned.num_points.tolist() == [42]
    assert thinned.t_near.item() == pytest.approx(1.0, abs=1e-12) and thinned.t_far.item() == pytest.approx(1.5)
