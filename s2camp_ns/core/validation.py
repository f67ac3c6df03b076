"""Input checks raising ``ValueError`` that names the parameter, its value and the allowed range.

A bad focal length or an empty frustum would turn P into NaN silently, so every public entry point of the core
validates its inputs with these.
"""

from __future__ import annotations

import math
from typing import Any

import torch


def _describe_range(low: float | None, high: float | None, low_inclusive: bool, high_inclusive: bool) -> str:
    left = "(-inf" if low is None else ("[" if low_inclusive else "(") + f"{low:g}"
    right = "inf)" if high is None else f"{high:g}" + ("]" if high_inclusive else ")")
    return f"{left}, {right}"


def _offending_value(value: Any, bad: torch.Tensor | None = None) -> str:
    if isinstance(value, torch.Tensor):
        flat = value.detach().reshape(-1)
        if bad is not None:
            index = int(torch.nonzero(bad.reshape(-1))[0])
            return f"{flat[index].item():g} (element {index})"
        return f"{flat[0].item():g}" if flat.numel() == 1 else f"tensor of shape {tuple(value.shape)}"
    return f"{value!r}"


def check_range(
    name: str,
    value: float | int | torch.Tensor,
    low: float | None = None,
    high: float | None = None,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> None:
    """Raise ``ValueError`` unless every element of ``value`` is finite and lies in the given range."""
    allowed = _describe_range(low, high, low_inclusive, high_inclusive)
    if isinstance(value, torch.Tensor):
        tensor = value.detach()
        bad = ~torch.isfinite(tensor)
        if low is not None:
            bad |= (tensor < low) if low_inclusive else (tensor <= low)
        if high is not None:
            bad |= (tensor > high) if high_inclusive else (tensor >= high)
        if bool(bad.any()):
            raise ValueError(f"{name} must lie in {allowed}, got {_offending_value(tensor, bad)}")
        return
    number = float(value)
    ok = math.isfinite(number)
    if ok and low is not None:
        ok = number >= low if low_inclusive else number > low
    if ok and high is not None:
        ok = number <= high if high_inclusive else number < high
    if not ok:
        raise ValueError(f"{name} must lie in {allowed}, got {value!r}")


def check_finite(name: str, value: torch.Tensor) -> None:
    """Raise ``ValueError`` if ``value`` holds a NaN or an infinity."""
    bad = ~torch.isfinite(value.detach())
    if bool(bad.any()):
        raise ValueError(f"{name} must be finite, got {_offending_value(value, bad)}")


def check_positive_int(name: str, value: int) -> None:
    """Raise ``ValueError`` unless ``value`` is an integer >= 1 (bools are rejected)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer in [1, inf), got {value!r}")


def check_choice(name: str, value: Any, choices: tuple[Any, ...]) -> None:
    """Raise ``ValueError`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, choices))}, got {value!r}")
