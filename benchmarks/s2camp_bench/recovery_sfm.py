"""Tier 3 of ``s2camp-bench recovery``: refinement from a real SfM start, the renderer's cameras as the truth.

Per generated scene:

1. SfM (``benchmarks.sfm``): pycolmap SIFT extraction, exhaustive matching and incremental mapping with one shared
   camera (SIMPLE_RADIAL by default) on the full-resolution images, the mapper starting from an EXIF-like focal
   length (``focal_prior``); the scene counts only if every image is registered in a single model whose
   similarity-aligned centres and rotations are close to the truth (``SfmCheck``); otherwise it is reported as
   failed and skipped. ``local_refinement_check`` adds whether bundle adjustment with the true camera model moves
   SfM's cameras, and how well SfM's tracks fit SfM's and the true cameras;
2. as tier 2 (``recovery_photometric``): a shared warm start on the SfM cameras with the camera learning rate frozen,
   stripped of camera state, then every variant from it with the same camera schedule and iteration count, trained
   on the half-resolution images; no perturbation: the SfM cameras are the start;
3. evaluation as tier 2 with the truth as the reference (``--reference-model``: the generated scene's
   ``sparse/0``): camera errors of every checkpoint after similarity alignment, held-out PSNR / SSIM after test-time
   alignment from the true held-out cameras. The start row is SfM's own errors.

Variants: none (camera optimizer off), so3xr3 (nerfstudio's stock pose optimizer), camp (``s2camp-camp``),
s2camp-per-image and s2camp-per-camera (``s2camp`` with intrinsics per image, or shared by the images of one
physical camera). Rows carry ``intrinsics`` ('per-camera' / 'per-image', as in tier 2): 'per-camera' for the start
(SfM's one shared camera) and s2camp-per-camera; 'per-image' for every other variant, tier 2's convention, which
includes none and so3xr3 (they keep SfM's intrinsics unrefined).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

from .common import log
from .data_parser import SUBCOMMAND as BENCH_DATAPARSER
from .recovery_photometric import (
    PhotometricConfig,
    TrainedRun,
    evaluate_runs,
    run_seeds,
    run_timestamp,
    seed_arguments,
    summarize_scene,
    train_from_warm_start,
    variant_command,
    warm_start,
)
from .sfm import SfmCheck, SfmResult, local_refinement_check, run_sfm

SFM_SCENES = {
    "sfm-narrow": MakeSceneConfig(num_cameras=24, width=320, height=240, fov="narrow", points_per_image=50, seed=0),
    "sfm-wide": MakeSceneConfig(num_cameras=24, width=320, height=240, fov="wide", points_per_image=50, seed=0),
}
"""SIFT needs more pixels than tiers 1 and 2 use: SfM runs on 320x240, training on the 160x120 ``images_2``."""
QUICK_SFM_SCENE = {"supersample": 1}
"""CI: the same ring rendered with one ray per pixel (a quarter of the default's rays). Smaller rings fail SfM: 16 or
12 cameras at 240x180 registered only part of the images, 10 cameras at 160x120 made no model (such attempts at the
default rendering: docs/benchmarks/recovery.md, tier 3)."""
TRAINING_DOWNSCALE = 2
SFM_VARIANTS = ("none", "so3xr3", "camp", "s2camp-per-image", "s2camp-per-camera")
METHODS = {
    "none": "s2camp",
    "so3xr3": "s2camp-so3xr3",
    "camp": "s2camp-camp",
    "s2camp-per-image": "s2camp",
    "s2camp-per-camera": "s2camp",
}
INTRINSICS = {
    "start": "per-camera",
    "none": "per-image",
    "so3xr3": "per-image",
    "camp": "per-image",
    "s2camp-per-image": "per-image",
    "s2camp-per-camera": "per-camera",
}
"""The ``intrinsics`` key of the rows: how the row's method refines the intrinsics (module docstring)."""


@dataclass
class SfmRecoveryConfig:
    """Tier 3: refinement from an SfM start (module docstring)."""

    scenes: tuple[str, ...] = ("sfm-narrow", "sfm-wide")
    variants: tuple[str, ...] = SFM_VARIANTS
    camera_model: str = "SIMPLE_RADIAL"
    """Shared COLMAP camera model of SfM (SIMPLE_RADIAL or OPENCV)."""
    focal_prior: float | None = 1.05
    """SfM's initial focal length as a factor of the true one, as the EXIF focal length of a real capture gives it
    (the generated images carry no EXIF); None starts from COLMAP's guess without EXIF, 1.2 x max(W, H), from which
    SfM ends several times further from the truth on the wide scene (measured in docs/benchmarks/recovery.md,
    tier 3; ``benchmarks/s2camp_bench/sfm.py``)."""
    sfm_only: bool = False
    """Run SfM and its checks on every scene (the quality table), train nothing."""
    check: SfmCheck = field(default_factory=SfmCheck)
    photometric: PhotometricConfig = field(default_factory=lambda: PhotometricConfig(camp_seeds=(0,)))
    """Training and evaluation as tier 2 (its perturbation fields are not used); one CamP seed."""


def intrinsics_option_available() -> bool:
    """Whether the camera optimizer has the ``intrinsics`` option (per-image / per-camera)."""
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig

    return "intrinsics" in {f.name for f in dataclasses.fields(S2CampCameraOptimizerConfig)}


def available_variants(variants: tuple[str, ...]) -> tuple[str, ...]:
    """``variants`` without s2camp-per-camera while the camera optimizer has no ``intrinsics`` option."""
    if intrinsics_option_available():
        return variants
    return tuple(variant for variant in variants if variant != "s2camp-per-camera")


def variant_arguments(variant: str, seed: int, config: PhotometricConfig) -> list[str]:
    prefix = "--pipeline.model.camera-optimizer."
    intrinsics = [prefix + "intrinsics", INTRINSICS[variant]] if intrinsics_option_available() else []
    options = {
        "none": [prefix + "mode", "off"],
        "so3xr3": [],
        "camp": [prefix + "refresh-every", "0", *intrinsics],
        "s2camp-per-image": [prefix + "refresh-every", str(config.refresh_every), *intrinsics],
        "s2camp-per-camera": [prefix + "refresh-every", str(config.refresh_every), *intrinsics],
    }[variant]
    return seed_arguments(variant, seed) + options


def dataparser_arguments(truth: Path) -> list[str]:
    """The benchmarks' data parser with the generated scene's cameras as the reference (``--reference-model``)."""
    return [
        BENCH_DATAPARSER,
        "--downscale-factor", str(TRAINING_DOWNSCALE),
        "--reference-model", str(truth / "sparse" / "0"),
    ]  # fmt: skip


def sfm_scene(name: str, root: Path, config: SfmRecoveryConfig, quick: bool) -> SfmResult:
    """Generate the scene and run SfM on it."""
    scene_config = replace(SFM_SCENES[name], output_dir=root / "scenes" / name)
    if quick:
        scene_config = replace(scene_config, **QUICK_SFM_SCENE)
    truth = make_scene(scene_config)
    result = run_sfm(truth, root / "sfm" / name, config.camera_model, config.check, config.focal_prior)
    log(
        f"recovery tier 3 {name}: SfM registered {result.registered}/{result.images} images, {result.points} points, "
        f"rot {result.rot_err_mean:.2e} rad, centre {result.centre_err_mean:.2e}, focal {result.focal:.1f} px "
        f"(true {result.true_focal:.1f})" + (f"; FAILED: {result.failure}" if result.failure else "")
    )
    return result


def train_sfm_scene(
    name: str, truth: Path, sfm: Path, variants: tuple[str, ...], config: PhotometricConfig, root: Path
) -> list[TrainedRun]:
    """Shared warm start on the SfM cameras, then every variant (once per seed), one at a time."""
    work = root / "runs"
    arguments = dataparser_arguments(truth)
    warm = warm_start(sfm, work, name, config, tuple(arguments)) if config.warm_start > 0 else None
    runs = []
    for variant in variants:
        for seed in run_seeds(variant, config):
            method, timestamp = METHODS[variant], run_timestamp(variant, seed, config)
            command = variant_command(
                sfm, work, name, warm, method, timestamp, variant_arguments(variant, seed, config), arguments, config
            )
            path = train_from_warm_start(command, work, name, method, timestamp)
            runs.append(TrainedRun(name, variant, path))
    return runs


def sfm_row(name: str, result: SfmResult) -> dict:
    """SfM quality of one scene (errors in the truth's world units, focal at full resolution)."""
    return {
        "scene": name,
        "registered": f"{result.registered}/{result.images}",
        "points": result.points,
        "sfm_rot_err_mean": result.rot_err_mean,
        "sfm_rot_err_max": result.rot_err_max,
        "sfm_centre_err_mean": result.centre_err_mean,
        "sfm_centre_err_max": result.centre_err_max,
        "sfm_focal": result.focal,
        "true_focal": result.true_focal,
        "status": "ok" if result.failure is None else f"failed: {result.failure}",
    }


def run_sfm_tier(config: SfmRecoveryConfig, root: Path, quick: bool) -> tuple[list[dict], dict, list[dict]]:
    """Tier 3 rows (a start row per scene, then one per variant), error curves and the SfM quality rows."""
    photometric = config.photometric.quick() if quick else config.photometric
    scenes = config.scenes[:1] if quick else config.scenes
    variants = available_variants(config.variants)
    if len(variants) < len(config.variants):
        log("recovery tier 3: s2camp-per-camera skipped: the camera optimizer has no 'intrinsics' option yet")
    sfm_rows, runs, good = [], [], []
    for name in scenes:
        result = sfm_scene(name, root, config, quick)
        sfm_rows.append(sfm_row(name, result))
        if result.failure is not None:  # a failed scene is no data point: only its SfM quality row
            continue
        sfm_rows[-1] |= local_refinement_check(root / "scenes" / name, result.scene, config.check)
        if config.sfm_only:
            continue
        good.append(name)
        runs += train_sfm_scene(name, root / "scenes" / name, result.scene, variants, photometric, root)
    log(f"  evaluating {len(runs)} runs ({photometric.eval_workers} processes)")
    results = list(zip(runs, evaluate_runs(runs, photometric), strict=True))
    rows, histories = [], {}
    for name in good:
        scene_rows, scene_histories = summarize_sfm_scene(name, results, sfm_rows[scenes.index(name)])
        rows.extend(scene_rows)
        histories.update(scene_histories)
    return rows, histories, sfm_rows


def summarize_sfm_scene(name: str, results: list[tuple[TrainedRun, dict]], quality: dict) -> tuple[list[dict], dict]:
    """The scene's start row (SfM's own errors and quality), then one row per variant as in tier 2."""
    scene_rows, histories = summarize_scene(name, results, tier=3)
    first = scene_rows[0]
    start = {"tier": 3, "scene": name, "variant": "start", "seeds": 1}
    start |= {key: first[f"start_{key}"] for key in ("rot_err", "pos_err", "focal_err")}
    start |= {key: math.nan for key in ("psnr", "ssim", "lpips", "psnr_unaligned", "sec_per_iter")}
    start |= {key: value for key, value in quality.items() if key != "scene"}
    rows = [start, *scene_rows]
    for row in rows:
        row["intrinsics"] = INTRINSICS[row["variant"]]
    return rows, histories
