"""Every `s2camp-bench` subcommand runs in quick mode, prints one JSON object and writes its report."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

REQUIRED_KEYS = {
    "dispersion": {"frustum", "transform", "sampler", "L", "dispersion", "covering_bound"},
    "gram-error": {"frustum", "sampler", "L", "rel_error", "seeds"},
    "speed": {"method", "cameras", "L", "seconds", "peak_mb"},
    "scaling": {"kind"},
    "recovery": {"tier", "scene", "variant", "rot_err", "pos_err", "focal_err", "sec_per_iter"},
    "train-time": {"kind", "method", "sec_per_iter"},
    "proxy-range": {"scene", "range", "t_near", "t_far", "gram_error", "cond_whitened", "cond_content"},
}
REPORTS = {
    "dispersion": "dispersion.md",
    "gram-error": "gram-error.md",
    "speed": "speed.md",
    "scaling": "scaling.md",
    "recovery": "recovery.md",
    "train-time": "train-time.md",
    "proxy-range": "proxy-range.md",
}


def _bench() -> str:
    script = Path(sys.executable).with_name("s2camp-bench")
    # A missing console script is a broken install (pyproject.toml declares it), not a reason to skip.
    assert script.exists(), f"s2camp-bench is not installed next to {sys.executable}: run `make venv`"
    return str(script)


@pytest.mark.slow
@pytest.mark.timeout(400)
@pytest.mark.parametrize("name", sorted(REQUIRED_KEYS))
def test_quick_benchmark_prints_json_and_writes_report(name: str, tmp_path: Path) -> None:
    result = subprocess.run(
        [_bench(), name, "--quick", "--json", "--output-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=390,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    payload = json.loads(result.stdout)
    rows = payload["rows"]
    assert rows, "no rows"
    for row in rows:
        if name == "speed" and row.get("kind", "comparison") != "comparison":
            continue
        assert REQUIRED_KEYS[name] <= row.keys(), f"{name} row misses {REQUIRED_KEYS[name] - row.keys()}"
    report = tmp_path / REPORTS[name]
    assert report.exists() and "Regenerate with" in report.read_text()
    if name == "recovery":
        expected = {"none", "so3xr3", "raw", "camp", "s2camp", "s2camp-once", "s2camp-per-camera"}
        for tier in (1, 2):
            assert {row["variant"] for row in rows if row["tier"] == tier} == expected, f"tier {tier}"
        for row in rows:
            if row["tier"] == 2:
                assert 0.0 < row["psnr"] < 100.0 and 0.0 < row["ssim"] <= 1.0, row
                assert row["sec_per_iter"] > 0.0, row
        assert (tmp_path / "recovery-tier2.png").exists()
        from s2camp_ns.benchmarks.recovery_sfm import intrinsics_option_available

        tier3 = {row["variant"]: row for row in rows if row["tier"] == 3}
        expected = {"start", "none", "so3xr3", "camp", "s2camp-per-image"}
        if intrinsics_option_available():
            expected.add("s2camp-per-camera")
        assert set(tier3) == expected
        intrinsics = {"start": "per-camera", "none": "per-image", "so3xr3": "per-image", "camp": "per-image"}
        intrinsics |= {"s2camp-per-image": "per-image", "s2camp-per-camera": "per-camera"}
        for variant, row in tier3.items():
            assert row["intrinsics"] == intrinsics[variant], row
            if variant != "start":
                assert 0.0 < row["psnr"] < 100.0 and 0.0 < row["ssim"] <= 1.0, row
                assert row["start_rot_err"] == tier3["start"]["rot_err"], row
        # SfM's start is imperfect (the refinement has something to do) but close to the truth.
        assert 1e-4 < tier3["start"]["rot_err"] < 0.1 and 1e-4 < tier3["start"]["pos_err"] < 0.2, tier3["start"]
        assert (tmp_path / "recovery-tier3.png").exists()
        assert "## Tier 3" in report.read_text()
    if name == "train-time":
        summary = {row["method"]: row for row in rows if row["kind"] == "summary"}
        assert set(summary) == {"s2camp-so3xr3", "s2camp", "s2camp-camp"}
        assert all(row["sec_per_iter"] > 0.0 for row in rows)
        # Every ratio is that method's median over the baseline's (nerfstudio's SO3xR3) median, from the timed runs;
        # the per-round ratios pair each run with the baseline's run of the same round.
        runs = {
            method: {r["round"]: r["sec_per_iter"] for r in rows if r["kind"] == "run" and r["method"] == method}
            for method in summary
        }
        baseline = runs["s2camp-so3xr3"]
        for method, row in summary.items():
            assert row["sec_per_iter"] == statistics.median(runs[method].values()), method
            assert row["ratio_to_baseline"] == pytest.approx(row["sec_per_iter"] / statistics.median(baseline.values()))
            per_round = [runs[method][i] / baseline[i] for i in baseline]
            assert (row["ratio_min"], row["ratio_max"]) == pytest.approx((min(per_round), max(per_round))), method
    if name == "speed":
        methods = {row["method"] for row in rows if row.get("kind") == "comparison"}
        assert methods == {"s2camp", "camp-baseline"}
    if name == "scaling":
        kinds = {row["kind"] for row in rows}
        assert kinds == {"P", "step", "allreduce"}
        assert {row["intrinsics"] for row in rows if row["kind"] == "P"} == {"distinct", "unchunked", "shared"}
        flag = [row for row in rows if row["kind"] == "allreduce" and row["bytes"] == 8]
        assert len(flag) == 1
