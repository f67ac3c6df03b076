"""``s2camp-bench scaling``: cost of P and of the camera optimizer's per-step work against images, rays and ranks.

Three measurements, each on this machine's processes (docs/SCALING.md turns them into the multi-GPU picture):

1. P for many cameras at L = 500 (``compute_preconditioner``, chunks of ``chunk_size`` cameras): seconds and peak
   memory (growth of the resident set) in a fresh subprocess per cell, every camera with its own intrinsics (the
   refreshed P of a refined run: no two cameras share intrinsics), plus the start of a run where all cameras share
   one set of intrinsics (computed once), and one unchunked cell of the same size as the baseline of the memory
   ratio.
2. The camera optimizer's work in one training step on one rank: P^-1 phi_hat and the refined pose and
   intrinsics of the cameras the rays come from, the regenerated rays of the rank's batch, and the backward pass
   to the latents (the default shared intrinsics: all cameras here are one physical camera).
3. What DDP communicates for the cameras per step: an all-reduce of the dense phi_hat gradient (N x K float32)
   and of the 8-byte refresh-request flag, timed with gloo between processes of this machine.
"""

from __future__ import annotations

import multiprocessing
import os
import resource
import socket
import statistics
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from s2camp_bench.report import markdown_table
from s2camp_ns.core.camera import Intrinsics
from s2camp_ns.core.preconditioner import DEFAULT_CHUNK_SIZE, SamplingConfig, compute_preconditioner

from .common import DEFAULT_OUTPUT_DIR, FRUSTA, log, write_report

NUM_PARAMS = 12
"""K, all camera parameters (the paper's setting and the s2camp default)."""


@dataclass
class ScalingConfig:
    """Cost of P and of the per-step camera work as a function of cameras, rays per rank and ranks."""

    cameras: tuple[int, ...] = (1_000, 10_000, 100_000)
    """Cameras of the P cells (each with its own intrinsics)."""
    num_points: int = 500
    """L, proxy points per camera."""
    chunk_size: int = DEFAULT_CHUNK_SIZE
    """Cameras per chunk of the P computation."""
    unchunked_cameras: int = 4_096
    """Size of the unchunked baseline cell (one batch: memory grows with the cameras), above ``chunk_size``; a
    chunked cell of the same size is measured with it."""
    repeats: int = 3
    """Timed repetitions of each P cell below 50k cameras (median, min and max reported)."""
    large_repeats: int = 2
    """Timed repetitions of the P cells with 50k cameras or more."""
    step_cameras: tuple[int, ...] = (100, 1_000, 10_000, 100_000)
    """Cameras N of the per-step cells."""
    step_rays: tuple[int, ...] = (1_024, 4_096)
    """Rays per rank R of the per-step cells."""
    step_repeats: int = 7
    """Timed repetitions of each per-step cell after a warm-up."""
    ranks: tuple[int, ...] = (2,)
    """gloo process counts of the all-reduce cells (this machine has 2 cores)."""
    allreduce_repeats: int = 20
    quick: bool = False
    """Small run for CI: hundreds of cameras, one repeat."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    """Folder of the report and plots (``--output-dir docs/benchmarks`` rewrites the committed ones)."""
    write: bool = True
    json: bool = False

    def effective(self) -> ScalingConfig:
        if not self.quick:
            return self
        return replace(
            self,
            cameras=(200,),
            unchunked_cameras=200,
            chunk_size=64,
            repeats=1,
            large_repeats=1,
            step_cameras=(100, 1_000),
            step_rays=(256,),
            step_repeats=2,
            allreduce_repeats=3,
        )


def distinct_intrinsics(cameras: int) -> Intrinsics:
    """``cameras`` room cameras with slightly different focal lengths and principal points (nothing shared)."""
    preset = FRUSTA["room"]
    jitter = torch.linspace(0.98, 1.02, cameras, dtype=torch.float64)
    return Intrinsics.create(
        fx=preset.fx * jitter,
        fy=preset.fy * jitter,
        cx=preset.cx * jitter,
        cy=preset.cy,
        width=preset.width,
        height=preset.height,
    )


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _measure_p(cameras: int, num_points: int, chunk_size: int | None, shared: bool, repeats: int, queue) -> None:
    """Subprocess body: seconds (every repeat) and peak resident-set growth of one P cell."""
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", torch.get_num_threads())))
    sampling = SamplingConfig(num_points=num_points)
    compute_preconditioner(distinct_intrinsics(4), sampling=sampling)  # warm-up: lattice table, kernels
    intrinsics = (
        distinct_intrinsics(1)[torch.zeros(cameras, dtype=torch.long)] if shared else distinct_intrinsics(cameras)
    )
    before = _peak_rss_mb()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = compute_preconditioner(intrinsics, sampling=sampling, chunk_size=chunk_size)
        times.append(time.perf_counter() - start)
        del result
    queue.put({"times": times, "peak_mb": _peak_rss_mb() - before, "baseline_rss_mb": before})


def _in_subprocess(target, *args) -> dict:
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=target, args=(*args, queue))
    process.start()
    result = queue.get()
    process.join()
    if process.exitcode != 0:
        raise RuntimeError(f"benchmark subprocess failed with exit code {process.exitcode}")
    return result


def p_rows(config: ScalingConfig) -> list[dict]:
    cells = [("distinct", n, config.chunk_size) for n in sorted({*config.cameras, config.unchunked_cameras})]
    cells.append(("unchunked", config.unchunked_cameras, None))
    cells.append(("shared", max(config.cameras), config.chunk_size))
    rows = []
    for kind, cameras, chunk in cells:
        repeats = config.large_repeats if cameras >= 50_000 else config.repeats
        result = _in_subprocess(_measure_p, cameras, config.num_points, chunk, kind == "shared", repeats)
        times = result["times"]
        row = {
            "kind": "P",
            "intrinsics": kind,
            "cameras": cameras,
            "L": config.num_points,
            "chunk": "all" if chunk is None else chunk,
            "seconds": statistics.median(times),
            "seconds_min": min(times),
            "seconds_max": max(times),
            "repeats": len(times),
            "peak_mb": result["peak_mb"],
            "us_per_camera": 1e6 * statistics.median(times) / cameras,
        }
        rows.append(row)
        log(
            f"scaling P {kind:9s} cameras={cameras} chunk={row['chunk']} {row['seconds']:.2f} s "
            f"[{row['seconds_min']:.2f}, {row['seconds_max']:.2f}] peak {row['peak_mb']:.0f} MB"
        )
    baseline = next(r for r in rows if r["intrinsics"] == "unchunked")
    same_size = next((r for r in rows if r["intrinsics"] == "distinct" and r["cameras"] == baseline["cameras"]), None)
    if same_size is not None:
        same_size["memory_vs_unchunked"] = same_size["peak_mb"] / max(baseline["peak_mb"], 1e-9)
        same_size["time_vs_unchunked"] = same_size["seconds"] / baseline["seconds"]
        baseline["memory_vs_unchunked"] = baseline["time_vs_unchunked"] = 1.0
    return rows


def _step_optimizer(cameras: int):
    """The s2camp camera optimizer over ``cameras`` room cameras, P left at the identity (its cost is in part 1)."""
    from nerfstudio.cameras.cameras import Cameras, CameraType

    from s2camp_ns.camera_optimizer import S2CampCameraOptimizer, S2CampCameraOptimizerConfig

    preset = FRUSTA["room"]
    generator = torch.Generator().manual_seed(0)
    c2w = torch.eye(4)[:3].expand(cameras, 3, 4).clone()
    c2w[:, :, 3] = torch.randn(cameras, 3, generator=generator)
    nerfstudio_cameras = Cameras(
        camera_to_worlds=c2w,
        fx=preset.fx,
        fy=preset.fy,
        cx=preset.cx,
        cy=preset.cy,
        width=preset.width,
        height=preset.height,
        camera_type=CameraType.PERSPECTIVE,
    )
    optimizer = S2CampCameraOptimizer(S2CampCameraOptimizerConfig(), num_cameras=cameras, device="cpu")
    optimizer.refiner.last_refresh_step.fill_(0)  # skip the initial P: part 1 measures it
    optimizer.set_train_cameras(nerfstudio_cameras)
    with torch.no_grad():
        for latent in optimizer.parameters():
            latent.normal_(0.0, 1e-3, generator=generator)
    return optimizer


def _one_step(optimizer, indices: torch.Tensor, pixels: torch.Tensor) -> None:
    """Forward and backward of the camera part of one training step for the rays ``indices`` / ``pixels``."""
    from nerfstudio.cameras.rays import RayBundle

    from s2camp_ns.method.rays import PIXEL_KEY

    rays = indices.shape[0]
    bundle = RayBundle(
        origins=torch.zeros(rays, 3),
        directions=torch.zeros(rays, 3),
        pixel_area=torch.ones(rays, 1),
        camera_indices=indices,
        metadata={PIXEL_KEY: pixels, "directions_norm": torch.ones(rays, 1)},
    )
    optimizer.zero_grad(set_to_none=True)
    optimizer.apply_to_raybundle(bundle)
    (bundle.origins.sum() + bundle.directions.sum()).backward()


def step_rows(config: ScalingConfig) -> list[dict]:
    preset = FRUSTA["room"]
    rows = []
    for cameras in config.step_cameras:
        optimizer = _step_optimizer(cameras)
        for rays in config.step_rays:
            generator = torch.Generator().manual_seed(1)
            indices = torch.randint(cameras, (rays, 1), generator=generator)
            pixels = torch.rand(rays, 2, generator=generator) * torch.tensor([preset.width, preset.height])
            _one_step(optimizer, indices, pixels)
            times = []
            for _ in range(config.step_repeats):
                start = time.perf_counter()
                _one_step(optimizer, indices, pixels)
                times.append(time.perf_counter() - start)
            row = {
                "kind": "step",
                "cameras": cameras,
                "rays": rays,
                "ms": 1e3 * statistics.median(times),
                "ms_min": 1e3 * min(times),
                "ms_max": 1e3 * max(times),
                "gradient_bytes": 4 * sum(p.numel() for p in optimizer.parameters()),
            }
            rows.append(row)
            spread = f"[{row['ms_min']:.2f}, {row['ms_max']:.2f}]"
            log(f"scaling step cameras={cameras} rays={rays} {row['ms']:.2f} ms {spread}")
    return rows


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _allreduce_worker(rank: int, world_size: int, port: int, sizes: list[int], repeats: int, queue) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", world_size=world_size, rank=rank)
    results = {}
    for numel in sizes:
        tensor = torch.ones(numel, dtype=torch.int64 if numel == 1 else torch.float32)
        dist.all_reduce(tensor)  # warm-up (connection set-up)
        times = []
        for _ in range(repeats):
            dist.barrier()
            start = time.perf_counter()
            dist.all_reduce(tensor)
            times.append(time.perf_counter() - start)
        results[numel] = times
    dist.destroy_process_group()
    if rank == 0:
        queue.put(results)


def allreduce_rows(config: ScalingConfig) -> list[dict]:
    sizes = [1] + [n * NUM_PARAMS for n in config.step_cameras]
    rows = []
    context = multiprocessing.get_context("spawn")
    for world_size in config.ranks:
        queue = context.Queue()
        port = _free_port()
        processes = [
            context.Process(
                target=_allreduce_worker, args=(rank, world_size, port, sizes, config.allreduce_repeats, queue)
            )
            for rank in range(world_size)
        ]
        for process in processes:
            process.start()
        results = queue.get()
        for process in processes:
            process.join()
        for numel, times in results.items():
            cameras = numel // NUM_PARAMS
            payload = "refresh flag (int64)" if numel == 1 else f"latent gradient, {cameras} cameras x K = 12"
            rows.append(
                {
                    "kind": "allreduce",
                    "ranks": world_size,
                    "payload": payload,
                    "bytes": 8 if numel == 1 else 4 * numel,
                    "ms": 1e3 * statistics.median(times),
                    "ms_min": 1e3 * min(times),
                    "ms_max": 1e3 * max(times),
                }
            )
            log(f"scaling allreduce ranks={world_size} {payload}: {rows[-1]['ms']:.3f} ms")
    return rows


def run(config: ScalingConfig) -> list[dict]:
    config = config.effective()
    return p_rows(config) + step_rows(config) + allreduce_rows(config)


def report(rows: list[dict], config: ScalingConfig) -> Path:
    config = config.effective()
    p_cells = [r for r in rows if r["kind"] == "P"]
    step_cells = [r for r in rows if r["kind"] == "step"]
    allreduce_cells = [r for r in rows if r["kind"] == "allreduce"]
    return write_report(
        config.output_dir,
        "scaling",
        "Scaling: P and the camera optimizer's per-step work",
        "s2camp-bench scaling",
        [
            f"Threads: {torch.get_num_threads()} (OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}). "
            "What these numbers mean for many GPUs: [docs/SCALING.md](../SCALING.md).",
            f"## P for many cameras (L = {config.num_points}, all 12 parameters, float64)",
            markdown_table(
                p_cells,
                [
                    "intrinsics",
                    "cameras",
                    "chunk",
                    "seconds",
                    "seconds_min",
                    "seconds_max",
                    "repeats",
                    "us_per_camera",
                    "peak_mb",
                    "memory_vs_unchunked",
                    "time_vs_unchunked",
                ],
            ),  # fmt: skip
            "Each cell in a fresh subprocess: seconds is the median of the repeats (min and max beside it), peak_mb "
            "the growth of the resident set over the process after its warm-up. `distinct`: every camera has its "
            "own intrinsics (a refresh with intrinsics refined per image, `intrinsics per-image`; the default "
            "refines them per physical camera and computes P once per physical camera); `shared`: all cameras "
            "share one set of intrinsics (computed once); `unchunked`: one batch, the baseline of the ratios "
            "(same run, same size). On a shared machine the spread between min and max is the load of other "
            "jobs, not the method.",
            "## Camera optimizer work per training step, per rank",
            markdown_table(step_cells, ["cameras", "rays", "ms", "ms_min", "ms_max", "gradient_bytes"]),
            "Forward and backward of the camera part of one step (P^-1 phi_hat, refined pose and intrinsics of "
            "the cameras the rays come from, rays regenerated through their pixels), median of the repeats after a "
            "warm-up; what still grows with N is the dense gradient of the N x K latent. The same on every rank "
            "whatever the number of ranks.",
            "## What DDP communicates for the cameras per step (gloo, processes on this machine)",
            markdown_table(allreduce_cells, ["ranks", "payload", "bytes", "ms", "ms_min", "ms_max"]),
            "The latents' gradient travels inside DDP's gradient buckets with the field's parameters; it is timed "
            "here on its own (K = 12 per camera: intrinsics per image; the default shares them per physical "
            "camera, half the bytes). The flag is the one collective S2CamP adds, every refresh-request-every "
            "steps (refreshes requested from the viewer).",
        ],
    )


__all__ = ["ScalingConfig", "report", "run"]
