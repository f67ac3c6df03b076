"""Runs of earlier versions of s2camp-ns load in this one: their config.yml and their checkpoints.

nerfstudio rebuilds a run's config.yml with PyYAML (``eval_setup``, ``ns-train --load-config``), which names every
class by its module path, and loads checkpoints with the tensor names they were saved under. What each earlier
version wrote that this one reads differently, by the commit that last wrote it:

- up to 8b8539f (one ``s2camp_ns/nerfstudio/`` folder): the module paths of ``MOVED_MODULES``. Importing this module
  registers a finder for those paths (an entry of ``sys.meta_path`` that answers only for them): each old path is a
  module of its own that lends the new module's names, so PyYAML finds ``s2camp_ns.nerfstudio.dataparser.X`` as
  ``s2camp_ns.data.dataparser.X``. nerfstudio imports this module with the method entry points, before any config.
- up to 300510a: the schedule classes ``FloatExponentialDecayScheduler(Config)`` of ``s2camp_ns.nerfstudio.schedulers``,
  which were nerfstudio's exponential schedule (``RENAMED``);
- aff7253 to 8e80474: ``PerturbationConfig.drift``, a ``DriftConfig`` of ``s2camp_ns.core.perturbation`` (loads as a
  ``RemovedConfig``; one that was on is refused, ``refuse_removed_fields``), and 5dc81a3 to 8e80474 the data parser's
  ``reference_model`` (refused: it took the reference cameras from a model this version does not read);
- up to 8e80474: checkpoints whose refiner tensors were the camera optimizer's own (``refiner_keys``, and
  ``OLD_CAMERA_COUNT_KEYS`` for the check that a checkpoint fits the scene) and whose per-image latent was one
  [n, K] tensor (``split_per_image_adam_state``);
- any version: a config saved without a field that exists now loads with that field's default (``DefaultsOnLoad``).

Pure Python (no nerfstudio, no s2camp_ns import at import time): the core's configs use ``DefaultsOnLoad``.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
from dataclasses import MISSING, fields
from types import ModuleType

_OLD = "s2camp_ns.nerfstudio"
"""The package that held the nerfstudio side up to 8b8539f."""

MOVED_MODULES: dict[str, str] = {
    **{f"{_OLD}.{name}": f"s2camp_ns.data.{name}" for name in (
        "dataparser", "scene_formats", "colmap_scene", "transforms_scene", "transforms_file", "image_check",
        "camera_conversion", "camera_fields", "colmap_world", "camera_perturbation",
    )},
    f"{_OLD}.colmap_model": "s2camp_ns.data.colmap_files",
    f"{_OLD}.colmap_reconstruction": "s2camp_ns.data.colmap_writer",
    **{f"{_OLD}.{name}": f"s2camp_ns.tracks.{name}" for name in (
        "track_evidence", "colmap_tracks", "transforms_tracks", "robust_adjustment", "image_tracks", "track_cache",
        "build_progress", "feature_database", "undistorted_tracks",
    )},
    "s2camp_ns.colmap_log": "s2camp_ns.tracks.colmap_log",
    **{f"{_OLD}.{name}": f"s2camp_ns.method.{name}" for name in (
        "rays", "datamanager", "pipeline", "model", "splat_model", "trainer", "schedulers",
    )},
    f"{_OLD}.viewer_panel": "s2camp_ns.viewer.panel",
    **{f"{_OLD}.{name}": f"s2camp_ns.scripts.{name}" for name in (
        "export_cameras", "eval_aligned", "test_time_alignment", "ray_alignment", "splat_alignment",
        "alignment_camera",
    )},
    "s2camp_ns.core.colmap_models": "s2camp_ns.core.colmap_camera_models",
}  # fmt: skip
"""Module path up to 8b8539f -> the module that holds its names now."""

RENAMED: dict[tuple[str, str], str] = {
    (f"{_OLD}.schedulers", "FloatExponentialDecaySchedulerConfig"):
        "nerfstudio.engine.schedulers.ExponentialDecaySchedulerConfig",
    (f"{_OLD}.schedulers", "FloatExponentialDecayScheduler"): "nerfstudio.engine.schedulers.ExponentialDecayScheduler",
    ("s2camp_ns.core.perturbation", "DriftConfig"): "s2camp_ns.compat.RemovedConfig",
}  # fmt: skip
"""(module path, name) that earlier versions saved -> the dotted name of what loads in its place."""

OLD_CAMERA_COUNT_KEYS: tuple[str, ...] = ("camera_optimizer.precond",)
"""Checkpoint entries (after any prefix) up to 8e80474 whose first dimension is the number of training cameras."""


class DefaultsOnLoad:
    """Mixin for config dataclasses: a config loaded without some field (PyYAML and pickle fill ``__dict__`` through
    ``__setstate__``, not ``__init__``) gives that field its default."""

    def __setstate__(self, state: dict) -> None:
        defaults = {
            f.name: f.default_factory() if f.default_factory is not MISSING else f.default
            for f in fields(self)
            if f.default is not MISSING or f.default_factory is not MISSING
        }
        self.__dict__.update({**defaults, **state})


class RemovedConfig:
    """A saved config class that no longer exists: loads as its saved fields, for the config holding it to check."""

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)


def refuse_removed_fields(name: str, config: object) -> None:
    """ValueError for a loaded config that asks for what this version no longer does: a perturbation with the
    visual-inertial drift on (``name`` "perturbation"), a data parser with a ``reference_model`` ("dataparser")."""
    saved = vars(config)
    if name == "perturbation" and getattr(saved.get("drift"), "enabled", False):
        raise ValueError(
            "perturbation.drift: this run's config.yml turns on a visual-inertial drift of the cameras, which "
            "this version's s2camp-data no longer applies (s2camp-bench-data does, as --drift); load the run "
            "with the version that trained it"
        )
    if name == "dataparser" and saved.get("reference_model") is not None:
        raise ValueError(
            f"reference_model {saved['reference_model']}: this run's config.yml takes its reference cameras from a "
            "COLMAP model, which this version's s2camp-data no longer reads (s2camp-bench-data does); load the run "
            "with the version that trained it"
        )


def resolve(dotted: str) -> object:
    """The object a dotted name (``module.attribute``) names, its module imported."""
    module, _, attribute = dotted.rpartition(".")
    return getattr(importlib.import_module(module), attribute)


def old_names(module: str):
    """A module ``__getattr__`` (PEP 562) that lends the names ``RENAMED`` keeps for ``module`` after they left it."""

    def __getattr__(name: str) -> object:
        if (module, name) in RENAMED:
            return resolve(RENAMED[(module, name)])
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__


class _MovedModule(importlib.abc.Loader):
    """Loads an old module path as a module of its own whose names are looked up in the new module."""

    def __init__(self, new: str | None) -> None:
        self.new = new

    def create_module(self, spec) -> None:
        return None  # the default module object

    def exec_module(self, module: ModuleType) -> None:
        if self.new is None:  # the old package itself
            module.__path__ = []
            return
        target, renamed = importlib.import_module(self.new), old_names(module.__name__)

        def __getattr__(name: str) -> object:
            try:
                return renamed(name)
            except AttributeError:
                return getattr(target, name)

        module.__getattr__ = __getattr__
        module.__doc__ = f"Moved to {self.new} ({__name__})."


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds the module paths of ``MOVED_MODULES`` (and their old package) and nothing else."""

    def find_spec(self, fullname: str, path=None, target=None):
        if fullname == _OLD:
            return importlib.util.spec_from_loader(fullname, _MovedModule(None), is_package=True)
        if fullname in MOVED_MODULES:
            return importlib.util.spec_from_loader(fullname, _MovedModule(MOVED_MODULES[fullname]))
        return None


def split_per_image_adam_state(state: dict, num_pose_params: int) -> dict:
    """Adam's state of the ``camera_opt`` group written while a per-image latent was one tensor [n, K]: the same
    moments for the pose [n, ``num_pose_params``] and intrinsics [n, K - that] latents that store it now (a state of
    two or more tensors is returned as it is)."""
    group = state["param_groups"][0]
    if len(state["param_groups"]) != 1 or len(group["params"]) != 1:
        return state
    old = state["state"].get(group["params"][0])
    if old is None or old["exp_avg"].shape[-1] <= num_pose_params:
        return state
    parts = [{**old}, {**old}]
    for key in ("exp_avg", "exp_avg_sq"):
        parts[0][key], parts[1][key] = old[key][:, :num_pose_params], old[key][:, num_pose_params:]
    return {"state": {0: parts[0], 1: parts[1]}, "param_groups": [{**group, "params": [0, 1]}]}


def refiner_keys(module, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs) -> None:
    """Load hook of the camera optimizer: a checkpoint written while the refiner's tensors were the optimizer's own
    (``<prefix>precond``) loads them as the submodule's (``<prefix>refiner.precond``)."""
    names = set(module.refiner.state_dict()) | {"whitened_delta"}
    for name in names:
        if prefix + name in state_dict and prefix + "refiner." + name not in state_dict:
            state_dict[prefix + "refiner." + name] = state_dict.pop(prefix + name)


if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
    sys.meta_path.append(MovedModuleFinder())


__all__ = [
    "MOVED_MODULES",
    "OLD_CAMERA_COUNT_KEYS",
    "RENAMED",
    "DefaultsOnLoad",
    "MovedModuleFinder",
    "RemovedConfig",
    "old_names",
    "refiner_keys",
    "refuse_removed_fields",
    "resolve",
    "split_per_image_adam_state",
]
