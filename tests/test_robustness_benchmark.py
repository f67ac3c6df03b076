"""The pieces of ``s2camp-bench robustness`` that need no training: commands, scenes, summary (the quick ns-train run
is in test_benchmarks.py)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from s2camp_bench.grid import RunSpec, focal_for_fov, run_specs
from s2camp_bench.robustness import SCENES, STARTS, VARIANTS, RobustnessConfig, train_command
from s2camp_bench.robustness_report import summarize


def _option(command: list[str], name: str) -> str:
    return command[command.index(name) + 1]


def _dataparser_index(command: list[str]) -> int:
    """Where the data parser's subcommand starts: s2camp-data, or the benchmarks' s2camp-bench-data."""
    (index,) = [i for i, arg in enumerate(command) if arg in ("s2camp-data", "s2camp-bench-data")]
    return index


@pytest.mark.parametrize("start", ["accurate", "perturbed", "phone"])
@pytest.mark.parametrize("variant", VARIANTS)
def test_every_run_trains_with_the_method_defaults_plus_the_cpu_settings(variant: str, start: str) -> None:
    config = RobustnessConfig(iterations=123)
    command = train_command(RunSpec("regime-wide", start, variant, 2), Path("scene"), Path("runs"), config)
    methods = {"s2camp-so3xr3": "s2camp-so3xr3", "s2camp-camp": "s2camp-camp", "s2camp-camp-prior": "s2camp-camp"}
    assert command[1] == methods.get(variant, "s2camp")
    assert _option(command, "--max-num-iterations") == "123"
    assert _option(command, "--machine.seed") == "2"
    assert _option(command, "--machine.device-type") == "cpu"
    # No camera learning rate, schedule or sampling option: the method's defaults.
    assert not [arg for arg in command if arg.startswith("--optimizers.")]
    camera_options = {
        arg: command[index + 1]
        for index, arg in enumerate(command)
        if arg.startswith("--pipeline.model.camera-optimizer.")
    }
    rotation = "--pipeline.model.camera-optimizer.fix-common-rotation"
    prior = "--pipeline.model.camera-optimizer.track-prior"
    # Every s2camp variant but the default states both candidate options, so it keeps its meaning when a default
    # changes; "s2camp" and the baselines take the method's own defaults.
    photometric = "--pipeline.model.camera-optimizer.photometric"
    precondition = "--pipeline.model.camera-optimizer.precondition"
    expected_options = {
        "off": {"--pipeline.model.camera-optimizer.mode": "off"},
        "tracks": {photometric: "False", rotation: "True", prior: "True"},
        "s2camp-photometric": {rotation: "True", prior: "False"},
        "s2camp-camp-prior": {rotation: "True", prior: "True"},
        "s2camp-identity-prior": {precondition: "False", rotation: "True", prior: "True"},
    }  # fmt: skip
    assert camera_options == expected_options.get(variant, {})
    tail = command[_dataparser_index(command) :]
    seed = str(SCENES["regime-wide"].perturbation_seed)
    # Every start but sfm trains with tracks made from its images, never the generated scene's exact projections.
    if start == "accurate":
        assert tail == ["s2camp-data", "--downscale-factor", "2", "--image-tracks", "always"]
    elif start == "perturbed":
        assert tail == ["s2camp-data", "--downscale-factor", "2", "--perturbation.enabled", "True",
                        "--perturbation.seed", seed, "--image-tracks", "always"]  # fmt: skip
    else:  # phone: CamP's steps off, the VIO drift on, one draw per run seed (scene seed + run seed 2), own tracks
        phone_seed = str(SCENES["regime-wide"].perturbation_seed + 2)
        assert tail == [
            "s2camp-bench-data", "--downscale-factor", "2", "--perturbation.enabled", "True", "--perturbation.seed",
            phone_seed, "--perturbation.sigma-position", "0.0", "--perturbation.sigma-look-at", "0.0",
            "--perturbation.sigma-dolly-z", "0.0", "--perturbation.sigma-focal-length", "0.0",
            "--drift.enabled", "True", "--drift.position-drift", "0.01",
            "--drift.yaw-drift-deg", "1.5", "--drift.tilt-deg", "0.3",
            "--drift.focal-error", "0.015", "--image-tracks", "always",
        ]  # fmt: skip
    assert "--save-only-latest-checkpoint" not in command


def test_phone_and_sfm_commands_parse_to_the_benchmarks_data_parser() -> None:
    """ns-train's own parse of the two starts that need ``s2camp-bench-data`` (in the benchmarks' environment): the
    phone start's drift after CamP's steps with CamP's sigmas zero, the sfm start's truth."""
    from ns_train_parse import parse_ns_train

    from s2camp_bench.data_parser import BenchDataParserConfig
    from s2camp_bench.phone_drift import DriftConfig

    config = RobustnessConfig(iterations=10)
    phone = train_command(RunSpec("regime-wide", "phone", "s2camp", 1), Path("scene"), Path("runs"), config)
    sfm = train_command(RunSpec("regime-wide", "sfm", "s2camp", 1), Path("sfm"), Path("runs"), config, Path("truth"))
    parsed = [config.pipeline.datamanager.dataparser for config in parse_ns_train([phone, sfm])]
    assert all(isinstance(dataparser, BenchDataParserConfig) for dataparser in parsed)
    perturbation = parsed[0].perturbation
    assert perturbation.enabled and perturbation.seed == SCENES["regime-wide"].perturbation_seed + 1
    sigmas = (perturbation.sigma_position, perturbation.sigma_look_at, perturbation.sigma_dolly_z,
              perturbation.sigma_focal_length)  # fmt: skip
    assert sigmas == (0.0, 0.0, 0.0, 0.0)
    assert parsed[0].drift == DriftConfig(True, 0.01, 1.5, 0.3, 0.015) and parsed[0].reference_model is None
    assert parsed[1].reference_model == Path("truth") / "sparse" / "0"
    assert not parsed[1].perturbation.enabled and not parsed[1].drift.enabled


def test_sfm_start_trains_on_the_sfm_scene_against_the_generated_cameras() -> None:
    config = RobustnessConfig(iterations=3000)
    spec = RunSpec("regime-wide", "sfm", "s2camp", 0)
    command = train_command(spec, Path("sfm-scene"), Path("runs"), config, truth=Path("truth"))
    assert _option(command, "--data") == "sfm-scene"
    assert command[command.index("s2camp-bench-data") :] == [
        "s2camp-bench-data", "--downscale-factor", "2", "--reference-model", str(Path("truth") / "sparse" / "0"),
    ]  # fmt: skip
    assert _option(command, "--steps-per-save") == "3000"  # one checkpoint, evaluated, then removed


def test_regime_scene_sees_each_training_pixel_one_and_a_half_times() -> None:
    preset = SCENES["regime-wide"]
    # 56 images, every 8th held out (7): 49 training images of 160 x 120 (trained at half of 320 x 240).
    assert preset.training_pixels == 49 * 160 * 120
    config = RobustnessConfig()
    assert (config.scenes, config.starts, config.iterations) == (("regime-wide",), STARTS, 3000)
    assert STARTS == ("accurate", "perturbed", "sfm", "phone")
    assert config.iterations * config.rays_per_batch / preset.training_pixels == pytest.approx(1536000 / 940800)
    # Each evidence alone and the prior under each P, beside refinement off and the baselines.
    assert config.variants == (
        "off", "s2camp-so3xr3", "s2camp-camp", "s2camp", "tracks", "s2camp-photometric", "s2camp-camp-prior",
        "s2camp-identity-prior",
    )  # fmt: skip


def test_the_command_names_the_preset_and_what_the_command_line_chose() -> None:
    config = RobustnessConfig(starts=("sfm",), variants=("off",), seeds=1)
    assert config.command() == "s2camp-bench robustness --preset regime --starts sfm --variants off --seeds 1"
    assert RobustnessConfig(quick=True).command() == "s2camp-bench robustness --quick"
    quick = RobustnessConfig(quick=True).effective()
    assert (quick.scenes, quick.starts, quick.variants) == (("small-narrow-far",), ("accurate", "perturbed"),
                                                            ("off", "s2camp"))  # fmt: skip
    assert (quick.iterations, quick.seeds, quick.alignment.steps, quick.alignment.rays) == (20, 1, 10, 64)


def test_the_scenes_have_the_field_of_view_they_state_and_a_perturbation_seed_each() -> None:
    from s2camp_bench.robustness import RETIRED_SCENES

    for preset in (*SCENES.values(), *RETIRED_SCENES.values()):
        # The focal length written into the scene gives the stated field of view.
        fov = 2.0 * math.degrees(math.atan(0.5 * preset.scene.width / preset.scene.focal))
        assert fov == pytest.approx(preset.fov_degrees, abs=1e-9)
    pairs = {(preset.scene.seed, preset.perturbation_seed) for preset in SCENES.values()}
    assert len(pairs) == len({seed for seed, _ in pairs}) == len({seed for _, seed in pairs})
    low, full = SCENES["regime-wide"], RETIRED_SCENES["regime-wide-full"]
    assert full.scene == low.scene and full.perturbation_seed == low.perturbation_seed
    assert full.training_pixels == 4 * low.training_pixels == 49 * 320 * 240


def test_focal_for_fov_of_a_right_angle_is_half_the_width() -> None:
    assert focal_for_fov(100, 90.0) == pytest.approx(50.0, abs=1e-12)


def test_seeds_are_the_outermost_loop_of_the_runs() -> None:
    specs = run_specs(RobustnessConfig(seeds=2))
    assert len(specs) == 2 * 4 * 8  # seeds x starts x variants
    assert [spec.seed for spec in specs] == [0] * 32 + [1] * 32


def test_a_later_session_adds_seeds_from_first_seed() -> None:
    config = RobustnessConfig(starts=("sfm",), variants=("s2camp",), seeds=2, first_seed=1)
    assert [spec.seed for spec in run_specs(config)] == [1, 2]
    assert "--first-seed 1" in config.command()
    with pytest.raises(ValueError, match="first_seed must be >= 0, got -1"):
        RobustnessConfig(first_seed=-1).validate()


def test_bad_choices_are_rejected_with_the_parameter_name() -> None:
    with pytest.raises(ValueError, match="variants"):
        RobustnessConfig(variants=("s2camp", "nope")).validate()
    with pytest.raises(ValueError, match="seeds"):
        RobustnessConfig(seeds=0).validate()
    with pytest.raises(ValueError, match="starts"):
        RobustnessConfig(starts=()).validate()
    with pytest.raises(ValueError, match="preset"):
        RobustnessConfig(preset="fast").validate()  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="starts"):
        RobustnessConfig(starts=("accurate-untracked",)).validate()  # committed rows only


def _row(start: str, variant: str, seed: int, psnr: float, rot: float, start_rot: float) -> dict:
    row = {"scene": "s", "start": start, "variant": variant, "seed": seed, "psnr": psnr, "ssim": 0.5}
    row |= {"psnr_unaligned": psnr - 0.25, "passes": 1.5}
    row |= {"rot_err": rot, "pos_err": 0.0, "focal_err": 0.0, "drift_px": 2.0 * rot}
    row |= {"start_rot_err": start_rot, "start_pos_err": 0.0, "start_focal_err": 0.0, "start_drift_px": 2 * start_rot}
    return row


def test_summary_spread_difference_against_off_and_removed_start_error() -> None:
    rows = [_row("perturbed", "off", seed, 20.0 + seed, 1.0, 1.0) for seed in range(3)]
    rows += [_row("perturbed", "s2camp", seed, 20.5 + seed, 0.2 * (seed + 1), 1.0) for seed in range(3)]
    rows += [_row("accurate", "off", seed, 25.0 + 0.1 * seed, 0.0, 0.0) for seed in range(3)]
    rows += [_row("accurate", "s2camp", seed, 24.0 + 0.1 * seed, 0.1, 0.0) for seed in range(3)]
    summary = {(entry["start"], entry["variant"]): entry for entry in summarize(rows)}
    s2camp = summary[("perturbed", "s2camp")]
    assert (s2camp["psnr"].mean, s2camp["psnr"].low, s2camp["psnr"].high) == pytest.approx((21.5, 20.5, 22.5))
    # +0.5 dB against seed ranges of 2 dB: no difference.
    assert s2camp["psnr_vs_off"] == pytest.approx(0.5)
    assert s2camp["psnr_vs_off_label"] == "+0.50 dB (no difference)"
    # Final rotation errors 0.2, 0.4, 0.6 from 1.0: 60 % of the start error removed (drift alike).
    assert s2camp["removed_rot_err"] == pytest.approx(0.6)
    assert s2camp["removed_drift_px"] == pytest.approx(0.6)
    assert summary[("perturbed", "off")]["removed_rot_err"] == pytest.approx(0.0)
    # -1 dB against seed ranges of 0.2 dB: a difference; no removed fraction from an accurate start.
    accurate = summary[("accurate", "s2camp")]
    assert accurate["psnr_vs_off_label"].startswith("-1.00 dB (beyond")
    assert math.isnan(accurate["removed_rot_err"])
    assert summary[("accurate", "off")]["psnr_vs_off_label"] == ""


def test_a_seed_run_twice_is_counted_as_a_run_and_named(tmp_path: Path) -> None:
    from s2camp_bench.robustness import report

    extra = {"scene": "regime-wide", "train_seconds": 1.0, "iterations": 3000, "eval_seconds": 1.0, "sec_per_iter": 0.5}
    rows = [_row("phone", "off", seed, 23.0 + seed, 1.0, 1.0) | extra for seed in (0, 2, 2)]
    rows += [_row("phone", "s2camp", seed, 26.0, 0.1, 1.0) | extra for seed in (0, 1, 2)]
    text = report(rows, RobustnessConfig(output_dir=tmp_path)).read_text()
    assert "| regime-wide | phone | off | 3 runs, 2 seeds (seed 2 x2) | 1.50 |" in text
    assert "| regime-wide | phone | s2camp | 3 | 1.50 |" in text


def test_sfm_rows_of_different_reconstructions_are_different_starts() -> None:
    # pycolmap's builds differ between work folders: rows that started from another build are summarized apart and
    # compared with refinement off from their own build only; phone seeds, each its own draw, stay one row.
    rows = [_row("sfm", "off", seed, 25.0 + 0.1 * seed, 0.115, 0.115) for seed in range(2)]
    rows += [_row("sfm", "s2camp", seed, 25.0, 0.11, 0.115) for seed in range(2)]
    rows += [_row("sfm", "s2camp", seed, 24.0, 0.129, 0.133) for seed in range(2)]
    rows += [_row("phone", "s2camp", seed, 26.0, 0.1, 1.0 + seed) for seed in range(3)]
    summary = summarize(rows)
    sfm = {entry["start_rot_err"]: entry for entry in summary if entry["start"] == "sfm" and entry["variant"] != "off"}
    assert sorted(sfm) == [0.115, 0.133] and [sfm[0.115]["seeds"], sfm[0.133]["seeds"]] == [2, 2]
    assert sfm[0.115]["rot_err"].mean == pytest.approx(0.11) and sfm[0.133]["rot_err"].mean == pytest.approx(0.129)
    assert sfm[0.115]["psnr_vs_off_label"] == "-0.05 dB (no difference)"
    assert sfm[0.133]["psnr_vs_off_label"] == ""  # no refinement off from that build
    assert [entry["seeds"] for entry in summary if entry["start"] == "phone"] == [3]


def test_rows_of_different_passes_per_pixel_are_summarized_apart() -> None:
    # More rays per step (or more steps) is another regime: its seeds are not pooled with the default's, and its PSNR
    # compares with refinement off at its own passes only.
    rows = [_row("perturbed", "off", seed, 25.0, 1.0, 1.0) for seed in range(2)]
    rows += [_row("perturbed", "s2camp", seed, 25.5, 0.2, 1.0) for seed in range(2)]
    rows += [_row("perturbed", "s2camp", 0, 27.0, 0.1, 1.0) | {"passes": 6.0}]
    summary = {(entry["variant"], entry["passes"]): entry for entry in summarize(rows)}
    assert sorted(summary) == [("off", 1.5), ("s2camp", 1.5), ("s2camp", 6.0)]
    assert summary[("s2camp", 1.5)]["seeds"] == 2 and summary[("s2camp", 1.5)]["rot_err"].mean == pytest.approx(0.2)
    assert summary[("s2camp", 6.0)]["seeds"] == 1 and summary[("s2camp", 6.0)]["rot_err"].mean == pytest.approx(0.1)
    assert summary[("s2camp", 1.5)]["psnr_vs_off"] == pytest.approx(0.5)
    assert math.isnan(summary[("s2camp", 6.0)]["psnr_vs_off"])  # no refinement off at 6 passes


def test_the_untracked_true_cameras_compare_with_refinement_off_from_the_tracked_ones() -> None:
    # Refinement off never reads the tracks: its rows from the true cameras are the untracked start's reference.
    rows = [_row("accurate", "off", seed, 25.0 + 0.1 * seed, 0.0, 0.0) for seed in range(2)]
    rows += [_row("accurate-untracked", "s2camp", seed, 24.0 + 0.1 * seed, 0.1, 0.0) for seed in range(2)]
    summary = {(entry["start"], entry["variant"]): entry for entry in summarize(rows)}
    untracked = summary[("accurate-untracked", "s2camp")]
    assert untracked["psnr_vs_off"] == pytest.approx(-1.0)
    assert untracked["psnr_vs_off_label"] == "-1.00 dB (beyond the seed range 0.10)"


def test_regime_report_gives_passes_unaligned_psnr_and_the_camera_path(tmp_path: Path) -> None:
    from s2camp_bench.robustness import report
    from s2camp_bench.robustness_report import TRACE_COLUMNS

    rows = [
        _row("sfm", variant, seed, psnr, rot, 0.1)
        | {
            "scene": "regime-wide",
            "train_seconds": 1.0,
            "iterations": 3000,
            "eval_seconds": 1.0,
            "sec_per_iter": 0.5,
        }
        for variant, psnr, rot in (("off", 20.0, 0.1), ("s2camp", 21.0, 0.3))
        for seed in (0, 1)
    ]
    rows[-1]["trace"] = [dict.fromkeys(TRACE_COLUMNS, 0.5) | {"step": 250}, dict.fromkeys(TRACE_COLUMNS, 0.25)]
    config = RobustnessConfig(output_dir=tmp_path)
    path = report(rows, config)
    assert path == tmp_path / "regime.md"
    text = path.read_text()
    assert f"Regenerate with `s2camp-bench robustness --preset regime --output-dir {tmp_path}`." in text
    assert "| regime-wide | sfm | s2camp | 2 | 1.50 | 0.1 / 0 / 0 / 0.2 | 0.3 [0.3, 0.3] |" in text
    assert "20.8" in text  # the unaligned PSNR of s2camp (21 - 0.25)
    assert "### Camera path: regime-wide, sfm start, s2camp, seed 1" in text
    assert "| 250 | 0.5 |" in text and "| 0.25 | 0.25 |" in text


def test_report_rows_are_sorted_by_scene_start_and_variant_in_the_benchmarks_order(tmp_path: Path) -> None:
    """Rows arrive in the order runs finished; the report lists them by scene, start and variant as ``SCENES``,
    ``STARTS`` and the variants are listed (names no longer run last, alphabetically), then by passes; the traced
    runs by seed."""
    from s2camp_bench.robustness import report
    from s2camp_bench.robustness_report import TRACE_COLUMNS

    extra = {"train_seconds": 1.0, "iterations": 3000, "eval_seconds": 1.0, "sec_per_iter": 0.5}
    finished = [
        ("regime-wide", "sfm", "s2camp"), ("regime-wide", "perturbed", "tracks"), ("regime-wide", "sfm", "off"),
        ("regime-wide-full", "perturbed", "off"), ("regime-wide", "accurate", "s2camp-zz-old"),
        ("regime-wide", "accurate", "s2camp"), ("regime-wide", "perturbed", "off"), ("regime-wide", "accurate", "off"),
        ("regime-wide", "accurate", "s2camp-aa-old"),
    ]  # fmt: skip
    rows = [_row(start, variant, 0, 20.0, 0.1, 0.1) | extra | {"scene": scene} for scene, start, variant in finished]
    rows.append(_row("perturbed", "off", 0, 20.0, 0.1, 0.1) | extra | {"scene": "regime-wide", "passes": 0.5})
    for seed in (2, 1):
        trace = [dict.fromkeys(TRACE_COLUMNS, 0.5)]
        rows.append(_row("sfm", "s2camp", seed, 20.0, 0.1, 0.1) | extra | {"scene": "regime-wide", "trace": trace})
    listed = [(e["scene"], e["start"], e["variant"], e["passes_key"]) for e in summarize(rows)]
    assert listed == [
        ("regime-wide", "accurate", "off", "1.5"), ("regime-wide", "accurate", "s2camp", "1.5"),
        ("regime-wide", "accurate", "s2camp-aa-old", "1.5"), ("regime-wide", "accurate", "s2camp-zz-old", "1.5"),
        ("regime-wide", "perturbed", "off", "0.5"), ("regime-wide", "perturbed", "off", "1.5"),
        ("regime-wide", "perturbed", "tracks", "1.5"), ("regime-wide", "sfm", "off", "1.5"),
        ("regime-wide", "sfm", "s2camp", "1.5"), ("regime-wide-full", "perturbed", "off", "1.5"),
    ]  # fmt: skip
    text = report(rows, RobustnessConfig(output_dir=tmp_path)).read_text()
    table = [line.split(" | ")[:3] for line in text.splitlines() if line.startswith("| regime-wide")]
    order = [(scene.lstrip("| "), start, variant) for scene, start, variant in table if start != "56"]
    # The results, then the rows of names no longer run.
    old = [("regime-wide", "accurate", "s2camp-aa-old"), ("regime-wide", "accurate", "s2camp-zz-old")]
    assert order == [entry[:3] for entry in listed if "old" not in entry[2]] + old
    assert text.index("seed 1") < text.index("seed 2")  # the camera paths by seed


def test_report_lists_rows_of_variants_and_starts_that_no_longer_run_apart(tmp_path: Path) -> None:
    """Committed rows of names no longer runnable still render, in their own table after the results, and their
    comparison with refinement off is that of the whole grid."""
    from s2camp_bench.grid_report import NO_LONGER_RUN_HEADING
    from s2camp_bench.robustness import report

    extra = {"scene": "regime-wide", "train_seconds": 1.0, "iterations": 3000, "eval_seconds": 1.0, "sec_per_iter": 0.5}
    rows = [_row("sfm", "off", 0, 20.0, 0.1, 0.1) | extra]
    config = RobustnessConfig(output_dir=tmp_path)
    assert "no longer run" not in report(rows, config).read_text()
    assert "s2camp-damped" not in VARIANTS and "phone-iid" not in STARTS  # committed names, no longer runnable
    rows.append(_row("sfm", "s2camp-damped", 0, 21.0, 0.1, 0.1) | extra)
    rows.append(_row("phone-iid", "s2camp", 0, 22.0, 0.1, 1.0) | extra)
    text = report(rows, config).read_text()
    results, old = text.split(NO_LONGER_RUN_HEADING)
    assert "| regime-wide | sfm | off | 1 |" in results
    assert "s2camp-damped" not in results and "phone-iid" not in results
    assert 'docs/RESULTS.md, "Names that no longer run"' in old
    assert "| regime-wide | sfm | s2camp-damped | 1 |" in old
    assert "+1.00 dB (1 seed, no spread)" in old  # against the sfm start's off row
    assert "| regime-wide | phone-iid | s2camp | 1 |" in old and "rot 90%" in old  # a start refinement must correct


def test_a_work_folder_keeps_its_rows_and_a_rerun_skips_the_finished_runs(tmp_path: Path) -> None:
    from s2camp_bench.grid import ROWS_FILE, record_row, resume

    specs = [RunSpec("s", "sfm", variant, 0) for variant in ("off", "s2camp")]
    assert resume(specs, tmp_path) == ([], specs)  # a new folder: everything to run
    other = _row("phone", "s2camp", 3, 20.0, 0.1, 0.1)  # a run of another grid in the same folder
    finished = _row("sfm", "off", 0, 20.0, 0.1, 0.1)
    for row in (other, finished):
        record_row(row, tmp_path / "gone", tmp_path)
    done, pending = resume(specs, tmp_path)
    assert done == [finished] and pending == specs[1:]
    assert (tmp_path / ROWS_FILE).read_text().count("\n") == 2  # nothing removed


def test_every_committed_name_that_no_longer_runs_is_described_in_the_results() -> None:
    """The reports list committed rows of names no longer runnable apart and point to docs/RESULTS.md for what each
    ran: every such variant and start of the committed rows files has its line there."""
    import json
    import re

    from s2camp_bench import splat_bench

    root = Path(__file__).resolve().parents[1]
    text = (root / "docs" / "RESULTS.md").read_text(encoding="utf8").split("## Names that no longer run")[1]
    described = set(re.findall(r"^\| `([^`]+)` \|", text, flags=re.M))
    benchmarks = (
        ("regime-rows.jsonl", VARIANTS, STARTS),
        ("splat-rows.jsonl", splat_bench.RUNNABLE_VARIANTS, splat_bench.STARTS),
    )
    for name, variants, starts in benchmarks:
        lines = (root / "docs" / "benchmarks" / name).read_text(encoding="utf8").splitlines()
        rows = [json.loads(line) for line in lines if line.strip()]
        old = {row["variant"] for row in rows if row["variant"] not in variants}
        old |= {row["start"] for row in rows if row["start"] not in starts}
        assert old and old <= described, (name, sorted(old - described))


@pytest.mark.parametrize(("benchmark", "name"), [("robustness", "regime"), ("splat_bench", "splat")])
def test_the_committed_report_is_rendered_from_the_committed_rows(benchmark: str, name: str, tmp_path: Path) -> None:
    """``--rows-from`` the committed rows file gives the committed report, line for line but the command's output
    folder and the machine line (rows of names that no longer run, and traces, included)."""
    import importlib

    module = importlib.import_module(f"s2camp_bench.{benchmark}")
    root = Path(__file__).resolve().parents[1] / "docs" / "benchmarks"
    config_type = module.RobustnessConfig if benchmark == "robustness" else module.SplatBenchConfig
    config = config_type(rows_from=root / f"{name}-rows.jsonl", output_dir=tmp_path)
    written = module.report(module.run(config), config).read_text().splitlines()
    committed = (root / f"{name}.md").read_text().splitlines()
    assert written[2] == committed[2].replace("docs/benchmarks", tmp_path.as_posix())
    assert written[5:] == committed[5:]
