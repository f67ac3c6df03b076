"""Repeated runs in the recovery benchmark's photometric tiers: which seed each run gets, how runs are named, and how
their errors are summarized (mean and range)."""

from __future__ import annotations

from pathlib import Path

from s2camp_bench.recovery import RecoveryConfig, _tier2_section
from s2camp_bench.recovery_photometric import (
    PhotometricConfig,
    TrainedRun,
    run_seeds,
    run_timestamp,
    seed_arguments,
    summarize_scene,
)
from s2camp_bench.recovery_sfm import variant_arguments


def test_every_variant_seeds_nerfstudio() -> None:
    assert seed_arguments("camp", 2) == ["--machine.seed", "2"]
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
    assert arguments[:2] == ["--machine.seed", "1"]


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
    from s2camp_bench.recovery import _tier3_section
    from s2camp_bench.recovery_sfm import SfmRecoveryConfig

    (row,) = _summary()
    row = dict(row, tier=3, scene="sfm-wide")
    start = {"tier": 3, "scene": "sfm-wide", "variant": "start", "seeds": 1, "intrinsics": "per-camera"}
    photometric = PhotometricConfig(training_seeds=(0, 1, 2))
    config = RecoveryConfig(tiers=(3,), sfm=SfmRecoveryConfig(scenes=("sfm-wide",), photometric=photometric))
    text = "\n".join(_tier3_section([start, row], [], config))
    assert "| sfm-wide | s2camp-per-camera | 3 | 0.01 - 0.03 | 0.01 - 0.03 | 0.3 - 0.9 |" in text
    assert "| sfm-wide | start | 1 |" not in text


# What each variant's ns-train run is, checked by parsing its command line with nerfstudio's own CLI (``--quick``
# trains only some of them): method, camera-optimizer settings, run length and the perturbed start.
TIER2_EXPECTED = {
    "none": ("s2camp", {"mode": "off"}),
    "so3xr3": ("s2camp-so3xr3", {"mode": "SO3xR3"}),
    "raw": ("s2camp", {"precondition": False, "refresh_every": 0, "intrinsics": "per-image"}),
    "camp": ("s2camp-camp", {"refresh_every": 0, "intrinsics": "per-image"}),
    "s2camp": ("s2camp", {"precondition": True, "refresh_every": 7, "intrinsics": "per-image"}),
    "s2camp-once": ("s2camp", {"precondition": True, "refresh_every": 0, "intrinsics": "per-image"}),
    "s2camp-per-camera": ("s2camp", {"precondition": True, "refresh_every": 7, "intrinsics": "per-camera"}),
}
TIER3_EXPECTED = {
    "none": ("s2camp", {"mode": "off"}),
    "so3xr3": ("s2camp-so3xr3", {"mode": "SO3xR3"}),
    "camp": ("s2camp-camp", {"refresh_every": 0, "intrinsics": "per-image"}),
    "s2camp-per-image": ("s2camp", {"refresh_every": 7, "intrinsics": "per-image"}),
    "s2camp-per-camera": ("s2camp", {"refresh_every": 7, "intrinsics": "per-camera"}),
}


def _parsed(command: list[str]):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    return tyro.cli(AnnotatedBaseConfigUnion, args=command[1:])


def _check_run(config, method: str, camera: dict, warm: Path) -> None:
    assert config.method_name == method
    assert config.max_num_iterations == 5 and config.load_dir == warm
    optimizer = config.pipeline.model.camera_optimizer
    if method != "s2camp-so3xr3":  # the tiers compare preconditioners: no track prior, no common-rotation removal
        assert optimizer.track_prior is False and optimizer.fix_common_rotation is False, method
    for key, value in camera.items():
        assert getattr(optimizer, key) == value, (method, key)


def test_every_tier2_variant_parses_to_its_camera_optimizer_settings() -> None:
    from s2camp_bench.recovery_geometric import VARIANTS
    from s2camp_bench.recovery_photometric import (
        METHODS,
        _variant_arguments,
        perturbation_arguments,
        variant_command,
    )

    assert set(TIER2_EXPECTED) == set(VARIANTS)
    config = PhotometricConfig(iterations=5, refresh_every=7)
    warm = Path("/tmp/warm")
    for variant, (method, camera) in TIER2_EXPECTED.items():
        command = variant_command(
            Path("/tmp/scene"), Path("/tmp/work"), "s", warm, METHODS[variant], "ts",
            _variant_arguments(variant, 0, config), perturbation_arguments(config), config,
        )  # fmt: skip
        parsed = _parsed(command)
        _check_run(parsed, method, camera, warm)
        assert parsed.pipeline.datamanager.dataparser.perturbation.enabled, variant


def test_every_tier3_variant_parses_to_its_camera_optimizer_settings() -> None:
    from ns_train_parse import parse_ns_train

    from s2camp_bench.recovery_photometric import variant_command
    from s2camp_bench.recovery_sfm import METHODS, SFM_VARIANTS, dataparser_arguments

    assert set(TIER3_EXPECTED) == set(SFM_VARIANTS)
    config = PhotometricConfig(iterations=5, refresh_every=7)
    warm = Path("/tmp/warm")
    commands = [
        variant_command(
            Path("/tmp/sfm"),
            Path("/tmp/work"),
            "s",
            warm,
            METHODS[variant],
            "ts",
            variant_arguments(variant, 0, config),
            dataparser_arguments(Path("/tmp/truth")),
            config,
        )  # fmt: skip
        for variant in TIER3_EXPECTED
    ]
    # s2camp-bench-data parses only where the benchmarks register it (tests/ns_train_parse.py).
    for (variant, (method, camera)), parsed in zip(TIER3_EXPECTED.items(), parse_ns_train(commands), strict=True):
        _check_run(parsed, method, camera, warm)
        reference = parsed.pipeline.datamanager.dataparser.reference_model
        assert reference == Path("/tmp/truth/sparse/0"), variant


def test_quick_trains_a_subset_and_every_variant_of_tier_1() -> None:
    config = RecoveryConfig(quick=True).effective()
    assert config.photometric_variants() == ("none", "so3xr3", "s2camp")
    assert config.sfm.variants == ("none", "s2camp-per-camera")
    assert len(config.variants) == 7  # tier 1 (geometric, no ns-train) runs every variant
    assert RecoveryConfig().photometric_variants() == config.variants
