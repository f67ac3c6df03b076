"""``s2camp-bench splat``: the ns-train commands, the regime and the summary (no training), and the ``--quick`` run
end to end (marked slow)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from hang_guard import HANG_GUARD_S

from s2camp_bench.grid import RunSpec, run_specs
from s2camp_bench.splat_bench import (
    RUNNABLE_VARIANTS,
    SCENES,
    STARTS,
    VARIANTS,
    SplatBenchConfig,
    add_quarter_images,
    passes,
    train_command,
)
from s2camp_bench.splat_report import summarize
from s2camp_bench.train_commands import SMALL_MODEL, ns_train_arguments, ns_train_base_arguments


def _option(command: list[str], name: str) -> str:
    return command[command.index(name) + 1]


def _command(variant: str, start: str, **config) -> list[str]:
    truth = Path("truth") if start == "sfm" else None
    spec = RunSpec("splat-ring", start, variant, 2)
    return train_command(spec, Path("scene"), Path("runs"), SplatBenchConfig(**config), truth)


@pytest.mark.parametrize("start", STARTS)
@pytest.mark.parametrize("variant", RUNNABLE_VARIANTS)
def test_splat_runs_get_no_nerfacto_options_and_only_their_variants_camera_options(variant: str, start: str) -> None:
    command = _command(variant, start, iterations=900)
    assert command[1] == ("s2camp-splat-so3xr3" if variant == "s2camp-splat-so3xr3" else "s2camp-splat")
    # nerfacto's model size and ray batch: splatfacto has no such options (tyro would refuse them).
    assert not set(SMALL_MODEL[::2]) & set(command)
    assert "--pipeline.model.log2-hashmap-size" not in command
    assert not [arg for arg in command if arg.startswith("--pipeline.datamanager.")]
    assert _option(command, "--max-num-iterations") == "900"
    assert _option(command, "--machine.device-type") == "cpu"
    assert _option(command, "--machine.seed") == "2"
    assert _option(command, "--pipeline.model.camera-error-every") == "0"
    camera_options = [arg for arg in command if arg.startswith("--pipeline.model.camera-optimizer.")]
    optimizer = "--pipeline.model.camera-optimizer"
    prior = f"{optimizer}.track-prior"
    expected_options = {
        "splat-off": {f"{optimizer}.mode": "off"},
        "s2camp-splat-tracks": {f"{optimizer}.photometric": "False", prior: "True"},
        "s2camp-splat-photometric": {prior: "False"},
    }
    assert {arg: _option(command, arg) for arg in camera_options} == expected_options.get(variant, {})
    # The scaled schedule: 900 of splatfacto's 30000 steps = 3 %.
    assert _option(command, "--pipeline.model.resolution-schedule") == "90"  # 3000 x 0.03
    assert _option(command, "--pipeline.model.sh-degree-interval") == "30"  # 1000 x 0.03
    assert _option(command, "--optimizers.means.scheduler.max-steps") == "900"
    assert _option(command, "--pipeline.model.stop-split-at") == "0"  # densification off
    camera_schedule = [arg for arg in command if arg.startswith("--optimizers.camera-opt.")]
    if variant == "s2camp-splat-so3xr3":  # splatfacto's absolute camera schedule, compressed like the rest
        assert _option(command, "--optimizers.camera-opt.scheduler.warmup-steps") == "30"  # 1000 x 0.03
        assert _option(command, "--optimizers.camera-opt.scheduler.max-steps") == "900"
    elif variant != "splat-off":  # S2CamP: fractions of the run already, except the 2500-step warm-up floor
        assert camera_schedule == ["--optimizers.camera-opt.scheduler.min-warmup-steps"]
        assert _option(command, "--optimizers.camera-opt.scheduler.min-warmup-steps") == "75"  # 2500 x 0.03
    else:  # no camera refinement
        assert camera_schedule == []
    subcommand = "s2camp-bench-data" if start == "sfm" else "s2camp-data"  # the benchmarks' parser: true cameras
    assert [arg for arg in command if arg.startswith("s2camp-") and arg.endswith("-data")] == [subcommand]
    tail = command[command.index(subcommand) :]
    assert _option(tail, "--downscale-factor") == "4"  # images_4: 64x48
    assert ("--perturbation.enabled" in tail) == (start == "perturbed")
    if start == "perturbed":
        assert _option(tail, "--perturbation.seed") == str(SCENES["splat-ring"].perturbation_seed)
    assert ("--reference-model" in tail) == (start == "sfm")
    # Every start but sfm trains with tracks made from its images, never the generated scene's exact projections.
    assert (tail[-2:] == ["--image-tracks", "always"]) == (start != "sfm")
    if start == "sfm":
        assert _option(tail, "--reference-model") == str(Path("truth") / "sparse" / "0")


def test_an_sfm_start_without_the_true_scene_is_refused() -> None:
    spec = RunSpec("splat-ring", "sfm", "s2camp-splat", 0)
    with pytest.raises(ValueError, match="sfm start needs the generated scene"):
        train_command(spec, Path("scene"), Path("runs"), SplatBenchConfig())


def test_nerfacto_commands_keep_their_batch_and_model_size() -> None:
    arguments = ("s2camp", Path("scene"), Path("runs"), "experiment", "stamp", 20, 20)
    nerfacto = ns_train_arguments(*arguments, 512)
    assert nerfacto == [
        *ns_train_base_arguments(*arguments),
        "--pipeline.datamanager.train-num-rays-per-batch", "512",
        *SMALL_MODEL,
    ]  # fmt: skip
    assert "--pipeline.model.log2-hashmap-size" in nerfacto


def test_quarter_images_are_the_2x2_box_average_of_the_half_size_ones(tmp_path: Path) -> None:
    import numpy as np
    from PIL import Image

    (tmp_path / "images_2").mkdir()
    pixels = np.zeros((4, 6, 3), dtype=np.uint8)
    pixels[:2, :2] = [[[10, 20, 30], [20, 20, 30]], [[30, 20, 31], [40, 20, 30]]]  # block means 25, 20, 30.25
    pixels[2:, 4:] = 255
    Image.fromarray(pixels).save(tmp_path / "images_2" / "frame_00000.png")
    add_quarter_images(tmp_path)
    quarter = np.asarray(Image.open(tmp_path / "images_4" / "frame_00000.png"))
    assert quarter.shape == (2, 3, 3)
    assert quarter[0, 0].tolist() == [25, 20, 30] and quarter[1, 2].tolist() == [255, 255, 255]
    assert int(quarter.sum()) == 25 + 20 + 30 + 3 * 255
    Image.fromarray(np.zeros((3, 4, 3), dtype=np.uint8)).save(tmp_path / "images_2" / "frame_00001.png")
    with pytest.raises(ValueError, match="frame_00001.png is 4x3 px"):
        add_quarter_images(tmp_path)


def test_passes_count_whole_training_images_per_step() -> None:
    # 24 images, every 8th (0, 8, 16) held out: 21 training images, one rendered whole per step.
    assert passes(1050, "splat-ring") == pytest.approx(50.0)
    assert SplatBenchConfig().iterations / 21 > 20  # the default regime: tens of passes


def test_config_is_validated_by_name() -> None:
    with pytest.raises(ValueError, match="variants"):
        SplatBenchConfig(variants=("s2camp",)).validate()
    with pytest.raises(ValueError, match="starts"):
        SplatBenchConfig(starts=("phone",)).validate()
    with pytest.raises(ValueError, match="iterations"):
        SplatBenchConfig(iterations=0).validate()
    quick = SplatBenchConfig(quick=True).effective()
    assert quick.variants == VARIANTS and quick.starts == ("perturbed",) and quick.seeds == 1
    assert len(run_specs(quick)) == 3
    assert SplatBenchConfig(seeds=2, workers=1).command() == "s2camp-bench splat --seeds 2 --workers 1"
    assert SplatBenchConfig(quick=True).command() == "s2camp-bench splat --quick"


def _row(start: str, variant: str, seed: int, **values) -> dict:
    row = {"scene": "splat-ring", "start": start, "variant": variant, "seed": seed, "passes": 47.6}
    row |= {key: 1.0 for key in ("rot_err", "pos_err", "focal_err", "drift_px", "psnr", "ssim", "psnr_unaligned")}
    row |= {f"start_{key}": 2.0 for key in ("rot_err", "pos_err", "focal_err", "drift_px")}
    row |= {"sec_per_iter": 0.2, "gaussians": 2000}
    return row | values


def test_summary_gives_removed_fractions_changes_psnr_differences_and_time_ratios() -> None:
    rows = [
        _row("perturbed", "s2camp-splat-so3xr3", 0, psnr=20.0, focal_err=2.0, sec_per_iter=0.20),
        _row("perturbed", "s2camp-splat-so3xr3", 1, psnr=22.0, focal_err=2.0, sec_per_iter=0.30),
        _row("perturbed", "s2camp-splat", 0, psnr=23.0, focal_err=0.4, sec_per_iter=0.30),
        _row("perturbed", "s2camp-splat", 1, psnr=24.0, focal_err=0.6, sec_per_iter=0.35),
        _row("perturbed", "splat-off", 0, psnr=19.0, focal_err=2.0),
        _row("accurate", "s2camp-splat", 0, rot_err=0.3, start_rot_err=0.1),
    ]
    summary = {(e["start"], e["variant"]): e for e in summarize(rows)}
    s2camp = summary[("perturbed", "s2camp-splat")]
    assert s2camp["focal_err"].mean == pytest.approx(0.5) and s2camp["focal_err"].width == pytest.approx(0.2)
    assert s2camp["removed_focal_err"] == pytest.approx(0.75)  # 1 - 0.5 / 2
    assert summary[("perturbed", "s2camp-splat-so3xr3")]["removed_focal_err"] == pytest.approx(0.0)
    assert s2camp["psnr_vs_so3xr3"] == pytest.approx(23.5 - 21.0)
    assert s2camp["psnr_vs_off"] == pytest.approx(23.5 - 19.0)
    assert s2camp["time_ratio"] == pytest.approx(0.325 / 0.25)
    accurate = summary[("accurate", "s2camp-splat")]
    assert math.isnan(accurate["removed_rot_err"]) and accurate["change_rot_err"] == pytest.approx(0.2)
    assert math.isnan(accurate["time_ratio"]) and math.isnan(accurate["psnr_vs_so3xr3"])  # no baseline run


def test_summary_is_sorted_by_scene_start_and_variant_in_the_benchmarks_order() -> None:
    finished = [
        ("sfm", "s2camp-splat"), ("accurate", "splat-off"), ("perturbed", "s2camp-splat"), ("accurate", "s2camp-splat"),
        ("perturbed", "splat-off"), ("accurate", "s2camp-splat-so3xr3"),
    ]  # fmt: skip
    listed = [(e["start"], e["variant"]) for e in summarize([_row(start, variant, 0) for start, variant in finished])]
    assert listed == [
        ("accurate", "splat-off"), ("accurate", "s2camp-splat-so3xr3"), ("accurate", "s2camp-splat"),
        ("perturbed", "splat-off"), ("perturbed", "s2camp-splat"), ("sfm", "s2camp-splat"),
    ]  # fmt: skip


def test_time_ratios_compare_seconds_of_one_invocation_only() -> None:
    # The machine is shared: seconds per step from different invocations of the benchmark are not comparable.
    rows = [
        _row("sfm", "s2camp-splat-so3xr3", 0, sec_per_iter=0.30),  # an earlier invocation (no field: "")
        _row("sfm", "s2camp-splat-so3xr3", 1, sec_per_iter=0.04, invocation="b"),
        _row("sfm", "s2camp-splat", 0, sec_per_iter=0.05, invocation="b"),
        _row("sfm", "s2camp-splat", 1, sec_per_iter=0.06, invocation="b"),
        _row("sfm", "splat-off", 0, sec_per_iter=0.05, invocation="c"),
    ]
    summary = {(e["start"], e["variant"]): e for e in summarize(rows)}
    assert summary[("sfm", "s2camp-splat")]["time_ratio"] == pytest.approx(0.055 / 0.04)  # not over the mean 0.17
    assert math.isnan(summary[("sfm", "splat-off")]["time_ratio"])  # no baseline run in its invocation


def _bench() -> str:
    script = Path(sys.executable).with_name("s2camp-bench")
    assert script.exists(), f"s2camp-bench is not installed next to {sys.executable}: run `make venv`"
    return str(script)


@pytest.mark.slow
@pytest.mark.timeout(HANG_GUARD_S)
def test_quick_splat_benchmark_trains_the_three_variants(tmp_path: Path) -> None:
    """``s2camp-bench splat --quick``: the three variants from the CamP perturbation, one seed, a few steps."""
    result = subprocess.run(
        [_bench(), "splat", "--quick", "--json", "--output-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=HANG_GUARD_S, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    rows = json.loads(result.stdout)["rows"]
    by = {row["variant"]: row for row in rows}
    assert sorted(by) == sorted(VARIANTS) and len(rows) == 3
    for row in rows:
        assert row["start"] == "perturbed" and row["passes"] == pytest.approx(row["iterations"] / 21)
        for key in ("rot_err", "pos_err", "focal_err", "drift_px", "psnr", "ssim", "psnr_unaligned", "sec_per_iter"):
            assert isinstance(row[key], float) and math.isfinite(row[key]), (key, row)
        assert 5.0 < row["psnr"] < 60.0 and 0.0 < row["ssim"] <= 1.0, row
        assert row["sec_per_iter"] > 0.0 and row["gaussians"] > 0
        # The same CamP perturbation for every variant: about 0.4 deg and 3.4 px focal on this scene.
        assert row["start_rot_err"] == pytest.approx(by["splat-off"]["start_rot_err"])
        assert row["start_rot_err"] > 0.1 and row["start_focal_err"] > 1.0, row
    off, so3xr3, s2camp = by["splat-off"], by["s2camp-splat-so3xr3"], by["s2camp-splat"]
    for key in ("rot_err", "pos_err", "focal_err", "drift_px"):  # no refinement: the cameras end where they started
        assert off[key] == pytest.approx(off[f"start_{key}"], rel=1e-9, abs=1e-12), key
    # SO3xR3 refines the pose only; S2CamP the focal length too.
    assert so3xr3["focal_err"] == pytest.approx(so3xr3["start_focal_err"], rel=1e-9)
    assert so3xr3["rot_err"] != so3xr3["start_rot_err"]
    assert abs(s2camp["focal_err"] - s2camp["start_focal_err"]) > 1e-4
    assert s2camp["rot_err"] != s2camp["start_rot_err"]
    text = (tmp_path / "splat.md").read_text()
    assert "s2camp-bench splat --quick" in text and "passes over each training pixel" in text
    assert "time ratio vs so3xr3" in text


REPORT_FIELDS = {"iterations": 1000, "train_seconds": 1.0, "eval_seconds": 1.0, "workers": 1}
"""What a row needs beyond ``_row`` for the report: run settings and timings."""


def test_report_says_which_rows_were_rebuilt_from_logs(tmp_path: Path) -> None:
    from s2camp_bench.splat_bench import SplatBenchConfig, report

    rows = [_row("perturbed", variant, 0, **REPORT_FIELDS) for variant in ("splat-off", "s2camp-splat-so3xr3")]
    config = SplatBenchConfig(output_dir=tmp_path)
    assert "rebuilt from their run's log line" not in report(rows, config).read_text()
    rows.append(_row("perturbed", "s2camp-splat", 0, psnr_unaligned=float("nan"), reconstructed="log", **REPORT_FIELDS))
    text = " ".join(report(rows, config).read_text().split())
    assert "1 row(s) were rebuilt from their run's log line" in text


def test_report_lists_rows_of_variants_that_no_longer_run_apart(tmp_path: Path) -> None:
    from s2camp_bench.grid_report import NO_LONGER_RUN_HEADING
    from s2camp_bench.splat_bench import SplatBenchConfig, report

    rows = [_row("sfm", variant, 0, **REPORT_FIELDS) for variant in ("splat-off", "s2camp-splat")]
    config = SplatBenchConfig(output_dir=tmp_path)
    assert "no longer run" not in report(rows, config).read_text()
    rows.append(_row("sfm", "s2camp-splat-prior-rms", 0, **REPORT_FIELDS))
    with pytest.raises(ValueError, match="variants"):
        SplatBenchConfig(variants=("s2camp-splat-prior-rms",)).validate()
    results, old = report(rows, config).read_text().split(NO_LONGER_RUN_HEADING)
    assert "| sfm | s2camp-splat | 1 |" in results and "s2camp-splat-prior-rms" not in results
    assert 'docs/RESULTS.md, "Names that no longer run"' in old
    assert "| sfm | s2camp-splat-prior-rms | 1 |" in old
