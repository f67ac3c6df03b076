"""``make gpu-check`` / ``python -m s2camp_ns.benchmarks.gpu_check``: the stages in order, the report, the exit status.

1. the machine: CUDA devices (refused without one), tiny-cuda-nn (missing: said so, nerfstudio's torch fallback
   runs), nvcc, gsplat; ``--tcnn-source`` builds a local tiny-cuda-nn checkout;
2. ``pytest -m cuda``: every test marked ``cuda`` must pass, none may skip;
3. the scene: mip-NeRF 360 room at images_4 size (``config.ROOM_IMAGES_4``);
4. nerfacto, s2camp-so3xr3, s2camp and s2camp-camp trained one after the other on the perturbed scene: time per
   iteration against nerfacto, peak CUDA memory, camera errors from the perturbed start, held-out PSNR;
5. with two GPUs, ``ns-train s2camp --machine.num-devices 2`` (NCCL).

The exit status is 0 only if every stage that ran passed; 2 when the check cannot run (no CUDA, bad options).
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import replace

import tyro
from rich.console import Console

from . import report
from .config import DOCS_REPORT, GpuCheckConfig
from .environment import GpuCheckError, describe, detect_environment, install_tinycudann, require_cuda
from .runs import (
    EXPERIMENT,
    cuda_tests_result,
    generate_scene,
    junit_counts,
    method_result,
    run_cuda_tests,
    run_nccl,
    train_method,
)

CONSOLE = Console()


def setup_text(config: GpuCheckConfig) -> str:
    """How the runs were made, above the training table."""
    s = config.scene
    a = config.alignment
    smoke = (
        "**CPU smoke run of the script itself (`--cpu-smoke`): tiny scene, small nerfacto, a few steps on the CPU. "
        "Not a GPU check; the numbers mean nothing.** "
        if config.cpu_smoke
        else ""
    )
    return smoke + (
        f"Each method trains {config.iterations} steps of {config.rays_per_batch} rays from scratch with its default "
        f"options (mixed precision on) on a generated scene of {s.num_cameras} images {s.width}x{s.height} "
        f"(every 8th held out) whose training cameras are perturbed by CamP's protocol "
        f"(`s2camp-data --perturbation.enabled True`); s2camp refreshes P every {config.refresh_every} steps "
        f"(its default is 1000). Time per iteration: mean over the steps after the first {config.warmup_steps}, "
        "each stamped after `torch.cuda.synchronize()`. Peak memory: `torch.cuda.max_memory_allocated()` of the "
        "training process at the end of training. Camera errors: perturbed start → end, mean over the training "
        "cameras after a similarity alignment to the true ones (rotation in degrees, position in scene units, "
        f"focal in px). PSNR: held-out views after {a.steps} test-time alignment steps of {a.rays} rays "
        "(`s2camp-eval`'s protocol). nerfacto is nerfstudio's stock method, fed the same data by `s2camp-data`."
    )


def run(config: GpuCheckConfig) -> bool:
    """Run the check; write the report; True when everything that ran passed. Raises GpuCheckError when it
    cannot run at all."""
    began = time.perf_counter()
    config = config.effective()
    config.validate()
    if config.report_from is not None:
        return rebuild_report(config)
    environment = detect_environment()
    if not config.cpu_smoke:
        require_cuda(environment)
    config.output_dir.mkdir(parents=True, exist_ok=True)
    stages: list[report.StageResult] = []
    if config.tcnn_source is not None:
        stages.append(build_tinycudann(config, environment))
        environment = detect_environment()
    lines = describe(environment)
    for line in lines:
        CONSOLE.print(line)
    config.environment_path.write_text("\n".join(lines) + "\n", encoding="utf8")
    if "tests" in config.stages:
        stages.append(announced("pytest -m cuda", lambda: run_cuda_tests(config)))
    results: list[report.MethodResult] = []
    if "train" in config.stages or "nccl" in config.stages:
        stages.append(announced("scene", lambda: generate_scene(config)))
        scene = config.scene_dir if stages[-1].passed else None
        if scene is not None and "train" in config.stages:
            results, notes = train_all(config, scene)
            lines.extend(notes)
        if scene is not None and "nccl" in config.stages:
            command = "ns-train s2camp --machine.num-devices 2"
            stages.append(announced(command, lambda: run_nccl(config, scene, environment.device_count)))

    minutes = (time.perf_counter() - began) / 60.0
    return write_reports(config, lines, stages, results, minutes, "make gpu-check")


def write_reports(
    config: GpuCheckConfig,
    lines: list[str],
    stages: list[report.StageResult],
    results: list[report.MethodResult],
    minutes: float | None,
    command: str,
) -> bool:
    """Write the report (and with ``write_docs`` the committed one), print it; True when all of it passed."""
    arguments = (lines, stages, results, setup_text(config), config.baseline, minutes, config.time_budget_minutes)
    config.output_dir.mkdir(parents=True, exist_ok=True)
    path = report.write(config.report_path, *arguments, command)
    if config.write_docs:
        report.write(DOCS_REPORT / "gpu-check.md", *arguments, command)
    print(path.read_text(), flush=True)
    CONSOLE.print(f"report: {path}")
    return report.all_passed(stages, results)


def rebuild_report(config: GpuCheckConfig) -> bool:
    """The report of the check whose output folder is ``config.report_from``, from what it left there: the machine
    (``environment.txt``), the ``cuda`` tests' JUnit file and each method's measurements (``runs/<method>.json``; a
    run without its evaluation is a failed row). Written like a finished check's; True when all of it passed."""
    folder = config.report_from
    earlier = replace(config, output_dir=folder)  # the layout of the earlier check's folder
    environment = earlier.environment_path
    lines = environment.read_text(encoding="utf8").splitlines() if environment.is_file() else []
    lines = lines or ["the machine is not recorded in this folder (no environment.txt)"]
    lines.append(
        f"Rebuilt from `{folder.as_posix()}` (`--report-from`): the stages that left nothing there (the scene, NCCL) "
        "are not in the tables."
    )
    stages = []
    junit = earlier.junit_path
    if junit.is_file():  # pytest's own counts: passed only if every collected test ran and passed
        stages.append(cuda_tests_result(0, junit_counts(junit), junit.with_suffix(".log"), 0.0))
    results = []
    for method in config.methods:
        path = earlier.measurements_path(method)
        if path.is_file():
            results.append(method_result(method, json.loads(path.read_text()), config.warmup_steps, None))
    command = f"python -m s2camp_ns.benchmarks.gpu_check --report-from {folder.as_posix()}" + (
        " --write-docs" if config.write_docs else ""
    )
    return write_reports(config, lines, stages, results, None, command)


def announced(what: str, stage) -> report.StageResult:
    """Run ``stage`` (returns a StageResult) between a line naming it and a line with its outcome."""
    CONSOLE.print(f">>> {what}", highlight=False)
    result = stage()
    CONSOLE.print(f"    {result.detail}", highlight=False)
    return result


def build_tinycudann(config: GpuCheckConfig, environment) -> report.StageResult:
    name = "tiny-cuda-nn build"
    log_path = config.logs_dir / "tinycudann.log"
    try:
        install_tinycudann(config.tcnn_source, environment, log_path, 60 * config.run_timeout_minutes)
    except GpuCheckError as error:
        return report.StageResult(name, False, str(error))
    return report.StageResult(name, True, f"from {config.tcnn_source}")


def train_all(config: GpuCheckConfig, scene) -> tuple[list[report.MethodResult], list[str]]:
    """Every method, one after the other; the results and notes for the report (LPIPS left out)."""
    results, notes = [], []
    for method in config.methods:
        CONSOLE.print(f">>> ns-train {method}", highlight=False)
        result, measured = train_method(config, method, scene)
        results.append(result)
        if measured is not None and measured.get("lpips_left_out"):
            notes.append(f"{method}: LPIPS left out (torchvision's AlexNet weights are not cached and not reachable)")
        CONSOLE.print(f"    {'passed' if result.error is None else result.error}", highlight=False)
    for checkpoints in config.runs_dir.glob(f"{EXPERIMENT}/*/*/nerfstudio_models"):
        shutil.rmtree(checkpoints)  # nerfacto-sized checkpoints with Adam's moments: not needed afterwards
    return results, notes


def main(config: GpuCheckConfig) -> int:
    try:
        passed = run(config)
    except (GpuCheckError, ValueError) as error:
        CONSOLE.print(f"[bold red]gpu-check: {error}", highlight=False)
        return 2
    CONSOLE.print("[bold green]gpu-check passed" if passed else "[bold red]gpu-check FAILED (see the report)")
    return 0 if passed else 1


def entrypoint() -> None:
    raise SystemExit(main(tyro.cli(GpuCheckConfig, description=__doc__)))
