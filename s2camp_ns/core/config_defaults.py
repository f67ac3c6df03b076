"""Configs saved without a field load with that field's default.

nerfstudio's ``eval_setup`` rebuilds a run's ``config.yml`` with PyYAML, filling ``__dict__`` without ``__init__``;
``__setstate__`` (also used by unpickling) gives every missing field its default. A saved config class that no longer
exists loads as a ``RemovedConfig``.
"""

from __future__ import annotations

from dataclasses import MISSING, fields


class DefaultsOnLoad:
    """Mixin for config dataclasses: missing fields of a loaded config take their defaults."""

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


__all__ = ["DefaultsOnLoad", "RemovedConfig"]
