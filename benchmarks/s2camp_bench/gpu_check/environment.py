"""What the machine offers the GPU check: CUDA devices, tiny-cuda-nn, a CUDA compiler, gsplat."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import torch


class GpuCheckError(RuntimeError):
    """The check cannot run here (no CUDA device, a bad option); the message says why."""


@dataclass(frozen=True)
class Environment:
    cuda_available: bool
    device_names: tuple[str, ...]
    torch_version: str
    torch_cuda: str | None
    """CUDA version torch was built for; None for a CPU-only build."""
    tinycudann: bool
    nvcc: str | None
    """Path of the CUDA compiler, if any (PATH, then $CUDA_HOME/bin)."""
    gsplat: bool

    @property
    def device_count(self) -> int:
        return len(self.device_names)


def find_nvcc() -> str | None:
    found = shutil.which("nvcc")
    if found is not None:
        return found
    for variable in ("CUDA_HOME", "CUDA_PATH"):
        root = os.environ.get(variable)
        if root and (Path(root) / "bin" / "nvcc").is_file():
            return str(Path(root) / "bin" / "nvcc")
    return None


def detect_environment() -> Environment:
    available = torch.cuda.is_available()
    names = tuple(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())) if available else ()
    return Environment(
        cuda_available=available,
        device_names=names,
        torch_version=torch.__version__,
        torch_cuda=torch.version.cuda,
        tinycudann=importlib.util.find_spec("tinycudann") is not None,
        nvcc=find_nvcc(),
        gsplat=importlib.util.find_spec("gsplat") is not None,
    )


def require_cuda(environment: Environment) -> None:
    """Refuse to run without a CUDA device: the check exists to run the GPU path, and must never pass without it."""
    if environment.cuda_available:
        return
    build = f"built for CUDA {environment.torch_cuda}" if environment.torch_cuda else "a CPU-only build"
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    hint = f"; CUDA_VISIBLE_DEVICES={visible!r}" if visible is not None else ""
    raise GpuCheckError(
        f"gpu-check needs a CUDA device, and torch.cuda.is_available() is False here (torch "
        f"{environment.torch_version}, {build}{hint}). Nothing was checked. Run it on a machine with an NVIDIA GPU "
        "and a driver for that CUDA version; the CPU-side tests run with `make test`."
    )


def describe(environment: Environment) -> list[str]:
    """One line per fact, for the terminal and the report."""
    devices = ", ".join(f"cuda:{i} {name}" for i, name in enumerate(environment.device_names)) or "none"
    return [
        f"torch {environment.torch_version} (CUDA {environment.torch_cuda or 'none: CPU-only build'})",
        f"CUDA devices: {devices}",
        tinycudann_line(environment),
        f"CUDA compiler (nvcc): {environment.nvcc or 'not found'}",
        f"gsplat: {'installed' if environment.gsplat else 'not installed'}",
    ]


def tinycudann_line(environment: Environment) -> str:
    if environment.tinycudann:
        return "tiny-cuda-nn: installed; nerfacto's hash grids and MLPs run in its fused kernels"
    return (
        "tiny-cuda-nn: not installed. It is not on the package registries (it is built from its source tree with "
        "nvcc), so it is not installed here; nerfacto runs on nerfstudio's pure-torch fallback (the same model, "
        "slower hash grids and MLPs), and every time below is of that fallback. --tcnn-source PATH builds a local "
        "checkout when nvcc exists."
    )


def install_tinycudann(source: Path, environment: Environment, log_path: Path, timeout_s: float) -> None:
    """Build and install tiny-cuda-nn's torch bindings from a local checkout (no network); raise on failure."""
    if environment.nvcc is None:
        raise GpuCheckError(
            f"tcnn_source {source} was given but no CUDA compiler was found (nvcc on PATH or in $CUDA_HOME/bin); "
            "tiny-cuda-nn cannot be built here"
        )
    command = [sys.executable, "-m", "pip", "install", "--no-build-isolation", str(source / "bindings" / "torch")]
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w", encoding="utf8") as output:
        result = subprocess.run(command, stdout=output, stderr=subprocess.STDOUT, timeout=timeout_s)
    if result.returncode != 0:
        raise GpuCheckError(f"building tiny-cuda-nn from {source} failed (status {result.returncode}); log {log_path}")
