"""Similarity alignment and camera error metrics."""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_ns.core.alignment import Similarity, camera_errors, rotation_angle, umeyama
from s2camp_ns.core.camera import se3_exp


def random_poses(n: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, dtype=torch.float64, generator=generator)
    return se3_exp(xi)


def known_similarity() -> Similarity:
    rotation = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.3, -1.2, 2.0], dtype=torch.float64))[:, :3]
    return Similarity(2.7, rotation, torch.tensor([1.0, -4.0, 0.5], dtype=torch.float64))


def test_umeyama_recovers_known_similarity():
    points = torch.randn(20, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    truth = known_similarity()
    fit = umeyama(points, truth.apply_to_points(points))
    assert abs(fit.scale - truth.scale) < 1e-10
    torch.testing.assert_close(fit.rotation, truth.rotation, atol=1e-10, rtol=0)
    torch.testing.assert_close(fit.translation, truth.translation, atol=1e-10, rtol=0)


def test_camera_errors_vanish_after_alignment_of_a_similar_copy():
    ref = random_poses(12)
    est = known_similarity().apply_to_poses(ref)  # the same cameras in another gauge
    f = torch.full((12,), 400.0, dtype=torch.float64)
    errors = camera_errors(est, ref, f, f)
    for key in ("rot_err_mean", "rot_err_max", "pos_err_mean", "pos_err_max", "focal_err_max"):
        assert errors[key] < 1e-10, (key, errors[key])
    assert errors["raw_pos_err_max"] > 1.0 and errors["raw_rot_err_max"] > 0.1
    assert errors["aligned"] == 1.0
    assert abs(errors["align_scale"] - 1 / 2.7) < 1e-10


def test_camera_errors_report_known_errors():
    ref = random_poses(10, seed=2)
    est = ref.clone()
    # Rotate one camera about its own centre by 0.05 rad: centres unchanged, so the alignment is the identity.
    est[3, :, :3] = est[3, :, :3] @ se3_exp(torch.tensor([0, 0, 0, 0.05, 0, 0], dtype=torch.float64))[:, :3]
    est_f = torch.full((10,), 100.0, dtype=torch.float64)
    ref_f = est_f.clone()
    ref_f[5] = 103.0
    errors = camera_errors(est, ref, est_f, ref_f)
    assert abs(errors["rot_err_max"] - 0.05) < 1e-10
    assert abs(errors["rot_err_mean"] - 0.005) < 1e-10
    assert errors["pos_err_max"] < 1e-10
    assert abs(errors["focal_err_max"] - 3.0) < 1e-12 and abs(errors["focal_err_mean"] - 0.3) < 1e-12
    # A shifted centre: raw error is exact.
    est2 = ref.clone()
    est2[0, 0, 3] += 0.25
    raw = camera_errors(est2, ref, align=False)
    assert abs(raw["pos_err_max"] - 0.25) < 1e-12 and raw["aligned"] == 0.0


def test_rotation_angle_small_and_near_pi():
    for angle in (1e-9, 1e-4, 1.0, math.pi - 1e-6):
        r = se3_exp(torch.tensor([[0, 0, 0, 0, angle, 0]], dtype=torch.float64))[:, :, :3]
        got = float(rotation_angle(torch.eye(3, dtype=torch.float64)[None], r)[0])
        assert abs(got - angle) < 1e-9 * max(1.0, angle) + 1e-15


def test_few_cameras_fall_back_to_unaligned():
    ref = random_poses(2)
    est = ref.clone()
    est[:, 0, 3] += 0.1
    with pytest.warns(UserWarning, match="cannot fix a similarity"):
        errors = camera_errors(est, ref)
    assert errors["aligned"] == 0.0
    assert abs(errors["pos_err_max"] - 0.1) < 1e-12 and errors["pos_err_max"] == errors["raw_pos_err_max"]


def test_coincident_centres_fall_back():
    ref = random_poses(4)
    ref[:, :, 3] = 0.0
    with pytest.warns(UserWarning, match="alignment skipped"):
        errors = camera_errors(ref.clone(), ref)
    assert errors["aligned"] == 0.0 and errors["rot_err_max"] < 1e-12


def test_bad_inputs():
    ref = random_poses(4)
    with pytest.raises(ValueError, match="shape"):
        camera_errors(ref[:3], ref)
    with pytest.raises(ValueError, match="both est_fx and ref_fx"):
        camera_errors(ref, ref, est_fx=torch.ones(4))
    bad = ref.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="est_c2w must be finite"):
        camera_errors(bad, ref)
