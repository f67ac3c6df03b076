"""Time and peak memory to compute P for many cameras: S2CamP against a CamP-style baseline, in one run.

S2CamP: L = 500 deterministic lattice points per camera and the closed-form Jacobian (s2camp_ns.core.jacobian).
CamP-style baseline: CamP's published proxy points (5000 per camera: random pixel, power-ladder distance along the
ray, ``CAMP_SAMPLING``) and the Jacobian by forward-mode autodiff (torch.func.jacfwd, vmapped over cameras), as CamP
does with JAX.
Both then form the Gram matrix in float64, damp it and take the symmetric square root by eigendecomposition.
Each method runs in a fresh subprocess so that its peak memory (resident set growth on the CPU, allocator peak on
CUDA) is its own. Scaling in L and in the number of cameras is measured for S2CamP in-process.
"""

from __future__ import annotations

import multiprocessing
import resource
import statistics
import time
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import torch
from torch.func import jacfwd, vmap

from s2camp_bench.report import markdown_table
from s2camp_ns.core.camera import Intrinsics, ParameterLayout, in_image, project, project_with_delta
from s2camp_ns.core.jacobian import gram_matrix
from s2camp_ns.core.preconditioner import (
    CAMP_SAMPLING,
    DampingConfig,
    SamplingConfig,
    compute_preconditioner,
    damped_gram,
    sample_proxy_points,
    symmetric_sqrt_and_inverse,
)

from .common import DEFAULT_OUTPUT_DIR, FRUSTA, log, write_report


@dataclass
class SpeedConfig:
    """Time to compute the preconditioner for a batch of cameras."""

    cameras: int = 300
    """Cameras in the batch (the room scene has about 300 images)."""
    s2camp_points: int = 500
    baseline_points: int = 5000
    repeats: int = 3
    """Timed repetitions of S2CamP after one warm-up; the median is reported."""
    baseline_repeats: int = 1
    """Timed repetitions of the (much slower) baseline after one warm-up."""
    baseline_chunk: int = 100
    """Cameras per vmapped autodiff call in the baseline (bounds its memory)."""
    scaling_points: tuple[int, ...] = (125, 250, 500, 1000, 2000, 4000)
    scaling_cameras: tuple[int, ...] = (75, 150, 300, 600, 1200)
    device: str = "auto"
    """"auto" uses CUDA when available."""
    quick: bool = False
    """Small run for CI: 20 cameras, one repeat, short scaling sweeps."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False

    def effective(self) -> SpeedConfig:
        if not self.quick:
            return self
        return replace(self, cameras=20, repeats=1, scaling_points=(125, 500), scaling_cameras=(10, 20))

    def torch_device(self) -> torch.device:
        if self.device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        return torch.device(self.device)


def batch_intrinsics(cameras: int, device: torch.device) -> Intrinsics:
    """``cameras`` copies of the room camera with slightly varied focal lengths (so no work can be shared)."""
    preset = FRUSTA["room"]
    jitter = torch.linspace(0.98, 1.02, cameras, dtype=torch.float64)
    return Intrinsics.create(
        fx=preset.fx * jitter,
        fy=preset.fy * jitter,
        cx=preset.cx,
        cy=preset.cy,
        width=preset.width,
        height=preset.height,
        device=device,
    )


def s2camp_preconditioner(intrinsics: Intrinsics, num_points: int) -> torch.Tensor:
    return compute_preconditioner(intrinsics, ParameterLayout(), SamplingConfig(num_points=num_points)).matrix


def _autodiff_jacobian(points: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    def one_camera(camera_points, fx, fy, cx, cy, skew, k1, k2, width, height):
        camera = Intrinsics(*(v.reshape(1) for v in (fx, fy, cx, cy, skew, k1, k2, width, height)))

        def stacked_projection(delta):
            return project_with_delta(camera_points[None], camera, delta[None])[0]

        return jacfwd(stacked_projection)(torch.zeros(12, dtype=camera_points.dtype, device=camera_points.device))

    fields = (
        intrinsics.fx,
        intrinsics.fy,
        intrinsics.cx,
        intrinsics.cy,
        intrinsics.skew,
        intrinsics.k1,
        intrinsics.k2,
        intrinsics.width,
        intrinsics.height,
    )
    return vmap(one_camera)(points, *fields)


def camp_baseline_preconditioner(intrinsics: Intrinsics, num_points: int, chunk: int) -> torch.Tensor:
    points = sample_proxy_points(intrinsics, replace(CAMP_SAMPLING, num_points=num_points))
    sigmas = []
    for start in range(0, intrinsics.num_cameras, chunk):
        part = intrinsics[start : start + chunk]
        jacobian = _autodiff_jacobian(points[start : start + chunk], part)
        pixels, depth = project(points[start : start + chunk], part)
        sigma, _ = gram_matrix(jacobian, in_image(pixels, depth, part), part.image_scale())
        sigmas.append(sigma)
    matrix, _ = symmetric_sqrt_and_inverse(damped_gram(torch.cat(sigmas), DampingConfig()))
    return matrix


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_call(function, device: torch.device, repeats: int) -> float:
    function()  # warm-up: caches the lattice, loads kernels
    _synchronize(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        _synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _measure(method: str, config: SpeedConfig, queue) -> None:
    """Subprocess body: time one method and report its own peak memory."""
    device = config.torch_device()
    intrinsics = batch_intrinsics(config.cameras, device)
    baseline_rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    if method == "s2camp":
        seconds = time_call(partial(s2camp_preconditioner, intrinsics, config.s2camp_points), device, config.repeats)
    else:
        seconds = time_call(
            lambda: camp_baseline_preconditioner(intrinsics, config.baseline_points, config.baseline_chunk),
            device,
            config.baseline_repeats,
        )
    if device.type == "cuda":
        peak_mb = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - baseline_rss_kb) / 1024
    queue.put({"seconds": seconds, "peak_mb": peak_mb, "device": str(device)})


def measure_in_subprocess(method: str, config: SpeedConfig) -> dict:
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=_measure, args=(method, config, queue))
    process.start()
    result = queue.get()
    process.join()
    return result


def run(config: SpeedConfig) -> list[dict]:
    config = config.effective()
    device = config.torch_device()
    rows = []
    for method, points in (("s2camp", config.s2camp_points), ("camp-baseline", config.baseline_points)):
        result = measure_in_subprocess(method, config)
        rows.append(
            {
                "kind": "comparison",
                "method": method,
                "cameras": config.cameras,
                "L": points,
                "jacobian": "analytic" if method == "s2camp" else "autodiff",
                **result,
            }
        )
        log(
            f"speed {method:14s} cameras={config.cameras} L={points} {result['seconds']:.3f} s "
            f"peak {result['peak_mb']:.0f} MB"
        )
    baseline_seconds = rows[1]["seconds"]
    for row in rows:
        row["speedup_vs_baseline"] = baseline_seconds / row["seconds"]
    for points in config.scaling_points:
        intrinsics = batch_intrinsics(config.cameras, device)
        seconds = time_call(partial(s2camp_preconditioner, intrinsics, points), device, config.repeats)
        rows.append(
            {
                "kind": "scaling-L",
                "method": "s2camp",
                "cameras": config.cameras,
                "L": points,
                "seconds": seconds,
                "device": str(device),
            }
        )
    for cameras in config.scaling_cameras:
        intrinsics = batch_intrinsics(cameras, device)
        seconds = time_call(partial(s2camp_preconditioner, intrinsics, config.s2camp_points), device, config.repeats)
        rows.append(
            {
                "kind": "scaling-cameras",
                "method": "s2camp",
                "cameras": cameras,
                "L": config.s2camp_points,
                "seconds": seconds,
                "device": str(device),
            }
        )
    for row in rows[2:]:
        row["seconds_per_point_camera"] = row["seconds"] / (row["L"] * row["cameras"])
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(8.4, 3.6))
    for axis, kind, key, label in (
        (axes[0], "scaling-L", "L", "L (points per camera)"),
        (axes[1], "scaling-cameras", "cameras", "cameras"),
    ):
        cells = [r for r in rows if r["kind"] == kind]
        xs, ys = [r[key] for r in cells], [r["seconds"] for r in cells]
        axis.loglog(xs, ys, marker="o", label="S2CamP (measured)")
        if cells:
            axis.loglog(xs, [ys[0] * x / xs[0] for x in xs], "--", color="gray", label="linear")
        axis.set_xlabel(label)
        axis.set_ylabel("seconds to compute P")
        axis.grid(True, which="both", alpha=0.3)
        axis.legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)


def report(rows: list[dict], config: SpeedConfig) -> Path:
    plot(rows, config.output_dir / "speed.png")
    comparison = [r for r in rows if r["kind"] == "comparison"]
    scaling = [r for r in rows if r["kind"] != "comparison"]
    return write_report(
        config.output_dir,
        "speed",
        "Time to compute the preconditioner",
        "s2camp-bench speed",
        [
            "## S2CamP vs CamP-style baseline, same run",
            markdown_table(
                comparison, ["method", "cameras", "L", "jacobian", "seconds", "peak_mb", "speedup_vs_baseline"]
            ),
            "Median of the timed repetitions after a warm-up; each method in its own subprocess. Peak memory is the "
            "growth of the resident set on the CPU (allocator peak on CUDA).",
            "## Scaling of S2CamP",
            markdown_table(scaling, ["kind", "cameras", "L", "seconds", "seconds_per_point_camera"]),
            "![scaling](speed.png)",
        ],
    )
