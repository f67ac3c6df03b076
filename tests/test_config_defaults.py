"""A run's config.yml written before a field existed still loads (ns-render, ns-eval, s2camp-export-cameras rebuild
the config with PyYAML): the missing field takes its default."""

from __future__ import annotations

import pytest
import yaml

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.perturbation import PerturbationConfig


def _without(saved: str, line_start: str) -> str:
    """The yaml text with the field whose line starts with ``line_start`` (and its nested lines) removed."""
    lines, out, skipping, indent = saved.splitlines(), [], False, 0
    for line in lines:
        stripped = line.lstrip()
        if skipping and len(line) - len(stripped) > indent:
            continue
        skipping = stripped.startswith(line_start)
        indent = len(line) - len(stripped)
        if not skipping:
            out.append(line)
    return "\n".join(out) + "\n"


PREVIOUS_PERTURBATION = """\
!!python/object:s2camp_ns.core.perturbation.PerturbationConfig
drift: !!python/object:s2camp_ns.core.perturbation.DriftConfig
  enabled: {drift}
  focal_error: 0.015
  position_drift: 0.01
  tilt_deg: 0.3
  up: !!python/tuple
  - 0.0
  - 0.0
  - 1.0
  yaw_drift_deg: 1.5
enabled: true
seed: 3
sigma_dolly_z: 0.05
sigma_focal_length: 0.02
sigma_look_at: 0.005
sigma_position: 0.005
single_dolly: true
zero_distortion: true
"""
"""A perturbation config as the previous version wrote it into every run's config.yml (its drift since moved to the
benchmarks' data parser, its two protocol switches since fixed at these values)."""


def test_a_perturbation_config_of_the_previous_version_loads_and_a_drift_it_turned_on_is_refused() -> None:
    loaded = yaml.load(PREVIOUS_PERTURBATION.format(drift="false"), Loader=yaml.Loader)
    assert isinstance(loaded, PerturbationConfig) and (loaded.enabled, loaded.seed) == (True, 3)
    loaded.validate()  # what the data parser does first
    assert loaded.drift.enabled is False  # kept as saved, read by nothing but the check below
    on = yaml.load(PREVIOUS_PERTURBATION.format(drift="true"), Loader=yaml.Loader)
    with pytest.raises(ValueError, match="perturbation.drift: this run's config.yml turns on a visual-inertial drift"):
        on.validate()


def test_a_data_parser_config_saved_with_a_reference_model_is_refused_by_name(tmp_path) -> None:
    """``reference_model`` (now the benchmarks' data parser's) in a run's config.yml: None loads and parses as
    saved, a model is refused rather than left out of the reference cameras."""
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    saved = yaml.dump(S2CampDataParserConfig(data=tmp_path / "missing"))
    for value, refused in (("null", False), ("/truth/sparse/0", True)):
        loaded = yaml.load(saved + f"reference_model: {value}\n", Loader=yaml.Loader)
        parser = loaded.setup()
        if refused:
            with pytest.raises(ValueError, match=r"reference_model /truth/sparse/0: this run's config.yml takes"):
                parser.get_dataparser_outputs("train")
        else:
            with pytest.raises(FileNotFoundError, match="does not exist"):  # validated, then the missing scene
                parser.get_dataparser_outputs("train")


def test_a_camera_optimizer_config_saved_before_photometric_loads_with_the_images_on() -> None:
    saved = yaml.dump(S2CampCameraOptimizerConfig(track_prior=True, refresh_every=7))
    old = _without(saved, "photometric:")
    assert "photometric" not in old
    loaded = yaml.load(old, Loader=yaml.Loader)
    assert loaded.photometric is True and loaded.track_prior is True and loaded.refresh_every == 7
    loaded.validate()


def test_a_camera_optimizer_config_saved_with_a_removed_field_still_loads() -> None:
    """``fix_common_dolly`` (an option since removed) in a run's config.yml: the config loads and validates, with every
    field as saved. The stale key stays on the instance (``DefaultsOnLoad`` keeps what it is given) and nothing
    reads it."""
    saved = yaml.dump(S2CampCameraOptimizerConfig(track_prior=True, fix_common_rotation=True, refresh_every=7))
    old = saved.replace("fix_common_rotation: true\n", "fix_common_dolly: true\nfix_common_rotation: true\n")
    assert "fix_common_dolly: true" in old
    loaded = yaml.load(old, Loader=yaml.Loader)
    loaded.validate()
    assert loaded == S2CampCameraOptimizerConfig(track_prior=True, fix_common_rotation=True, refresh_every=7)
    assert (loaded.track_prior, loaded.fix_common_rotation, loaded.refresh_every) == (True, True, 7)


def test_a_camera_optimizer_config_saved_with_the_old_defaults_keeps_them() -> None:
    """Both options were off by default before they became the shipped defaults; a run's config.yml writes every
    field, so a run saved with them off (the old defaults, the CamP baseline, the photometric-only rows) loads with
    them off, and one saved with them on with them on."""
    for value in (False, True):
        saved = yaml.dump(S2CampCameraOptimizerConfig(track_prior=value, fix_common_rotation=value))
        assert f"track_prior: {str(value).lower()}\n" in saved
        assert f"fix_common_rotation: {str(value).lower()}\n" in saved
        loaded = yaml.load(saved, Loader=yaml.Loader)
        assert (loaded.track_prior, loaded.fix_common_rotation) == (value, value)
        loaded.validate()
