"""COLMAP camera models <-> ``Intrinsics``, in COLMAP's meaning of every coefficient.

Parameter orders are COLMAP's (src/colmap/sensor/models.h, pycolmap's ``Camera.params``):

==================  ====================================================  =================================
COLMAP model        parameters                                            ``Intrinsics``
==================  ====================================================  =================================
SIMPLE_PINHOLE      f, cx, cy                                             perspective, fx = fy = f
PINHOLE             fx, fy, cx, cy                                        perspective
SIMPLE_RADIAL       f, cx, cy, k                                          perspective, k1 = k
RADIAL              f, cx, cy, k1, k2                                     perspective
OPENCV              fx, fy, cx, cy, k1, k2, p1, p2                        perspective
FULL_OPENCV         fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6        perspective, k4 = k5 = k6 = 0 only
OPENCV_FISHEYE      fx, fy, cx, cy, k1, k2, k3, k4                        fisheye (equidistant)
==================  ====================================================  =================================

FULL_OPENCV's radial factor is rational, (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6), only its
polynomial part an ``Intrinsics`` camera; ``Intrinsics``' k4 (an r^8 term, nerfstudio's) and skew have no COLMAP
counterpart.
"""

from __future__ import annotations

import torch

from s2camp_ns.core.camera import CAMERA_MODEL_PROJECTION, Intrinsics

COLMAP_PARAMETERS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
SUPPORTED_COLMAP_MODELS: tuple[str, ...] = tuple(COLMAP_PARAMETERS)

_INTRINSICS_NAME = {"f": ("fx", "fy"), "k": ("k1",)}
"""COLMAP parameter -> Intrinsics fields it sets (the others map to the field of the same name)."""

_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def check_colmap_model(model: str) -> None:
    if model not in COLMAP_PARAMETERS:
        raise ValueError(
            f"COLMAP camera model {model!r} is not supported; supported are {', '.join(SUPPORTED_COLMAP_MODELS)}"
        )


def colmap_to_values(model: str, params) -> dict[str, float]:
    """fx, fy, cx, cy, k1..k4, p1, p2 (``Intrinsics`` meaning) of one COLMAP camera; raises for a wrong parameter
    count and for FULL_OPENCV with a rational part."""
    check_colmap_model(model)
    names = COLMAP_PARAMETERS[model]
    params = [float(p) for p in params]
    if len(params) != len(names):
        raise ValueError(f"COLMAP {model} has {len(names)} parameters ({', '.join(names)}), got {len(params)}")
    given = dict(zip(names, params, strict=True))
    if model == "FULL_OPENCV":
        rational = {name: given.pop(name) for name in ("k4", "k5", "k6")}
        if any(value != 0.0 for value in rational.values()):
            raise ValueError(
                "COLMAP FULL_OPENCV with a rational radial factor is not supported: "
                + ", ".join(f"{name} = {value:g}" for name, value in rational.items())
                + "; allowed are k4 = k5 = k6 = 0 (the denominator 1 + k4 r^2 + k5 r^4 + k6 r^6 has no counterpart "
                "in nerfstudio or S2CamP, whose k4 multiplies r^8)"
            )
    values = dict.fromkeys(_DISTORTION, 0.0)
    for name, value in given.items():
        for field in _INTRINSICS_NAME.get(name, (name,)):
            values[field] = value
    return values


def intrinsics_from_colmap(
    model: str, params, width: float, height: float, dtype: torch.dtype = torch.float64, validate: bool = True
) -> Intrinsics:
    """``Intrinsics`` of one COLMAP camera (``COLMAP_PARAMETERS`` order)."""
    values = colmap_to_values(model, params)
    return Intrinsics.create(
        width=width, height=height, dtype=dtype, validate=validate, model=CAMERA_MODEL_PROJECTION[model], **values
    )


def colmap_model_for(values: dict[str, float], projection: str, tolerance: float = 1e-9) -> str:
    """The simplest COLMAP model that holds a camera exactly: OPENCV_FISHEYE, or RADIAL (fx = fy, k1, k2), OPENCV
    (+ fy, p1, p2) or FULL_OPENCV (+ k3)."""
    if projection == "fisheye":
        return "OPENCV_FISHEYE"
    if values.get("k3", 0.0) != 0.0:
        return "FULL_OPENCV"
    same_focal = abs(values["fx"] - values["fy"]) <= tolerance * abs(values["fx"])
    tangential = values.get("p1", 0.0) != 0.0 or values.get("p2", 0.0) != 0.0
    return "RADIAL" if same_focal and not tangential else "OPENCV"


def values_to_colmap(model: str, values: dict[str, float], projection: str, tolerance: float = 1e-9) -> list[float]:
    """COLMAP parameters of ``model`` for ``Intrinsics`` values; raises, naming the coefficient, when the model cannot
    hold the camera."""
    check_colmap_model(model)
    if CAMERA_MODEL_PROJECTION[model] != projection:
        raise ValueError(f"COLMAP {model} is a {CAMERA_MODEL_PROJECTION[model]} model, the camera is {projection}")
    values = {**dict.fromkeys(_DISTORTION, 0.0), **values}
    if projection == "perspective" and values["k4"] != 0.0:
        raise ValueError(
            f"k4 = {values['k4']:g} (a polynomial r^8 term) cannot be written to COLMAP: FULL_OPENCV's k4 is a "
            "coefficient of the rational denominator (nerfstudio issue 3355); allowed is k4 = 0"
        )
    names = COLMAP_PARAMETERS[model]
    if "f" in names and abs(values["fx"] - values["fy"]) > tolerance * abs(values["fx"]):
        raise ValueError(f"COLMAP {model} needs fx = fy, got fx = {values['fx']:.9g}, fy = {values['fy']:.9g}")
    held = {field for name in names for field in _INTRINSICS_NAME.get(name, (name,))}
    for name in _DISTORTION:
        if name not in held and values[name] != 0.0:
            raise ValueError(f"COLMAP {model} has no {name}, but the camera's {name} = {values[name]:g}")
    params = []
    for name in names:
        if name == "f":
            params.append(values["fx"])
        elif name == "k":
            params.append(values["k1"])
        elif model == "FULL_OPENCV" and name in ("k4", "k5", "k6"):
            params.append(0.0)
        else:
            params.append(values[name])
    return params


__all__ = [
    "COLMAP_PARAMETERS",
    "SUPPORTED_COLMAP_MODELS",
    "check_colmap_model",
    "colmap_model_for",
    "colmap_to_values",
    "intrinsics_from_colmap",
    "values_to_colmap",
]
