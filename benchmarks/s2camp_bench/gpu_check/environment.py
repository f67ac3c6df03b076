"""What the machine offers the GPU check (CUDA devices, tiny-cuda-nn, gsplat), and the refusal without CUDA."""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass

import torch


class GpuCheckError(RuntimeError):
    """A command cannot run here (no CUDA device); the message says why."""


@dataclass(frozen=True)
class Environment:
    cuda_available: bool
    device_names: tuple[str, ...]
    torch_version: str
    torch_cuda: str | None
    """CUDA version torch was built for; None for a CPU-only build."""
    tinycudann: bool
    gsplat: bool


def detect_environment() -> Environment:
    available = torch.cuda.is_available()
    names = tuple(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())) if available else ()
    return Environment(
        cuda_available=available, device_names=names, torch_version=torch.__version__, torch_cuda=torch.version.cuda,
        tinycudann=importlib.util.find_spec("tinycudann") is not None,
        gsplat=importlib.util.find_spec("gsplat") is not None,
    )


def require_cuda(environment: Environment) -> None:
    """Refuse to run without a CUDA device: the check exists to run the GPU path, and must never pass without it."""
    if environment.cuda_available:
        return
    build = f"built for CUDA {environment.torch_cuda}" if environment.torch_cuda else "a CPU-only build"
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    hint = f"; CUDA_VISIBLE_DEVICES={visible!r}" if visible is not None else ""
    raise GpuCheckError(f"gpu-check needs a CUDA device, and torch.cuda.is_available() is False here (torch "
                        f"{environment.torch_version}, {build}{hint}). Nothing was checked. Run it on a machine with "
                        "an NVIDIA GPU and a driver for that CUDA version; the CPU-side tests run with `make test`.")


def describe(environment: Environment) -> list[str]:
    """One line per fact, for the terminal and the report."""
    devices = ", ".join(f"cuda:{i} {name}" for i, name in enumerate(environment.device_names)) or "none"
    tcnn = "installed" if environment.tinycudann else (
        "not installed (not on the package registries): nerfacto runs nerfstudio's pure-torch fallback, and every "
        "nerfacto time below is of that fallback"
    )  # fmt: skip
    return [
        f"torch {environment.torch_version} (CUDA {environment.torch_cuda or 'none: CPU-only build'})",
        f"CUDA devices: {devices}",
        f"tiny-cuda-nn: {tcnn}",
        f"gsplat: {'installed' if environment.gsplat else 'not installed'} (its CUDA kernels compile on first use)",
    ]
