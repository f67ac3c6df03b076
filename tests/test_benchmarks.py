"""Every `s2camp-bench` subcommand runs in quick mode, prints one JSON object and writes its report, under
outputs/benchmarks unless ``--output-dir`` names another folder (the committed docs/benchmarks only when asked)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hang_guard import HANG_GUARD_S

REQUIRED_KEYS = {
    "dispersion": {"frustum", "transform", "sampler", "L", "dispersion", "error_bound"},
    "gram-error": {"frustum", "sampler", "L", "rel_error", "seeds"},
    "robustness": {
        "scene",
        "start",
        "variant",
        "seed",
        "rot_err",
        "pos_err",
        "focal_err",
        "psnr",
        "ssim",
        "drift_px",
        "start_rot_err",
        "start_pos_err",
        "start_focal_err",
        "start_drift_px",
        "train_seconds",
    },  # fmt: skip
    "image-tracks": {"images", "pairs", "seconds", "SIFT_seconds", "matching_seconds", "summary", "device"},
    "step-cost": {"method", "camera_model", "ops", "syncs", "added_ops", "added_syncs", "camera_path_ms"},
    "anchors": {"start", "seed", "keypoints", "rot_err", "start_rot_err", "keypoint_median", "keypoint_pairs"},
    "export-load": {"scene", "images", "observations", "export_seconds_with_file", "export_seconds_with_track_work",
                    "anchor_rms_px", "exported_rms_px"},  # fmt: skip
}
REPORTS = {
    "dispersion": "dispersion.md",
    "gram-error": "gram-error.md",
    "robustness": "regime.md",
    "image-tracks": "image-tracks.md",
    "step-cost": "step-cost.md",
    "anchors": "anchors.md",
    "export-load": "export-load.md",
}


def _bench() -> str:
    script = Path(sys.executable).with_name("s2camp-bench")
    # A missing console script is a broken install (pyproject.toml declares it), not a reason to skip.
    assert script.exists(), f"s2camp-bench is not installed next to {sys.executable}: run `make venv`"
    return str(script)


@pytest.mark.slow
@pytest.mark.timeout(HANG_GUARD_S)
@pytest.mark.parametrize("name", sorted(REQUIRED_KEYS))
def test_quick_benchmark_prints_json_and_writes_report(name: str, tmp_path: Path) -> None:
    result = subprocess.run(
        [_bench(), name, "--quick", "--json", "--output-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=HANG_GUARD_S,  # not a speed check: the robustness run trains four ns-train runs
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    payload = json.loads(result.stdout)
    rows = payload["rows"]
    assert rows, "no rows"
    for row in rows:
        assert REQUIRED_KEYS[name] <= row.keys(), f"{name} row misses {REQUIRED_KEYS[name] - row.keys()}"
    report = tmp_path / REPORTS[name]
    assert report.exists() and "Regenerate with" in report.read_text()
    if name == "export-load":  # the exported points agree with the exported cameras at least as well as at the anchors
        assert all(0 < row["exported_rms_px"] <= row["anchor_rms_px"] for row in rows), rows
    if name == "step-cost":  # the camera path adds no host read nerfstudio's own pose optimizer does not
        added = {row["method"]: row["added_syncs"] for row in rows}
        assert set(added) == {"off", "s2camp-so3xr3", "s2camp"}
        assert added["s2camp"] <= added["s2camp-so3xr3"], added
    if name == "robustness":
        _check_robustness_rows(rows, tmp_path)
    if name == "anchors":  # the same tracks, detected then refined: the refined keypoints agree better
        detected, refined = rows
        assert (detected["keypoints"], refined["keypoints"]) == ("detected", "refined")
        assert refined["keypoint_median"] < detected["keypoint_median"], rows
    if name == "image-tracks":
        assert [row["images"] for row in rows] == [12, 8]
        assert all(row["SIFT_seconds"] > 0.0 and row["matching_seconds"] > 0.0 for row in rows), rows
        assert [row["pairs"] for row in rows] == [66, 28]  # every pair up to EXHAUSTIVE_LIMIT images


def _check_robustness_rows(rows: list[dict], folder: Path) -> None:
    """Quick mode: one scene, one seed, variants off and s2camp from both starts; values finite and plausible."""
    import math

    assert {(row["start"], row["variant"]) for row in rows} == {
        (start, variant) for start in ("accurate", "perturbed") for variant in ("off", "s2camp")
    }
    for row in rows:
        for key in REQUIRED_KEYS["robustness"] - {"scene", "start", "variant", "seed"}:
            assert isinstance(row[key], float) and math.isfinite(row[key]), (key, row)
        assert 5.0 < row["psnr"] < 60.0 and 0.0 < row["ssim"] <= 1.0, row
        # Small camera errors: no visible point falls behind a camera (it would leave the drift).
        assert row["drift_behind"] == 0 and row["start_drift_behind"] == 0, row
    by = {(row["start"], row["variant"]): row for row in rows}
    accurate, perturbed = by[("accurate", "off")], by[("perturbed", "off")]
    # The accurate start is the truth; CamP's perturbation moves every camera (0.005 look-at and position, 2 %
    # focal, 5 % dolly in normalized units): about 0.3 deg, 4.5 px focal and 1 px drift on this scene.
    for key, at_least in (("rot_err", 0.05), ("pos_err", 1e-3), ("focal_err", 0.5), ("drift_px", 0.2)):
        assert accurate[f"start_{key}"] < 1e-9, (key, accurate)
        assert perturbed[f"start_{key}"] > at_least, (key, perturbed)
        # Camera optimizer off: the cameras end where they started.
        assert perturbed[key] == pytest.approx(perturbed[f"start_{key}"], rel=1e-9, abs=1e-12), (key, perturbed)
    for start in ("accurate", "perturbed"):
        assert by[(start, "s2camp")]["start_drift_px"] == pytest.approx(by[(start, "off")]["start_drift_px"])
    text = (folder / "regime.md").read_text()
    assert "s2camp-bench robustness --quick" in text and "small-narrow-far" in text


def test_every_benchmark_writes_outside_the_committed_docs_by_default() -> None:
    """Without ``--output-dir`` every subcommand (``all`` included) writes under outputs/benchmarks, never docs/."""
    import tyro

    from s2camp_bench.cli import Command

    names = [*REQUIRED_KEYS, "splat", "all"]
    for name in names:
        config = tyro.cli(Command, args=[name])
        assert config.output_dir == Path("outputs/benchmarks"), (name, config.output_dir)


def test_regenerate_line_names_the_output_folder(tmp_path: Path) -> None:
    """A report's "Regenerate with" command writes the report where it is: the committed ones name docs/benchmarks."""
    from s2camp_bench.common import regenerate_command, write_report

    assert regenerate_command("s2camp-bench gram-error", Path("outputs/benchmarks")) == "s2camp-bench gram-error"
    docs = "s2camp-bench gram-error --quick --output-dir docs/benchmarks"
    assert regenerate_command("s2camp-bench gram-error --quick", Path("docs/benchmarks")) == docs
    path = write_report(tmp_path / "reports", "gram-error", "Gram error", "s2camp-bench gram-error", ["body"])
    folder = (tmp_path / "reports").as_posix()
    assert f"Regenerate with `s2camp-bench gram-error --output-dir {folder}`." in path.read_text()


def test_committed_reports_regenerate_into_docs() -> None:
    """Each committed report's first "Regenerate with" command writes docs/benchmarks (the default would not)."""
    docs = Path(__file__).resolve().parents[1] / "docs" / "benchmarks"
    for report in [*REPORTS.values(), "splat.md"]:
        line = (docs / report).read_text().splitlines()[2]
        command = line.split("`")[1]
        assert command.startswith("s2camp-bench ") and command.endswith(" --output-dir docs/benchmarks"), line


@pytest.mark.timeout(HANG_GUARD_S)
def test_quick_json_run_leaves_docs_untouched(tmp_path: Path) -> None:
    """``s2camp-bench <name> --quick --json`` without ``--output-dir``, run from a checkout-like folder: the report
    goes to outputs/benchmarks and the committed docs/benchmarks files keep their bytes."""
    docs = tmp_path / "docs" / "benchmarks"
    docs.mkdir(parents=True)
    committed = docs / "dispersion.md"
    committed.write_text("committed table\n")
    result = subprocess.run(
        [_bench(), "dispersion", "--quick", "--json"],
        capture_output=True,
        text=True,
        timeout=HANG_GUARD_S,
        check=False,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads(result.stdout)["rows"]
    assert committed.read_text() == "committed table\n"
    assert sorted(p.name for p in docs.iterdir()) == ["dispersion.md"]
    report = tmp_path / "outputs" / "benchmarks" / "dispersion.md"
    assert "Regenerate with `s2camp-bench dispersion --quick`." in report.read_text()


def test_a_generated_scene_is_kept_when_it_is_the_one_asked_for(tmp_path: Path) -> None:
    # Several benchmark processes share a grid's work folder: regenerating a scene in place while another run reads
    # it made that run fail. The same config keeps the folder untouched; another config regenerates it.
    from dataclasses import replace

    from s2camp_bench.common import generated_scene
    from s2camp_bench.scene.make_scene import MakeSceneConfig

    config = MakeSceneConfig(num_cameras=4, width=64, height=48, points_per_image=150, k1=0.0, k2=0.0,
                             output_dir=tmp_path / "scene")  # fmt: skip
    scene = generated_scene(config)
    model = scene / "sparse" / "0" / "images.bin"
    model.write_bytes(model.read_bytes())  # a new modification time, same bytes: rewriting would change it again
    touched = model.stat().st_mtime_ns
    assert generated_scene(config) == scene and model.stat().st_mtime_ns == touched
    info = json.loads((scene / "scene_info.json").read_text())
    assert info["config"]["seed"] == config.seed
    generated_scene(replace(config, seed=config.seed + 1))
    assert model.stat().st_mtime_ns != touched  # regenerated
    assert json.loads((scene / "scene_info.json").read_text())["config"]["seed"] == config.seed + 1


def test_step_cost_report_names_the_options_it_ran_with() -> None:
    from s2camp_bench.step_cost import StepCostConfig

    config = StepCostConfig(methods=("off", "s2camp"), viewer=(True,), timing_repeats=10)
    assert config.command() == "s2camp-bench step-cost --methods off s2camp --viewer True --timing-repeats 10"
    assert StepCostConfig().command() == "s2camp-bench step-cost"
    assert StepCostConfig(quick=True).command() == "s2camp-bench step-cost --quick"
