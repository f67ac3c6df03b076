"""Configs saved before a field existed load with that field's default.

nerfstudio writes the whole config into a run's ``config.yml`` and ``eval_setup`` (ns-render, ns-eval,
s2camp-export-cameras) rebuilds it with PyYAML, which fills the object's ``__dict__`` from the saved fields without
calling ``__init__``. A field added to a config after the run was trained would then be missing, and the first read
of it an AttributeError. ``__setstate__`` (also what unpickling calls) gives every missing field its default.
A config class that an earlier version saved and this one no longer has loads as a ``RemovedConfig``.
"""

from __future__ import annotations

from dataclasses import MISSING, fields


class DefaultsOnLoad:
    """Mixin for config dataclasses: missing fields of a loaded config take their defaults (module docstring)."""

    def __setstate__(self, state: dict) -> None:
        defaults = {
            f.name: f.default_factory() if f.default_factory is not MISSING else f.default
            for f in fields(self)
            if f.default is not MISSING or f.default_factory is not MISSING
        }
        self.__dict__.update({**defaults, **state})


class RemovedConfig:
    """A config class of an earlier version, named in its runs' config.yml: loads as the saved fields, which the
    config that holds it may check (a saved option that was on and is no longer applied is refused there)."""

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)


__all__ = ["DefaultsOnLoad", "RemovedConfig"]
