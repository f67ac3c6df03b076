"""Repeated runs in the recovery benchmark's photometric tiers: which seed each run gets, how runs are named, and how
their errors are summarized (mean and range)."""

from __future__ import annotations

from pathlib import Path

from s2camp_ns.benchmarks.recovery import RecoveryConfig, _tier2_section
from s2camp_ns.benchmarks.recovery_photometric import (
    PhotometricConfig,
    TrainedRun,
    run_seeds,
    run_timestamp,
    seed_arguments,
    summarize_scene,
)
from s2camp_ns.benchmarks.recovery_sfm import variant_arguments


def test_camp_varies_its_sampling_seed_and_every_other_variant_nerfstudio_s() -> None:
    assert seed_arguments("camp", 2) == ["--pipeline.model.camera-optimizer.sampling.seed", "2"]
    assert seed_arguments("s2camp-per-camera", 7) == ["--machine.seed", "7"]
    assert seed_arguments("none", 0) == ["--machine.seed", "0"]


def test_each_variant_runs_once_per_seed_of_its_kind() -> None:
    config = PhotometricConfig(camp_seeds=(0, 1, 2), training_seeds=(5, 6))
    assert run_seeds("camp", config) == (0, 1, 2)
    assert run_seeds("s2camp", config) == (5, 6)
    assert run_seeds("so3xr3", config) == (5, 6)


def test_by_default_only_camp_repeats_and_nerfstudio_keeps_its_own_seed() -> None:
    config = PhotometricConfig()
    assert config.training_seeds == (42,)  # nerfstudio's MachineConfig.seed default
    assert run_seeds("s2camp", config) == (42,)


def test_run_folders_are_named_after_the_seed_only_where_a_variant_repeats() -> None:
    single = PhotometricConfig(training_seeds=(42,))
    repeated = PhotometricConfig(training_seeds=(1, 2))
    assert run_timestamp("s2camp", 42, single) == "s2camp"
    assert run_timestamp("camp", 0, single) == "camp-seed0"
    assert run_timestamp("s2camp", 2, repeated) == "s2camp-seed2"
    assert run_timestamp("camp", 1, repeated) == "camp-seed1"


def test_the_sfm_tier_passes_the_seed_to_ns_train() -> None:
    arguments = variant_arguments("s2camp-per-camera", 3, PhotometricConfig())
    assert arguments[:2] == ["--machine.seed", "3"]
    arguments = variant_arguments("camp", 1, PhotometricConfig())
    assert arguments[:2] == ["--pipeline.model.camera-optimizer.sampling.seed", "1"]


def _result(rot: float, pos: float, focal: float, psnr: float) -> dict:
    final = {"iteration": 20, "rot_err": rot, "pos_err": pos, "focal_err": focal}
    return {
        "start": {"rot_err": 0.04, "pos_err": 0.05, "focal_err": 8.0},
        "history": [{"iteration": 10, "rot_err": 0.03, "pos_err": 0.04, "focal_err": 3.0}, final],
        "final": final,
        "psnr": psnr,
        "ssim": 0.5,
        "lpips": float("nan"),
        "psnr_unaligned": psnr - 1.0,
        "sec_per_iter": 0.25,
        "eval_views": 2,
    }


def _summary() -> list[dict]:
    runs = [TrainedRun("narrow", "s2camp-per-camera", Path(f"s{seed}")) for seed in range(3)]
    results = [_result(0.01, 0.02, 0.3, 20.0), _result(0.03, 0.01, 0.9, 21.0), _result(0.02, 0.03, 0.6, 22.0)]
    rows, histories = summarize_scene("narrow", list(zip(runs, results, strict=True)))
    assert len(rows) == 1 and set(histories) == {("narrow", "s2camp-per-camera")}
    return rows


def test_repeated_runs_are_averaged_and_their_range_kept() -> None:
    (row,) = _summary()
    assert row["seeds"] == 3 and row["intrinsics"] == "per-camera"
    assert abs(row["focal_err"] - 0.6) < 1e-12 and abs(row["psnr"] - 21.0) < 1e-12
    assert (row["focal_err_min"], row["focal_err_max"]) == (0.3, 0.9)
    assert (row["rot_err_min"], row["rot_err_max"]) == (0.01, 0.03)
    assert (row["pos_err_min"], row["pos_err_max"]) == (0.01, 0.03)
    # the first checkpoint's mean focal error (3.0) is under half the start (8.0): reached at iteration 10
    assert row["iters_to_half_focal_err"] == 10.0


def test_the_report_lists_the_range_of_repeated_variants_only() -> None:
    rows = _summary()
    config = RecoveryConfig(photometric=PhotometricConfig(training_seeds=(0, 1, 2)))
    text = "\n".join(_tier2_section(rows, config))
    assert "| narrow | s2camp-per-camera | 3 | 0.01 - 0.03 | 0.01 - 0.03 | 0.3 - 0.9 |" in text
    assert "nerfstudio seeds [0, 1, 2]" in text
    single = [dict(rows[0], seeds=1)]
    assert "Run-to-run range" not in "\n".join(_tier2_section(single, config))


def test_the_sfm_report_lists_the_range_of_repeated_variants_and_not_the_start() -> None:
    from s2camp_ns.benchmarks.recovery import _tier3_section
    from s2camp_ns.benchmarks.recovery_sfm import SfmRecoveryConfig

    (row,) = _summary()
    row = dict(row, tier=3, scene="sfm-wide")
    start = {"tier": 3, "scene": "sfm-wide", "variant": "start", "seeds": 1, "intrinsics": "per-camera"}
    photometric = PhotometricConfig(training_seeds=(0, 1, 2))
    config = RecoveryConfig(tiers=(3,), sfm=SfmRecoveryConfig(scenes=("sfm-wide",), photometric=photometric))
    text = "\n".join(_tier3_section([start, row], [], config))
    assert "| sfm-wide | s2camp-per-camera | 3 | 0.01 - 0.03 | 0.01 - 0.03 | 0.3 - 0.9 |" in text
    assert "| sfm-wide | start | 1 |" not in text
