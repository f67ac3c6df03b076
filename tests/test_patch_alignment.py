"""Least-squares matching of patches (``s2camp_ns.tracks.patch_alignment``) on synthetic windows whose warp is known.

The texture is a sum of sinusoids, evaluated exactly at every pixel centre of both windows: the reference window
samples it at reference offsets, the target window at the offsets a known affine map A, shift t, gain and offset
send them to. The alignment must return t to a few hundredths of a pixel and A to a few thousandths.
"""

from __future__ import annotations

import math

import pytest
import torch

from s2camp_ns.tracks import patch_alignment
from s2camp_ns.tracks.patch_alignment import align_patches, halved, template_offsets

F64 = torch.float64
SIZE = 32


def texture(points: torch.Tensor, seed: int) -> torch.Tensor:
    """A smooth random texture at continuous points [..., 2] (periods of about 10 to 40 px)."""
    generator = torch.Generator().manual_seed(seed)
    frequencies = torch.randn(24, 2, generator=generator, dtype=F64) * 0.3
    phases = torch.rand(24, generator=generator, dtype=F64) * 2.0 * math.pi
    amplitudes = torch.rand(24, generator=generator, dtype=F64)
    return (amplitudes * torch.sin(points @ frequencies.T + phases)).sum(-1)


def pixel_centres() -> torch.Tensor:
    """Window coordinates [S, S, 2] (x, y) of every pixel centre, less the window's centre."""
    steps = torch.arange(SIZE, dtype=F64) + 0.5 - SIZE / 2
    return torch.stack(torch.meshgrid(steps, steps, indexing="xy"), dim=-1)


def warped_pair(affine: torch.Tensor, shift: torch.Tensor, seed: int, gain: float = 1.3, offset: float = 0.2):
    """Reference and target windows of one texture: target(c + A x + t) = gain * reference(c + x) + offset."""
    offsets = pixel_centres()
    reference = texture(offsets, seed)
    target = gain * texture((offsets - shift) @ torch.linalg.inv(affine).T, seed) + offset
    return reference, target


def rotation_scale_shear(angle: float, scale: float, shear: float) -> torch.Tensor:
    rotation = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]], dtype=F64)
    return scale * rotation @ torch.tensor([[1.0, shear], [0.0, 1.0]], dtype=F64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_known_sub_pixel_shift_and_affine_warp_are_recovered(dtype: torch.dtype) -> None:
    generator = torch.Generator().manual_seed(1)
    affines, shifts, references, targets = [], [], [], []
    for seed in range(32):
        angle, scale, shear = (torch.rand(3, generator=generator, dtype=F64) - 0.5).tolist()
        affine = rotation_scale_shear(0.5 * angle, 1.0 + 0.25 * scale, 0.2 * shear)
        shift = (torch.rand(2, generator=generator, dtype=F64) - 0.5) * 3.0  # up to 1.5 px each way
        reference, target = warped_pair(affine, shift, seed)
        affines.append(affine), shifts.append(shift), references.append(reference), targets.append(target)
    result = align_patches(
        torch.stack(references).to(dtype), torch.stack(targets).to(dtype), torch.eye(2, dtype=dtype).expand(32, 2, 2)
    )
    assert bool(result.converged.all())
    errors = (result.shift.double() - torch.stack(shifts)).norm(dim=-1)
    assert float(errors.median()) < 0.02 and float(errors.max()) < 0.06, errors
    assert float((result.affine.double() - torch.stack(affines)).abs().max()) < 0.02
    torch.testing.assert_close(result.gain.double(), torch.full((32,), 1 / 1.3, dtype=F64), rtol=0.05, atol=0)
    assert float(result.correlation.min()) > 0.99


def test_a_shift_beyond_the_finest_basin_is_found_coarse_to_fine() -> None:
    """A 3 px shift with an unknown 20% scale change: found with two levels, not with the finest alone."""
    affine = rotation_scale_shear(0.1, 1.2, 0.0)
    pairs = [warped_pair(affine, torch.tensor([3.0, -2.5], dtype=F64), seed) for seed in range(8)]
    reference, target = (torch.stack(windows) for windows in zip(*pairs, strict=True))
    start = torch.eye(2, dtype=F64).expand(8, 2, 2)
    coarse = align_patches(reference, target, start, levels=2)
    errors = (coarse.shift - torch.tensor([3.0, -2.5], dtype=F64)).norm(dim=-1)
    assert bool(coarse.converged.all()) and float(errors.max()) < 0.05
    fine = align_patches(reference, target, start, levels=1)
    assert not bool(((fine.shift - torch.tensor([3.0, -2.5], dtype=F64)).norm(dim=-1) < 0.05).all())


def occluded_pairs() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Four windows shifted by (0.4, -0.3) px, a quarter of each target replaced by another texture (an occluder
    covering a quarter of the template at both levels)."""
    shift = torch.tensor([0.4, -0.3], dtype=F64)
    pairs = [warped_pair(torch.eye(2, dtype=F64), shift, seed) for seed in (5, 6, 7, 8)]
    reference, target = (torch.stack(windows) for windows in zip(*pairs, strict=True))
    target[:, : SIZE // 2, SIZE // 2 :] = texture(pixel_centres()[: SIZE // 2, SIZE // 2 :] * 1.7, seed=99)
    return reference, target, shift


def test_an_occluded_part_of_the_patch_is_outweighed(monkeypatch: pytest.MonkeyPatch) -> None:
    """The robust loss finds the shift behind an occluder; plain least squares (unit weights) is pulled off by more
    than half a pixel."""
    reference, target, shift = occluded_pairs()
    start = torch.eye(2, dtype=F64).expand(4, 2, 2)
    errors = (align_patches(reference, target, start).shift - shift).norm(dim=-1)
    assert float(errors.max()) < 0.08 and float(errors.median()) < 0.04, errors
    monkeypatch.setattr(patch_alignment, "_cauchy_weights", torch.ones_like)
    plain = (align_patches(reference, target, start).shift - shift).norm(dim=-1)
    assert float(plain.median()) > 0.5, plain


def test_unrelated_windows_do_not_align_with_a_high_correlation() -> None:
    """Target windows of another texture: the alignment does not claim a match (it does not converge, or the aligned
    patches do not correlate); the caller then keeps the detected keypoint."""
    same = torch.eye(2, dtype=F64), torch.zeros(2, dtype=F64)
    references = torch.stack([warped_pair(*same, seed)[0] for seed in range(16)])
    targets = torch.stack([texture(pixel_centres(), 1000 + seed) for seed in range(16)])
    result = align_patches(references, targets, torch.eye(2, dtype=F64).expand(16, 2, 2))
    claimed = result.converged & (result.correlation >= 0.8) & (result.shift.norm(dim=-1) <= 2.0)
    assert int(claimed.sum()) == 0


def test_halving_maps_continuous_coordinates_by_one_half() -> None:
    """A linear ramp in x: the halved window's value at its pixel centre u equals the ramp at 2 u (blur and means of a
    linear function are the function), away from the replicated edges."""
    ramp = (torch.arange(SIZE, dtype=F64) + 0.5).expand(1, SIZE, SIZE)
    coarse = halved(ramp)
    centres = torch.arange(SIZE // 2, dtype=F64) + 0.5
    torch.testing.assert_close(coarse[0, 4, 1:-1], 2.0 * centres[1:-1], rtol=0, atol=1e-12)
    assert template_offsets(2, F64, torch.device("cpu")).shape == (25, 2)


def test_windows_that_cannot_hold_the_template_are_refused() -> None:
    window = torch.zeros(1, 16, 16)
    with pytest.raises(ValueError, match="cannot hold a template of radius 7 at 2 levels"):
        align_patches(window, window, torch.eye(2)[None], radius=7, levels=2)
    with pytest.raises(ValueError, match="square windows of one shape"):
        align_patches(window, torch.zeros(1, 16, 17), torch.eye(2)[None])
