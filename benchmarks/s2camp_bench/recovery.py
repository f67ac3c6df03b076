"""``s2camp-bench recovery``: does S2CamP recover perturbed cameras as well as CamP, with 10% of the samples?

Tier 1 (geometric, seconds): see ``recovery_geometric``. Tier 2 (photometric, ``ns-train`` of every variant,
minutes): see ``recovery_photometric``. Each variant starts from the same perturbed cameras (CamP protocol, fixed
seed) of the same generated scenes; CamP's random baseline is averaged over seeds. Tier 3 (a real SfM start, the
renderer's cameras as the truth): see ``recovery_sfm``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from s2camp_bench.report import markdown_table
from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene
from s2camp_ns.core.preconditioner import CAMP_SAMPLING

from .common import DEFAULT_OUTPUT_DIR, in_work_folder, log, write_report
from .recovery_geometric import SHARED_VARIANTS, VARIANTS, GeometricConfig, iterations_to, load_scene, run_variant
from .recovery_photometric import PhotometricConfig, run_photometric
from .recovery_sfm import SfmRecoveryConfig, run_sfm_tier

SCENES = {
    "narrow": MakeSceneConfig(num_cameras=24, width=160, height=120, fov="narrow", seed=0),
    "wide": MakeSceneConfig(num_cameras=24, width=160, height=120, fov="wide", seed=1),
}
QUICK_SCENE_SIZE = {"num_cameras": 8, "width": 64, "height": 48}


QUICK_PHOTOMETRIC_VARIANTS = ("none", "so3xr3", "s2camp")
"""``--quick`` (CI) trains these in tier 2: no refinement, the baseline of the time ratios and S2CamP. Each ns-train
start-up has a fixed cost on CI's CPU; every variant's ns-train command is checked without training
(tests/test_recovery_seeds.py)."""
QUICK_SFM_VARIANTS = ("none", "s2camp-per-camera")
"""``--quick`` trains these from the SfM start in tier 3 (the SfM reconstruction and its checks run in full)."""


@dataclass
class RecoveryConfig:
    """Camera recovery from CamP-perturbed cameras, every variant on the same scenes and start."""

    scenes: tuple[str, ...] = ("narrow", "wide")
    """Generated scenes (s2camp-make-scene presets)."""
    variants: tuple[str, ...] = VARIANTS
    tiers: tuple[int, ...] = (1, 2, 3)
    """1: geometric (minutes); 2: photometric ns-train runs (most of the hour); 3: ns-train from an SfM start (the
    report states the wall time)."""
    geometric: GeometricConfig = field(default_factory=GeometricConfig)
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)
    sfm: SfmRecoveryConfig = field(default_factory=SfmRecoveryConfig)
    """Tier 3: its scenes, variants, SfM camera model and checks, training as tier 2."""
    quick: bool = False
    """Small run for CI: tier 1 with 100 iterations (every variant), tiers 2 and 3 with a few iterations on a small
    scene, one CamP seed, training ``QUICK_PHOTOMETRIC_VARIANTS`` and ``QUICK_SFM_VARIANTS``; asserts only that they
    run."""
    scene_dir: Path | None = None
    """Where the scenes are generated (a temporary folder by default)."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False

    def effective(self) -> RecoveryConfig:
        if not self.quick:
            return self
        geometric = replace(self.geometric, iterations=100, camp_seeds=(0,), log_every=10)
        sfm = replace(self.sfm, variants=QUICK_SFM_VARIANTS)
        return replace(self, geometric=geometric, sfm=sfm)

    def photometric_variants(self) -> tuple[str, ...]:
        """Tier 2's trained variants: all of them, or ``QUICK_PHOTOMETRIC_VARIANTS`` for ``--quick``."""
        if not self.quick:
            return self.variants
        return tuple(variant for variant in self.variants if variant in QUICK_PHOTOMETRIC_VARIANTS)


def _s2camp_range(sampling) -> str:
    """How ns-train's S2CamP chooses its proxy range: from the scene's points unless the config fixes it."""
    near, far = sampling.fixed_range()
    if sampling.auto:
        return f"chosen per camera from the scene's points (s2camp_ns/core/proxy_range.py; [{near:g}, {far:g}] without)"
    return f"in [{near:g}, {far:g}]"


def _camp_sampling() -> str:
    c = CAMP_SAMPLING
    return (
        f"{c.num_points} random pixels, Euclidean distance along the ray in [{c.t_near:g}, {c.t_far:g}] from a power "
        f"ladder p = {c.ladder_p:g}, no contraction; docs/benchmarks/camp-check.md"
    )


def _mean(values: list[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return sum(finite) / len(finite) if len(finite) == len(values) else math.nan


def run_geometric(config: RecoveryConfig, scene_root: Path) -> tuple[list[dict], dict]:
    rows, histories = [], {}
    for scene_name in config.scenes:
        scene_config = replace(SCENES[scene_name], output_dir=scene_root / scene_name)
        if config.quick:
            scene_config = replace(scene_config, **QUICK_SCENE_SIZE)
        scene = load_scene(make_scene(scene_config), scene_name, config.geometric.max_points)
        baseline_seconds = None
        for variant in config.variants:
            seeds = config.geometric.camp_seeds if variant == "camp" else (0,)
            results = [run_variant(scene, variant, config.geometric, seed=seed) for seed in seeds]
            histories[(scene_name, variant)] = results[0]["history"]
            row = {"tier": 1, "scene": scene_name, "variant": variant, "seeds": len(seeds)}
            row["intrinsics"] = "per-camera" if variant in SHARED_VARIANTS else "per-image"
            for key in ("rot_err", "pos_err", "focal_err", "pp_err", "k1_err"):
                row[key] = _mean([r["final"][key] for r in results])
            for key, threshold in config.geometric.thresholds.items():
                row[f"iters_to_{key}"] = _mean([iterations_to(r["history"], key, threshold) for r in results])
            row["sec_per_iter"] = _mean([r["sec_per_iter"] for r in results])
            if variant == "so3xr3":
                baseline_seconds = row["sec_per_iter"]
            rows.append(row)
            log(
                f"recovery tier 1 {scene_name:6s} {variant:12s} rot {row['rot_err']:.2e} pos {row['pos_err']:.2e} "
                f"focal {row['focal_err']:.3f}"
            )
        for row in rows:
            if row["scene"] == scene_name and baseline_seconds:
                row["time_vs_so3xr3"] = row["sec_per_iter"] / baseline_seconds
    return rows, histories


def run(config: RecoveryConfig) -> list[dict]:
    config = config.effective()
    for tier in config.tiers:
        if tier not in (1, 2, 3):
            raise ValueError(f"tiers must contain only 1, 2 and 3, got {tier!r}")
    return in_work_folder(config.scene_dir, "s2camp-recovery-", lambda root: _run(config, root))


def _run(config: RecoveryConfig, root: Path) -> list[dict]:
    rows, histories = [], {}
    run.minutes = {}  # type: ignore[attr-defined]
    began = time.perf_counter()
    if 1 in config.tiers:
        # Tier 1 is many small tensor operations: one thread keeps per-iteration times stable and comparable
        # between variants (several threads on a busy 2-core machine made them vary widely).
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            rows, histories = run_geometric(config, root / "tier1")
        finally:
            torch.set_num_threads(threads)
        run.minutes[1] = (time.perf_counter() - began) / 60.0  # type: ignore[attr-defined]
    run.histories = histories  # type: ignore[attr-defined]
    run.photometric_histories = {}  # type: ignore[attr-defined]
    if 2 in config.tiers:
        began = time.perf_counter()
        tier2_rows, tier2_histories = run_photometric(
            config.scenes, config.photometric_variants(), config.photometric, root / "tier2", config.quick
        )
        rows.extend(tier2_rows)
        run.photometric_histories = tier2_histories  # type: ignore[attr-defined]
        run.minutes[2] = (time.perf_counter() - began) / 60.0  # type: ignore[attr-defined]
    run.sfm_histories, run.sfm_quality = {}, []  # type: ignore[attr-defined]
    if 3 in config.tiers:
        began = time.perf_counter()
        tier3_rows, run.sfm_histories, run.sfm_quality = run_sfm_tier(  # type: ignore[attr-defined]
            config.sfm, root / "tier3", config.quick
        )
        rows.extend(tier3_rows)
        run.minutes[3] = (time.perf_counter() - began) / 60.0  # type: ignore[attr-defined]
    return rows


def plot(histories: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({scene for scene, _ in histories})
    keys = (("focal_err", "focal error (px)"), ("rot_err", "rotation error (rad)"), ("pos_err", "position error"))
    figure, axes = plt.subplots(len(scenes), 3, figsize=(12, 3.3 * len(scenes)), squeeze=False)
    for row_axes, scene in zip(axes, scenes, strict=True):
        for axis, (key, label) in zip(row_axes, keys, strict=True):
            for (name, variant), history in histories.items():
                if name == scene and len(history) > 1:
                    axis.semilogy([h["iteration"] for h in history], [h[key] for h in history], label=variant)
            axis.set_title(f"{scene}: {label}")
            axis.set_xlabel("iteration")
            axis.grid(True, which="both", alpha=0.3)
        row_axes[0].legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def report(rows: list[dict], config: RecoveryConfig) -> Path:
    config = config.effective()
    sections = []
    tier1 = [row for row in rows if row["tier"] == 1]
    tier2 = [row for row in rows if row["tier"] == 2]
    if tier1:
        plot(getattr(run, "histories", {}), config.output_dir / "recovery-tier1.png")
        sections += _tier1_section(tier1, config)
    if tier2:
        plot(getattr(run, "photometric_histories", {}), config.output_dir / "recovery-tier2.png")
        sections += _tier2_section(tier2, config)
    if 3 in config.tiers:
        tier3 = [row for row in rows if row["tier"] == 3]
        if any(row["variant"] != "start" for row in tier3):
            plot(getattr(run, "sfm_histories", {}), config.output_dir / "recovery-tier3.png")
        sections += _tier3_section(tier3, getattr(run, "sfm_quality", []), config)
    minutes = getattr(run, "minutes", {})
    if minutes:
        spent = ", ".join(f"tier {tier} {value:.1f}" for tier, value in sorted(minutes.items()))
        sections.append(f"Wall time of this run: {sum(minutes.values()):.1f} minutes ({spent}).")
    command = "s2camp-bench recovery" + (" --quick" if config.quick else "")
    if tuple(config.tiers) != (1, 2, 3):
        command += " --tiers " + " ".join(str(tier) for tier in config.tiers)
    return write_report(config.output_dir, "recovery", "Camera recovery from perturbed cameras", command, sections)


def _tier2_section(rows: list[dict], config: RecoveryConfig) -> list[str]:
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig

    p = config.photometric.quick() if config.quick else config.photometric
    a = p.alignment
    sampling = S2CampCameraOptimizerConfig().sampling
    columns = [
        "scene", "variant", "seeds", "rot_err", "pos_err", "focal_err",
        "iters_to_half_rot_err", "iters_to_half_pos_err", "iters_to_half_focal_err",
        "psnr", "ssim", "lpips", "psnr_unaligned", "sec_per_iter", "time_vs_so3xr3",
    ]  # fmt: skip
    headers = [
        "scene", "variant", "seeds", "rot err (rad)", "pos err", "focal err (px)",
        "iters to half rot", "iters to half pos", "iters to half focal",
        "PSNR", "SSIM", "LPIPS", "PSNR before alignment", "s / iter", "time vs so3xr3",
    ]  # fmt: skip
    start = {row["scene"]: row for row in rows}
    starts = "; ".join(
        f"{scene}: rot {row['start_rot_err']:.2e} rad, pos {row['start_pos_err']:.2e}, "
        f"focal {row['start_focal_err']:.3g} px"
        for scene, row in start.items()
    )
    setup = (
        f"Tier 2: `ns-train` of every variant on generated scenes ({_scene_sizes(config)}, every 8th image held "
        f"out), CPU-sized nerfacto "
        f"(`s2camp_bench.train_commands.SMALL_MODEL`), {p.rays_per_batch} rays per step. A shared "
        f"warm start of {p.warm_start} iterations on the accurate cameras (camera learning rate zero), then "
        f"{p.iterations} iterations per variant from the perturbed cameras (seed {p.perturbation_seed}; sigma "
        f"position {p.sigma_position:g}, look-at {p.sigma_look_at:g}, focal {p.sigma_focal_length:g}, dolly "
        f"{p.sigma_dolly_z:g}), camera lr {p.camera_lr:g} -> {p.camera_lr_final:g} for every variant; P refreshed "
        f"every {p.refresh_every} iterations for s2camp; proxy frustum t {_s2camp_range(sampling)} "
        f"(contracted) for S2CamP, CamP's published sampling for CamP ({_camp_sampling()}); CamP over seeds "
        f"{list(p.camp_seeds)}. Errors as in tier 1, "
        f"evaluated on checkpoints every {p.checkpoint_every} iterations; start errors {starts}. Held-out views: "
        f"{a.steps} camera-only Adam steps (pose + focal scale, {a.rays} rays per step, lr {a.lr:g} -> "
        f"{a.lr_final:g}) from the similarity-mapped reference camera, then PSNR / SSIM of the full image (LPIPS "
        "NaN where its weights are not cached). 'iters to half' = first checkpoint with at most half the start "
        "error. s / iter from nerfstudio's per-step event stamps (checkpoint saves and refreshes included); "
        "so3xr3 is `ns-train s2camp-so3xr3`, nerfstudio's stock pose optimizer in the same pipeline."
    )
    sections = [
        "## Tier 2: photometric joint optimisation (ns-train)",
        setup,
        markdown_table(rows, columns, headers),
    ]
    return [*sections, *_spread_sections(rows, p), "![tier 2](recovery-tier2.png)"]


def _spread_sections(rows: list[dict], config: PhotometricConfig) -> list[str]:
    """The range table where a variant other than CamP repeated (CamP always does, and its seeds are listed)."""
    if any(row["seeds"] > 1 and row["variant"] != "camp" for row in rows):
        return [_spread_table(rows, config)]
    return []


def _spread_table(rows: list[dict], config: PhotometricConfig) -> str:
    """Each repeated variant's final errors as min - max over its runs (the table above gives their mean)."""
    keys = ("rot_err", "pos_err", "focal_err")
    ranges = [
        {"scene": row["scene"], "variant": row["variant"], "seeds": row["seeds"]}
        | {key: f"{row[f'{key}_min']:.3g} - {row[f'{key}_max']:.3g}" for key in keys}
        for row in rows
        if row["seeds"] > 1
    ]
    headers = ["scene", "variant", "runs", "rot err range (rad)", "pos err range", "focal err range (px)"]
    caption = (
        f"Run-to-run range of the final errors (nerfstudio seeds {list(config.training_seeds)}; CamP: its sampling "
        f"seeds {list(config.camp_seeds)}):"
    )
    return caption + "\n\n" + markdown_table(ranges, ["scene", "variant", "seeds", *keys], headers)


def _tier3_section(rows: list[dict], quality: list[dict], config: RecoveryConfig) -> list[str]:
    from .recovery_sfm import QUICK_SFM_SCENE, SFM_SCENES, TRAINING_DOWNSCALE, intrinsics_option_available

    s = config.sfm
    p = s.photometric.quick() if config.quick else s.photometric
    scenes = []
    for name in s.scenes[:1] if config.quick else s.scenes:
        scene = replace(SFM_SCENES[name], **QUICK_SFM_SCENE) if config.quick else SFM_SCENES[name]
        scenes.append(
            f"{name} {scene.fov} fov, {scene.num_cameras} cameras {scene.width}x{scene.height}, "
            f"{scene.supersample}x{scene.supersample} rays per pixel"
        )
    quality_columns = [
        "scene", "registered", "points", "sfm_rot_err_mean", "sfm_rot_err_max", "sfm_centre_err_mean",
        "sfm_centre_err_max", "sfm_focal", "true_focal", "sfm_reprojection_median_px",
        "truth_reprojection_median_px", "sfm_reprojection_rms_px", "truth_reprojection_rms_px",
        "ba_rot_err_mean", "ba_centre_err_mean", "ba_focal", "status",
    ]  # fmt: skip
    quality_headers = [
        "scene", "registered", "3D points", "rot err mean (rad)", "rot err max (rad)", "centre err mean",
        "centre err max", "SfM focal (px)", "true focal (px)", "reproj. median, SfM cameras (px)",
        "reproj. median, true cameras (px)", "reproj. RMS, SfM cameras (px)", "reproj. RMS, true cameras (px)",
        "after BA: rot err mean", "after BA: centre err mean", "after BA: focal (px)", "status",
    ]  # fmt: skip
    columns = [
        "scene", "variant", "intrinsics", "rot_err", "pos_err", "focal_err",
        "iters_to_half_rot_err", "iters_to_half_pos_err", "iters_to_half_focal_err",
        "psnr", "ssim", "psnr_unaligned", "sec_per_iter",
    ]  # fmt: skip
    headers = [
        "scene", "variant", "intrinsics", "rot err (rad)", "pos err", "focal err (px)",
        "iters to half rot", "iters to half pos", "iters to half focal",
        "PSNR", "SSIM", "PSNR before alignment", "s / iter",
    ]  # fmt: skip
    per_camera = (
        ""
        if intrinsics_option_available()
        else " s2camp-per-camera is missing: this checkout's camera optimizer has no `intrinsics` option yet."
    )
    setup = (
        f"Tier 3: SfM start, the renderer's cameras as the truth. Generated scenes ({'; '.join(scenes)}); pycolmap "
        f"SIFT extraction, exhaustive matching and incremental mapping (one thread, seed 0) with one shared "
        f"{s.camera_model} camera on the full-resolution images, {_focal_start(s.focal_prior)}. A scene counts only "
        f"if every image is registered in one model whose camera centres are within {s.check.max_centre_error:g} x "
        f"the ring radius of the truth and rotations within {s.check.max_rotation_error:g} rad after a similarity "
        "alignment; otherwise it is reported as failed and skipped. SfM quality (truth world units, ring radius 4; "
        "focal at full resolution). Reprojection errors: median and root mean square over SfM's SIFT observations, "
        "each track triangulated (DLT) with SfM's cameras and with the true ones. 'after BA': COLMAP's bundle "
        "adjustment of the SfM model with the true camera model (RADIAL; an OPENCV start keeps OPENCV) and no "
        "tolerance, run until no step lowers the cost: whether local refinement of SfM's own objective moves its "
        "cameras towards the truth:"
    )
    training = (
        f"Training as tier 2 on the 1/{TRAINING_DOWNSCALE} resolution images: a shared warm start of {p.warm_start} "
        f"iterations on the SfM cameras (camera learning rate zero), then {p.iterations} iterations per variant "
        f"from the SfM cameras (no perturbation), camera lr {p.camera_lr:g} -> {p.camera_lr_final:g}, P refreshed "
        f"every {p.refresh_every} iterations for s2camp, CamP seeds {list(p.camp_seeds)}. Errors against the true "
        "cameras (`--reference-model`: the scene's own model, similarity-aligned), after a similarity alignment, "
        "in normalized scene units and pixels at the training resolution; 'start' is SfM's own error. Held-out "
        "views (every 8th) from the true cameras, PSNR / SSIM after test-time alignment as in tier 2. "
        "'intrinsics': per-camera for the start (SfM's one shared camera) and s2camp-per-camera (one set per "
        "physical camera), per-image for the others (tier 2's convention; none and so3xr3 do not refine the "
        "intrinsics)." + per_camera
    )
    sections = [
        "## Tier 3: refinement from an SfM start",
        setup,
        markdown_table(quality, quality_columns, quality_headers),
        training,
    ]
    if rows:
        sections += [markdown_table(rows, columns, headers)]
    sections += _spread_sections(rows, p)
    if any(row["variant"] != "start" for row in rows):
        sections.append("![tier 3](recovery-tier3.png)")
    return sections


def _focal_start(focal_prior: float | None) -> str:
    if focal_prior is None:
        return "the mapper starting from COLMAP's focal length guess without EXIF (1.2 x max(W, H))"
    return f"the mapper starting from {focal_prior:g} x the true focal length (an EXIF-like prior)"


def _scene_sizes(config: RecoveryConfig) -> str:
    from .recovery_photometric import QUICK_SCENE_SIZE, SCENES

    parts = []
    for name in config.scenes[:1] if config.quick else config.scenes:
        scene = replace(SCENES[name], **QUICK_SCENE_SIZE) if config.quick else SCENES[name]
        parts.append(f"{name} {scene.fov} fov, {scene.num_cameras} cameras {scene.width}x{scene.height}")
    return "; ".join(parts)


def _tier1_section(rows: list[dict], config: RecoveryConfig) -> list[str]:
    thresholds = config.geometric.thresholds
    columns = [
        "scene",
        "variant",
        "seeds",
        "rot_err",
        "pos_err",
        "focal_err",
        "pp_err",
        "k1_err",
        "iters_to_rot_err",
        "iters_to_pos_err",
        "iters_to_focal_err",
        "sec_per_iter",
        "time_vs_so3xr3",
    ]
    headers = [
        "scene",
        "variant",
        "seeds",
        "rot err (rad)",
        "pos err",
        "focal err (px)",
        "pp err (px)",
        "k1 err",
        f"iters to rot < {thresholds['rot_err']:g}",
        f"iters to pos < {thresholds['pos_err']:g}",
        f"iters to focal < {thresholds['focal_err']:g} px",
        "s / iter",
        "time vs so3xr3",
    ]
    g = config.geometric
    setup = (
        f"Tier 1: {g.iterations} Adam iterations (b1 0.9, b2 0.99, one CPU thread) on the mean squared reprojection "
        "error of the "
        f"scene's 3D points (pixels / max(W, H)); lr {g.lr:g} -> {g.lr_final:g} (exponential) for raw and the "
        f"whitened variants, {g.so3xr3_lr:g} -> {g.so3xr3_lr_final:g} for so3xr3; P refreshed every "
        f"{g.refresh_every} iterations for s2camp; proxy frustum t in {list(g.sampling.fixed_range())} "
        f"(contracted) for S2CamP, CamP's published sampling for CamP ({_camp_sampling()}); CamP averaged over seeds "
        f"{list(g.camp_seeds)}; perturbation seed "
        f"{g.perturbation_seed} (CamP protocol, distortion zeroed). Errors after a similarity alignment to the true "
        "cameras: mean rotation angle (rad), mean camera-centre distance (normalized scene units), mean |fx error| "
        "(px), mean principal-point distance (px), mean |k1 error|."
    )
    return [
        "## Tier 1: geometric refinement",
        setup,
        markdown_table(rows, columns, headers),
        "![tier 1](recovery-tier1.png)",
    ]
