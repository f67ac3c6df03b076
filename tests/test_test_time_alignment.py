"""Test-time alignment of held-out views: rays, frame mapping, and recovery of a perturbed camera."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from torch import nn

from s2camp_ns.core.alignment import Similarity
from s2camp_ns.core.camera import Intrinsics, se3_exp
from s2camp_ns.scripts.ray_alignment import camera_rays
from s2camp_ns.scripts.test_time_alignment import (
    AlignmentConfig,
    HeldOutView,
    align_and_evaluate_views,
    alignment_work,
    frame_similarity,
    map_camera,
)

WIDTH, HEIGHT, FOCAL = 40, 30, 36.0


class AnalyticField(nn.Module):
    """A smooth, view- and position-dependent colour: stands in for a trained radiance field."""

    def __init__(self) -> None:
        super().__init__()
        generator = torch.Generator().manual_seed(3)
        self.directions = nn.Parameter(torch.randn(3, 3, generator=generator) * 3.0)
        self.positions = nn.Parameter(torch.randn(3, 3, generator=generator))
        self.device = torch.device("cpu")
        self.calls = 0

    def forward(self, rays) -> dict[str, torch.Tensor]:
        self.calls += 1
        phase = rays.directions @ self.directions.T + rays.origins @ self.positions.T
        return {"rgb": 0.5 + 0.5 * torch.sin(phase)}


def _intrinsics(focal: float = FOCAL) -> Intrinsics:
    return Intrinsics.create(fx=focal, fy=focal, cx=WIDTH / 2, cy=HEIGHT / 2, width=WIDTH, height=HEIGHT)


def _c2w_gl() -> torch.Tensor:
    angle = 0.3
    rotation = torch.tensor(
        [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]],
        dtype=torch.float64,
    )
    return torch.cat([rotation, torch.tensor([[0.2], [0.1], [1.5]], dtype=torch.float64)], dim=-1)


def _grid() -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(HEIGHT), torch.arange(WIDTH), indexing="ij")
    return torch.stack([xs, ys], dim=-1).reshape(-1, 2).double() + 0.5


def _true_image(field: AnalyticField, c2w: torch.Tensor) -> torch.Tensor:
    """The image [H, W, 3] the field renders through the unperturbed camera ``c2w``."""
    rays = camera_rays(c2w, _intrinsics(), _grid(), torch.zeros(6), torch.zeros(()), "cpu")
    with torch.no_grad():
        return field(rays)["rgb"].reshape(HEIGHT, WIDTH, 3)


def test_rays_at_zero_twist_match_nerfstudio_cameras():
    c2w = _c2w_gl()
    cameras = Cameras(
        camera_to_worlds=c2w.float()[None],
        fx=FOCAL,
        fy=FOCAL,
        cx=WIDTH / 2,
        cy=HEIGHT / 2,
        width=WIDTH,
        height=HEIGHT,
        camera_type=CameraType.PERSPECTIVE,
    )
    expected = cameras.generate_rays(camera_indices=0)
    rays = camera_rays(c2w, _intrinsics(), _grid(), torch.zeros(6), torch.zeros(()), "cpu")
    torch.testing.assert_close(rays.directions, expected.directions.reshape(-1, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(rays.origins, expected.origins.reshape(-1, 3), atol=1e-6, rtol=0)


def test_twist_and_focal_are_differentiable():
    twist = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    log_focal = torch.zeros((), dtype=torch.float64, requires_grad=True)
    rays = camera_rays(_c2w_gl(), _intrinsics(), _grid()[:50], twist, log_focal, "cpu")
    (rays.directions.sum() + rays.origins.sum()).backward()
    assert twist.grad is not None and bool(twist.grad[3:].abs().sum() > 0) and bool(twist.grad[:3].abs().sum() > 0)
    assert log_focal.grad is not None and float(log_focal.grad.abs()) > 0


def test_frame_similarity_maps_reference_cameras_onto_refined_ones():
    generator = torch.Generator().manual_seed(0)
    reference = torch.cat(
        [se3_exp(0.5 * torch.randn(6, 6, generator=generator, dtype=torch.float64))[:, :, :3],
         torch.randn(6, 3, 1, generator=generator, dtype=torch.float64)],
        dim=-1,
    )  # fmt: skip
    rotation = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.3, -0.2, 0.1], dtype=torch.float64))[:, :3]
    truth = Similarity(1.7, rotation, torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64))
    refined = torch.stack([map_camera(truth, c2w) for c2w in reference])
    torch.testing.assert_close(refined[:, :, 3], 1.7 * reference[:, :, 3] @ rotation.T + truth.translation)
    estimated = frame_similarity(reference, refined)
    assert estimated.scale == pytest.approx(1.7, rel=1e-10)
    for c2w, expected in zip(reference, refined, strict=True):
        torch.testing.assert_close(map_camera(estimated, c2w), expected, atol=1e-10, rtol=0)


def test_alignment_recovers_a_perturbed_camera_and_leaves_the_field_alone():
    field = AnalyticField()
    truth = _c2w_gl()
    image = _true_image(field, truth)
    perturbation = se3_exp(torch.tensor([0.02, -0.01, 0.015, 0.01, -0.015, 0.01], dtype=torch.float64))
    start = torch.cat([truth[:, :3] @ perturbation[:, :3], truth[:, 3:] + truth[:, :3] @ perturbation[:, 3:]], -1)
    before = [p.detach().clone() for p in field.parameters()]
    view = align_and_evaluate_views(
        field, [HeldOutView(image, start, _intrinsics(FOCAL * 1.02), 0)], AlignmentConfig(steps=150, rays=256, lr=3e-3)
    )[0]
    assert view.psnr > view.psnr_unaligned + 8.0, (view.psnr_unaligned, view.psnr)
    assert view.psnr > 35.0 and 0.9 < view.ssim <= 1.0 and math.isnan(view.lpips)
    assert all(torch.equal(a, b) for a, b in zip(before, field.parameters(), strict=True))
    assert all(p.requires_grad for p in field.parameters()) and field.training


def test_views_aligned_together_follow_the_same_steps_as_alone():
    field = AnalyticField()
    truth = _c2w_gl()
    image = _true_image(field, truth)
    twists = ([0.02, -0.01, 0.015, 0.01, -0.015, 0.01], [-0.01, 0.02, 0.0, -0.02, 0.01, 0.005])
    views = [
        HeldOutView(
            image,
            truth @ torch.block_diag(se3_exp(torch.tensor(t, dtype=torch.float64))[:, :3], torch.ones(1, 1)),
            _intrinsics(),
            index,
        )
        for index, t in enumerate(twists)
    ]
    config = AlignmentConfig(steps=20, rays=64, lr=3e-3)
    alone = [align_and_evaluate_views(field, [view], config)[0] for view in views]
    calls = field.calls
    together = align_and_evaluate_views(field, views, config)
    assert field.calls - calls == 20 + 2 * 2  # one forward per step for both views, plus the full renders
    for a, b in zip(alone, together, strict=True):
        assert a.index == b.index and a.psnr_unaligned == pytest.approx(b.psnr_unaligned, abs=1e-9)
        assert a.psnr == pytest.approx(b.psnr, abs=1e-6) and a.final_loss == pytest.approx(b.final_loss, rel=1e-6)
    assert together[0].psnr != pytest.approx(together[1].psnr, abs=1e-3)
    calls = field.calls
    one_at_a_time = align_and_evaluate_views(field, views, dataclasses.replace(config, views_per_batch=1))
    assert field.calls - calls == 2 * (20 + 2)  # views_per_batch bounds each forward pass to one view
    assert [v.psnr for v in one_at_a_time] == pytest.approx([v.psnr for v in together], abs=1e-6)


@pytest.mark.parametrize(("views_per_batch", "steps"), [(8, 20), (1, 20), (2, 0)])
def test_progress_counts_every_render_and_step_up_to_the_announced_total(views_per_batch: int, steps: int):
    """What s2camp-eval's bar shows: one unit per full render (before and after, each view) and per step of a batch,
    told in order and ending at the total announced from the start."""
    field = AnalyticField()
    truth = _c2w_gl()
    image = _true_image(field, truth)
    views = [HeldOutView(image, truth, _intrinsics(), index) for index in range(3)]
    config = AlignmentConfig(steps=steps, rays=32, views_per_batch=views_per_batch)
    told: list[tuple[int, int]] = []
    done_views: list = []
    results = align_and_evaluate_views(
        field, views, config, lambda done, total: told.append((done, total)), done_views.append
    )
    assert done_views == results and [view.index for view in done_views] == [0, 1, 2]  # s2camp-eval's line per view
    batches = -(-3 // views_per_batch)
    total = 2 * 3 + batches * steps
    assert alignment_work(3, config) == total
    assert told == [(done, total) for done in range(1, total + 1)]


def test_zero_steps_evaluates_the_mapped_camera_as_is():
    field = AnalyticField()
    image = _true_image(field, _c2w_gl())
    views = [HeldOutView(image, _c2w_gl(), _intrinsics(), 0)]
    view = align_and_evaluate_views(field, views, AlignmentConfig(steps=0))[0]
    assert view.psnr == view.psnr_unaligned and view.psnr > 60.0


@pytest.mark.parametrize(("name", "value"), [("steps", -1), ("rays", 0), ("lr", 0.0), ("lr_final", math.nan)])
def test_bad_alignment_settings_name_the_parameter(name: str, value: float):
    with pytest.raises(ValueError, match=name):
        AlignmentConfig(**{name: value}).validate()


def _cameras(centres: torch.Tensor, focal: float) -> Cameras:
    c2w = torch.eye(3).expand(len(centres), 3, 3)
    return Cameras(
        camera_to_worlds=torch.cat([c2w, centres.float()[:, :, None]], dim=-1),
        fx=focal, fy=focal, cx=WIDTH / 2, cy=HEIGHT / 2, width=WIDTH, height=HEIGHT,
        camera_type=CameraType.PERSPECTIVE,
    )  # fmt: skip


class _EvalDataset:
    def __init__(self, cameras: Cameras, metadata: dict) -> None:
        self.cameras, self.metadata = cameras, metadata

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, index: int) -> dict:
        return {"image": torch.zeros(HEIGHT, WIDTH, 3)}


@pytest.mark.parametrize("with_reference", [True, False])
def test_held_out_cameras_are_the_evaluation_reference_when_given(monkeypatch, with_reference: bool):
    """With the dataparser's evaluation-split reference (e.g. the true cameras of --reference-model) the held-out
    views start from it, not from the evaluation cameras as given (there: SfM's)."""
    from types import SimpleNamespace

    import s2camp_ns.scripts.test_time_alignment as module

    train = _cameras(torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), FOCAL)
    refined = (train.camera_to_worlds.double(), train.fx.reshape(-1).double())  # identity frame map
    model = SimpleNamespace(
        refined_train_cameras=lambda: refined, reference_cameras=lambda: train, _train_cameras=train
    )
    given = _cameras(torch.tensor([[0.5, 0.5, 0.5], [0.2, 0.3, 0.4]]), FOCAL)
    reference = _cameras(torch.tensor([[0.6, 0.4, 0.5], [0.1, 0.3, 0.5]]), FOCAL + 2.0)
    metadata = {"reference_cameras": reference} if with_reference else {}
    pipeline = SimpleNamespace(model=model, datamanager=SimpleNamespace(eval_dataset=_EvalDataset(given, metadata)))
    monkeypatch.setattr(module, "align_and_evaluate_views", lambda model, views, config, *callbacks: views)
    views = module.evaluate_held_out_views(pipeline, AlignmentConfig())
    expected = reference if with_reference else given
    for index, view in enumerate(views):
        torch.testing.assert_close(view.c2w_gl.float(), expected.camera_to_worlds[index], atol=1e-6, rtol=0)
        assert float(view.intrinsics.fx) == pytest.approx(float(expected.fx[index]))
