"""docs/ARCHITECTURE.md names only APIs that exist: every backticked ``s2camp_ns...`` name must import."""

from __future__ import annotations

import importlib
import importlib.util
import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "ARCHITECTURE.md"
NAME = re.compile(r"`(s2camp_ns(?:\.[A-Za-z_][A-Za-z0-9_]*)+)`")


def documented_names() -> list[str]:
    return sorted(set(NAME.findall(DOC.read_text(encoding="utf8"))))


def resolve(dotted: str) -> object:
    """Walk ``dotted``: submodules of packages are imported, everything else is an attribute."""
    parts = dotted.split(".")
    name = parts[0]
    value: object = importlib.import_module(name)
    for part in parts[1:]:
        name = f"{name}.{part}"
        if hasattr(value, "__path__") and importlib.util.find_spec(name) is not None:
            value = importlib.import_module(name)
        else:
            value = getattr(value, part)
    return value


def test_the_document_names_the_core_and_the_adapter() -> None:
    names = documented_names()
    assert "s2camp_ns.core.preconditioner.compute_preconditioner" in names
    assert "s2camp_ns.camera_optimizer.S2CampCameraOptimizer" in names
    assert len(names) > 50


@pytest.mark.parametrize("dotted", documented_names())
def test_every_documented_name_exists(dotted: str) -> None:
    resolve(dotted)
