"""A run's config.yml written before a field existed still loads (ns-render, ns-eval, s2camp-export-cameras rebuild
the config with PyYAML): the missing field takes its default."""

from __future__ import annotations

import yaml

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.perturbation import DriftConfig, PerturbationConfig


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


def test_a_perturbation_config_saved_before_the_drift_loads_with_it_off() -> None:
    saved = yaml.dump(PerturbationConfig(enabled=True, seed=3))
    old = _without(saved, "drift:")
    assert "drift" not in old and "seed: 3" in old
    loaded = yaml.load(old, Loader=yaml.Loader)
    assert loaded.drift == DriftConfig() and loaded.drift.enabled is False
    assert loaded.seed == 3 and loaded.enabled is True
    loaded.validate()  # what the data parser does first: an AttributeError before


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
