"""``s2camp_bench.evaluation``: a trained pipeline's camera errors, drift and held-out metrics, on a model that
only has the camera interface the evaluation reads (no training; the held-out views stubbed)."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from s2camp_bench import evaluation
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

F64 = torch.float64


def _look_at_origin(centre: torch.Tensor) -> torch.Tensor:
    """OpenGL c2w [3, 4] at ``centre`` looking at the origin, +z up."""
    back = centre / centre.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=F64), back)
    right = right / right.norm()
    up = torch.linalg.cross(back, right)
    return torch.cat([torch.stack([right, up, back], dim=1), centre[:, None]], dim=1)


def _ring(count: int = 6) -> Cameras:
    angles = torch.arange(count, dtype=F64) * (2 * math.pi / count)
    centres = torch.stack([4 * angles.cos(), 4 * angles.sin(), torch.full_like(angles, 0.5)], dim=1)
    c2w = torch.stack([_look_at_origin(centre) for centre in centres]).float()
    return Cameras(
        camera_to_worlds=c2w, fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48,
        camera_type=CameraType.PERSPECTIVE,
    )  # fmt: skip


def _yawed(c2w: torch.Tensor, index: int, degrees: float) -> torch.Tensor:
    """``c2w`` with camera ``index`` turned by ``degrees`` about its own y axis."""
    angle = math.radians(degrees)
    turn = torch.tensor(
        [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]], dtype=F64
    )
    moved = c2w.to(F64).clone()
    moved[index, :, :3] = moved[index, :, :3] @ turn
    return moved


def _pipeline(model) -> SimpleNamespace:
    points = (torch.rand(60, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1).to(F64)
    outputs = SimpleNamespace(metadata={"points3D_xyz": points})
    return SimpleNamespace(model=model, datamanager=SimpleNamespace(train_dataparser_outputs=outputs))


@pytest.fixture
def held_out(monkeypatch: pytest.MonkeyPatch) -> list[AlignmentConfig]:
    """Two held-out views of known PSNR / SSIM; the alignment config each call got."""
    calls: list[AlignmentConfig] = []

    def views(pipeline, config: AlignmentConfig) -> list[SimpleNamespace]:
        calls.append(config)
        return [
            SimpleNamespace(psnr=20.0, ssim=0.5, psnr_unaligned=19.0),
            SimpleNamespace(psnr=22.0, ssim=0.7, psnr_unaligned=21.0),
        ]

    monkeypatch.setattr(evaluation, "evaluate_held_out_views", views)
    return calls


def test_stock_pose_refinement_is_measured_against_the_given_cameras(held_out: list[AlignmentConfig]) -> None:
    """No reference cameras: the training cameras as given are the truth, so the start has no error; one camera
    turned by the pose optimizer gives a rotation error and drift, and the focal lengths stay the given ones."""
    cameras = _ring()
    refined = _yawed(cameras.camera_to_worlds, 2, 1.0)
    model = SimpleNamespace(
        _train_cameras=cameras, reference_cameras=lambda: None, uses_s2camp_optimizer=False,
        refined_train_cameras=lambda: (refined, cameras.fx.reshape(-1).to(F64)),
    )  # fmt: skip
    alignment = AlignmentConfig(steps=3)
    result = evaluation.evaluate_pipeline(_pipeline(model), alignment)
    assert held_out == [alignment]
    for key in ("rot_err", "pos_err", "focal_err", "drift_px"):
        assert result[f"start_{key}"] == pytest.approx(0.0, abs=1e-5), key
    assert 0.01 < result["rot_err"] < 1.0 and result["drift_px"] > 0.01
    assert result["focal_err"] == 0.0 and result["drift_behind"] == 0
    assert (result["psnr"], result["ssim"], result["psnr_unaligned"]) == pytest.approx((21.0, 0.6, 20.0))
    assert result["eval_views"] == 2 and result["eval_seconds"] >= 0.0


def test_s2camp_refinement_is_measured_against_the_reference_cameras(held_out: list[AlignmentConfig]) -> None:
    """With reference cameras the start is measured against them, and S2CamP's refined intrinsics are read."""
    reference = _ring()
    given = _ring()
    given.camera_to_worlds = _yawed(reference.camera_to_worlds, 0, 2.0).float()
    refined_intrinsics = intrinsics_from_cameras(reference)
    refined_intrinsics = dataclasses.replace(refined_intrinsics, fx=refined_intrinsics.fx * 1.02)
    refiner = SimpleNamespace(
        refined_c2w=lambda opengl: reference.camera_to_worlds.to(F64), refined_intrinsics=lambda: refined_intrinsics
    )
    optimizer = SimpleNamespace(refiner=refiner)
    model = SimpleNamespace(
        _train_cameras=given, reference_cameras=lambda: reference, uses_s2camp_optimizer=True,
        camera_optimizer=optimizer,
    )  # fmt: skip
    result = evaluation.evaluate_pipeline(_pipeline(model), AlignmentConfig())
    assert result["start_rot_err"] > 0.1 and result["start_drift_px"] > 0.01 and result["start_focal_err"] == 0.0
    assert result["rot_err"] == pytest.approx(0.0, abs=1e-4) and result["pos_err"] == pytest.approx(0.0, abs=1e-5)
    assert result["focal_err"] == pytest.approx(1.0, rel=1e-6)  # 2% of 50 px on every camera
