"""Each track's keypoints refined against its own images, before the tracks place the cameras.

A detected keypoint (SIFT) is located to a few tenths of a pixel; the observations of one track are each off on their
own. Here every observation of a track is aligned to one reference observation of the same track by least-squares
matching of image patches (``patch_alignment``: an affine warp with gain and offset, coarse to fine, robust to
occlusion), so that all of them see the point the reference sees, to a small part of a pixel. The track's common
offset (the reference keypoint's own error) moves its 3D point, not the cameras.

- Reference: the observation whose viewing direction is closest to all the others' (the smallest largest angle), so
  that the perspective change to any other view is least.
- Start of the affine warp: the map that the plane through the track's 3D point, facing the reference camera, induces
  from the reference image to the other (the cameras and the point of the model: an SfM model's images.bin holds
  positions only, no keypoint shapes); a square template about the reference keypoint (``patch_alignment``).
- Images: read at whatever size they are on disk; keypoints scale from the model's camera size to it per axis
  (continuous pixels, COLMAP's centres at +0.5), and back.
- A refined position replaces the detected one only where the alignment converged, the aligned patches correlate
  (``MIN_CORRELATION``), both windows lie inside their images (past the border a window reads zeros, whose edge
  would be matched), it moved the keypoint by at most ``MAX_SHIFT_PX`` and it agrees with the other views: its
  distance to the projection of the track's 3D point is at most ``AGREEMENT_PX`` more than the detected keypoint's.
  Elsewhere the detected keypoint stays.

Batched torch on the CPU or CUDA (``device``); the model is changed in place (its points are not moved: the caller
re-adjusts them on the refined keypoints).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from PIL import Image
from torch import Tensor

from s2camp_ns.core.camera import Intrinsics, pixel_to_ray_direction, project
from s2camp_ns.core.colmap_camera_models import intrinsics_from_colmap
from s2camp_ns.tracks.patch_alignment import align_patches

KEYPOINT_RECIPE = 1
"""Part of the track caches' keys (``image_tracks``, ``robust_adjustment``): raise it when the refinement changes."""
WINDOW = 32
"""Side of the windows cut about each keypoint (px of the image on disk): the template at both levels of
``patch_alignment`` and the search about it."""
MIN_CORRELATION = 0.8
"""Normalised cross-correlation of the aligned patches below which the alignment is not trusted."""
MAX_SHIFT_PX = 1.5
"""Largest move of a keypoint (px of the image on disk) that is taken: three standard deviations of the difference of
two SIFT localizations (about 0.35 px per axis each); farther, another structure was matched."""
AGREEMENT_PX = 1.0
"""How much farther than the detected keypoint from the projection of the track's point a refined one may lie (px)."""
CHUNK = 4096
"""Pairs aligned at once (memory: two windows of ``WINDOW`` squared floats each)."""


@dataclass(frozen=True)
class KeypointRefinement:
    """What ``refine_keypoints`` did."""

    aligned: int
    """Observations aligned to their track's reference (every observation of a track of two or more, but the
    reference)."""
    refined: int
    """Observations whose keypoint was replaced."""
    median_shift_px: float
    """Median move of the replaced keypoints (px of the model's cameras); NaN when none was."""
    seconds: float

    def describe(self) -> str:
        share = self.refined / max(self.aligned, 1)
        moved = f"median move {self.median_shift_px:.3g} px"
        return f"{self.refined} of {self.aligned} keypoints refined ({share:.0%}), {moved}, in {self.seconds:.1f} s"


@dataclass(frozen=True)
class _Pairs:
    """Each aligned observation (b) with its track's reference observation: images (indices into the model's sorted
    image ids), keypoints (model px) and the track's 3D point."""

    reference_image: Int[Tensor, " b"]
    target_image: Int[Tensor, " b"]
    target_point2d: list[int]
    reference_xy: Float[Tensor, "b 2"]
    target_xy: Float[Tensor, "b 2"]
    xyz: Float[Tensor, "b 3"]


def _cameras(reconstruction: pycolmap.Reconstruction, image_ids: list[int]) -> tuple[Intrinsics, Tensor]:
    """``Intrinsics`` [n] and OpenCV camera-to-world [n, 3, 4] (float64) of the images ``image_ids``."""
    camera_ids = [reconstruction.images[i].camera_id for i in image_ids]
    per_camera = {}
    for camera_id in dict.fromkeys(camera_ids):
        camera = reconstruction.cameras[camera_id]
        per_camera[camera_id] = intrinsics_from_colmap(camera.model.name, camera.params, camera.width, camera.height)
    projections = {intrinsics.model for intrinsics in per_camera.values()}
    if len(projections) > 1:
        raise ValueError(f"keypoint refinement needs one projection for all cameras, got {sorted(projections)}")
    values = torch.cat([per_camera[camera_id].tensors() for camera_id in camera_ids])  # [n, 13]
    intrinsics = Intrinsics.from_tensors(values, model=projections.pop())
    w2c = np.stack([np.asarray(reconstruction.images[i].cam_from_world().matrix()) for i in image_ids])
    rotation = torch.as_tensor(w2c[:, :, :3], dtype=torch.float64).transpose(1, 2)
    centre = -(rotation @ torch.as_tensor(w2c[:, :, 3:], dtype=torch.float64))
    return intrinsics, torch.cat([rotation, centre], dim=-1)


def _reference(centres: Float[Tensor, "m 3"], xyz: Float[Tensor, " 3"]) -> int:
    """The observation whose viewing direction has the smallest largest angle to the others'."""
    directions = F.normalize(centres - xyz, dim=-1)
    return int((directions @ directions.T).amin(dim=1).argmax())


def _pairs(reconstruction: pycolmap.Reconstruction, row_of: dict[int, int], centres: Tensor) -> _Pairs:
    """Every track of two or more observations: its other observations, each with the track's reference."""
    reference_image, target_image, target_point2d, reference_xy, target_xy, xyz = [], [], [], [], [], []
    for point_id in sorted(reconstruction.points3D):
        point = reconstruction.points3D[point_id]
        elements = [(element.image_id, element.point2D_idx) for element in point.track.elements]
        if len(elements) < 2:
            continue
        rows = [row_of[image_id] for image_id, _ in elements]
        position = torch.as_tensor(point.xyz, dtype=torch.float64)
        chosen = _reference(centres[rows], position)
        ref_image, ref_index = elements[chosen]
        ref_xy = reconstruction.images[ref_image].points2D[ref_index].xy
        for k, (image_id, index) in enumerate(elements):
            if k == chosen:
                continue
            reference_image.append(row_of[ref_image])
            target_image.append(row_of[image_id])
            target_point2d.append(index)
            reference_xy.append(ref_xy)
            target_xy.append(reconstruction.images[image_id].points2D[index].xy)
            xyz.append(point.xyz)
    as_tensor = lambda values, dtype, shape: torch.as_tensor(np.asarray(values, dtype=dtype).reshape(shape))  # noqa: E731
    return _Pairs(
        reference_image=as_tensor(reference_image, np.int64, (-1,)),
        target_image=as_tensor(target_image, np.int64, (-1,)),
        target_point2d=target_point2d,
        reference_xy=as_tensor(reference_xy, np.float64, (-1, 2)),
        target_xy=as_tensor(target_xy, np.float64, (-1, 2)),
        xyz=as_tensor(xyz, np.float64, (-1, 3)),
    )


def _world_to_pixels(
    points: Float[Tensor, "b l 3"], intrinsics: Intrinsics, c2w: Float[Tensor, "b 3 4"]
) -> Float[Tensor, "b l 2"]:
    """Pixels of world points in each pair's camera (``intrinsics`` and ``c2w`` indexed per pair)."""
    camera = (points - c2w[:, None, :, 3]) @ c2w[:, :, :3]
    return project(camera, intrinsics)[0]


def initial_affine(
    pairs: _Pairs, intrinsics: Intrinsics, c2w: Float[Tensor, "n 3 4"]
) -> tuple[Float[Tensor, "b 2 2"], Float[Tensor, "b 2"]]:
    """The plane-induced map of reference offsets to target offsets (model px; module docstring), and the
    projection of each track's point into the target image (model px)."""
    ref, tgt = pairs.reference_image, pairs.target_image
    ref_c2w, tgt_c2w = c2w[ref], c2w[tgt]
    pixels = pairs.reference_xy[:, None] + torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    rays = pixel_to_ray_direction(pixels, intrinsics[ref]) @ ref_c2w[:, :, :3].transpose(1, 2)  # [b, 3, 3] world
    centre = ref_c2w[:, :, 3]
    normal = F.normalize(centre - pairs.xyz, dim=-1)  # the plane faces the reference camera
    depth = ((pairs.xyz - centre) * normal).sum(-1, keepdim=True) / (rays * normal[:, None]).sum(-1)
    on_plane = centre[:, None] + depth[..., None] * rays  # [b, 3, 3]
    points = torch.cat([pairs.xyz[:, None], on_plane], dim=1)  # the point itself, then the plane's three
    target = _world_to_pixels(points, intrinsics[tgt], tgt_c2w)  # [b, 4, 2]
    affine = torch.stack([target[:, 2] - target[:, 1], target[:, 3] - target[:, 1]], dim=-1)  # columns: dx, dy
    return affine, target[:, 0]


def _windows(
    images: list[Tensor], image: Int[Tensor, " b"], centres: Float[Tensor, "b 2"], device: torch.device
) -> Float[Tensor, "b s s"]:
    """``WINDOW`` squared crops (bilinear, zero outside) of the images on disk about each centre (their px)."""
    out = torch.zeros(len(image), WINDOW, WINDOW, dtype=torch.float32, device=device)
    steps = torch.arange(WINDOW, dtype=torch.float64) + 0.5 - WINDOW / 2.0
    offsets = torch.stack(torch.meshgrid(steps, steps, indexing="xy"), dim=-1)  # [s, s, 2] x, y
    for index in torch.unique(image).tolist():
        rows = (image == index).nonzero()[:, 0]
        picture = images[index].to(device=device, dtype=torch.float32)[None, None] / 255.0
        height, width = picture.shape[-2:]
        points = centres[rows][:, None, None] + offsets  # [r, s, s, 2] continuous px of the picture
        grid = points / torch.tensor([width, height], dtype=torch.float64) * 2.0 - 1.0
        grid = grid.to(device=device, dtype=torch.float32).reshape(1, -1, WINDOW, 2)
        crops = F.grid_sample(picture, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        out[rows.to(device)] = crops.reshape(len(rows), WINDOW, WINDOW)
    return out


def _read_images(reconstruction: pycolmap.Reconstruction, image_ids: list[int], root: Path):
    """Each image on disk as 8-bit luminance [H, W], and its scale (sx, sy) from the model's camera pixels."""
    images, scales = [], []
    for image_id in image_ids:
        image = reconstruction.images[image_id]
        camera = reconstruction.cameras[image.camera_id]
        with Image.open(root / image.name) as picture:
            luminance = np.asarray(picture.convert("L"))
        images.append(torch.from_numpy(luminance.copy()))
        scales.append((luminance.shape[1] / camera.width, luminance.shape[0] / camera.height))
    return images, torch.tensor(scales, dtype=torch.float64)


def refine_keypoints(
    reconstruction: pycolmap.Reconstruction, image_root: Path, device: torch.device | str | None = None, progress=None
) -> KeypointRefinement:
    """Refine the keypoints of ``reconstruction``'s tracks in place (module docstring) from its images under
    ``image_root`` (by name), on ``device`` (None: CUDA where torch sees it, else the CPU). ``progress``: called as
    ``progress(done, total)`` after each chunk of pairs."""
    began = time.perf_counter()
    image_ids = sorted(reconstruction.reg_image_ids())
    row_of = {image_id: row for row, image_id in enumerate(image_ids)}
    intrinsics, c2w = _cameras(reconstruction, image_ids)
    pairs = _pairs(reconstruction, row_of, c2w[:, :, 3])
    total = len(pairs.target_point2d)
    if total == 0:
        return KeypointRefinement(0, 0, float("nan"), time.perf_counter() - began)
    images, scale = _read_images(reconstruction, image_ids, image_root)
    affine, projected = initial_affine(pairs, intrinsics, c2w)
    refined = torch.full((total, 2), float("nan"), dtype=torch.float64)
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    for start in range(0, total, CHUNK):
        rows = torch.arange(start, min(start + CHUNK, total))
        refined[rows] = _align_chunk(pairs, rows, affine, images, scale, device)
        if progress is not None:
            progress(int(rows[-1]) + 1, total)
    detected_miss = (pairs.target_xy - projected).norm(dim=-1)
    refined_miss = (refined - projected).norm(dim=-1)
    keep = torch.isfinite(refined).all(dim=-1) & (refined_miss <= detected_miss + AGREEMENT_PX)
    moved = (refined - pairs.target_xy).norm(dim=-1)[keep]
    for row in keep.nonzero()[:, 0].tolist():
        image = reconstruction.images[image_ids[int(pairs.target_image[row])]]
        image.points2D[pairs.target_point2d[row]].xy = refined[row].numpy()
    median = float(moved.median()) if moved.numel() else float("nan")
    return KeypointRefinement(total, int(keep.sum()), median, time.perf_counter() - began)


def _align_chunk(
    pairs: _Pairs, rows: Tensor, affine: Tensor, images: list[Tensor], scale: Tensor, device: torch.device
) -> Float[Tensor, "r 2"]:
    """The refined target keypoints (model px) of the pairs ``rows``; NaN where the alignment is not taken."""
    ref, tgt = pairs.reference_image[rows], pairs.target_image[rows]
    ref_scale, tgt_scale = scale[ref], scale[tgt]
    ref_centre, tgt_centre = pairs.reference_xy[rows] * ref_scale, pairs.target_xy[rows] * tgt_scale
    start = tgt_scale[:, :, None] * affine[rows] / ref_scale[:, None, :]  # in the pixels on disk
    result = align_patches(
        _windows(images, ref, ref_centre, device),
        _windows(images, tgt, tgt_centre, device),
        start.to(device=device, dtype=torch.float32),
    )
    shift = result.shift.to("cpu", torch.float64)
    correlated = result.correlation.cpu() >= MIN_CORRELATION
    taken = result.converged.cpu() & correlated & (shift.norm(dim=-1) <= MAX_SHIFT_PX)
    taken &= _window_in_image(ref_centre, images, ref) & _window_in_image(tgt_centre, images, tgt)
    refined = (tgt_centre + shift) / tgt_scale
    return torch.where(taken[:, None], refined, torch.full_like(refined, float("nan")))


def _window_in_image(centres: Float[Tensor, "b 2"], images: list[Tensor], image: Int[Tensor, " b"]) -> Tensor:
    """Whether each ``WINDOW`` about ``centres`` lies inside its image: past the border the window reads zeros, whose
    edge the alignment would match."""
    size = torch.tensor([[images[i].shape[1], images[i].shape[0]] for i in image.tolist()], dtype=torch.float64)
    half = WINDOW / 2.0
    return ((centres >= half) & (centres <= size.reshape(-1, 2) - half)).all(dim=-1)


__all__ = ["KEYPOINT_RECIPE", "KeypointRefinement", "initial_affine", "refine_keypoints"]
