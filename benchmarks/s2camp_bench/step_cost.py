"""``s2camp-bench step-cost``: what the camera path adds to a training step on a launch-bound device (a GPU).

On a GPU each aten op that computes is a kernel launch and each op whose result the host reads is a synchronisation,
so a step's cost there follows its counts (``op_count``). Every method's ``ns-train`` configuration is built
in-process with nerfstudio's Trainer on a generated scene (the small nerfacto field, ``train_commands.SMALL_MODEL``: the
field's size changes no camera op), a few steps run, and one later step (not a logging step, not a refresh of P) is
counted phase by phase (``PHASES``: the callbacks before it; the batch and rays; the forward pass, where S2CamP casts
the rays through the refined cameras; metrics; loss; backward; the optimizers' steps; the callbacks after it, where
S2CamP's prior step, rotation removal, refresh schedule and viewer panel check run). Rows: methods x camera models x
intrinsics layout (S2CamP's methods) x viewer (S2CamP's panel attached or not); "off" is ``s2camp`` with
``--pipeline.model.camera-optimizer.mode off`` ("splat-off" likewise), and added ops and syncs are a row's minus its
model's "off" row. Beside the counts, the CPU time of the camera path alone (one batch's rays through the camera
optimizer, or one camera's view matrix, forward and backward), median of repeats.
"""


from __future__ import annotations

import contextlib
import copy
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import torch

from s2camp_bench.report import markdown_table
from s2camp_bench.scene.make_scene import MakeSceneConfig

from .common import DEFAULT_OUTPUT_DIR, changed_options, generated_scene, log, write_report
from .op_count import OpCount, OpCounter

NERFACTO_METHODS = ("off", "s2camp-so3xr3", "s2camp", "s2camp-camp")
SPLAT_METHODS = ("splat-off", "s2camp-splat-so3xr3", "s2camp-splat")
S2CAMP_METHODS = ("s2camp", "s2camp-camp", "s2camp-splat")
"""The methods with S2CamP's camera optimizer (intrinsics layouts and the viewer panel apply to them)."""
PHASES = ("before", "rays", "forward", "metrics", "loss", "backward", "optimizer", "after")

CAMERA_MODELS: dict[str, dict] = {
    "PINHOLE": dict(camera_model="PINHOLE", k1=0.0, k2=0.0),
    "OPENCV": dict(camera_model="OPENCV", k1=-0.02, k2=0.005, p1=0.001, p2=-0.0005),
    "OPENCV_FISHEYE": dict(camera_model="OPENCV_FISHEYE", k1=0.02, k2=-0.005, fov="wide"),
}
"""Generated scenes' COLMAP camera models and their distortion."""

SMALL_FIELD = dict(
    log2_hashmap_size=15, num_levels=8, max_res=128, num_nerf_samples_per_ray=32, num_proposal_samples_per_ray=(64, 32)
)
"""``train_commands.SMALL_MODEL`` as config fields."""


@dataclass
class StepCostConfig:
    """Aten ops and host syncs per training step, and the camera path's CPU time, per method and camera."""

    methods: tuple[str, ...] = NERFACTO_METHODS + SPLAT_METHODS
    camera_models: tuple[str, ...] = tuple(CAMERA_MODELS)
    intrinsics: tuple[str, ...] = ("per-camera", "per-image")
    """Intrinsics layouts of S2CamP's methods (``s2camp-camp`` is per image by definition)."""
    viewer: tuple[bool, ...] = (False, True)
    rays_per_batch: int = 4096
    counted_step: int = 13
    """The step counted, after ``counted_step`` steps run uncounted (not a multiple of the logging period, 10)."""
    timing_repeats: int = 30
    """Repetitions of the camera path's timing (median reported), after 3 warm-ups."""
    scene: MakeSceneConfig = field(
        default_factory=lambda: MakeSceneConfig(num_cameras=12, width=96, height=72, points_per_image=150, seed=0)
    )
    quick: bool = False
    """Small run for CI: PINHOLE, off / SO3xR3 / s2camp, per camera, viewer off, 512 rays, 3 steps."""
    scene_dir: Path | None = None
    """Where scenes and runs go (a temporary folder by default)."""
    output_dir: Path = DEFAULT_OUTPUT_DIR
    write: bool = True
    json: bool = False

    def command(self) -> str:
        """The ``s2camp-bench`` command line that regenerates this report."""
        if self.quick:
            return "s2camp-bench step-cost --quick"
        names = ("methods", "camera_models", "intrinsics", "viewer", "rays_per_batch", "timing_repeats")
        return " ".join(["s2camp-bench step-cost", *changed_options(self, StepCostConfig(), names)])

    def effective(self) -> StepCostConfig:
        if not self.quick:
            return self
        return replace(
            self, methods=("off", "s2camp-so3xr3", "s2camp"), camera_models=("PINHOLE",), intrinsics=("per-camera",),
            viewer=(False,), rays_per_batch=512, counted_step=3, timing_repeats=3,
            scene=replace(self.scene, num_cameras=6, width=48, height=36),
        )  # fmt: skip


def _method_config(method: str):
    from s2camp_ns import method_config

    specifications = {
        "off": method_config.s2camp_method, "s2camp": method_config.s2camp_method,
        "s2camp-camp": method_config.s2camp_camp_method, "s2camp-so3xr3": method_config.s2camp_so3xr3_method,
        "splat-off": method_config.s2camp_splat_method, "s2camp-splat": method_config.s2camp_splat_method,
        "s2camp-splat-so3xr3": method_config.s2camp_splat_so3xr3_method,
    }  # fmt: skip
    config = copy.deepcopy(specifications[method].config)
    if method.endswith("off"):
        config.pipeline.model.camera_optimizer.mode = "off"
    return config


def build_trainer(method: str, scene: Path, work: Path, intrinsics: str, rays_per_batch: int):
    """nerfstudio's Trainer of ``method`` on ``scene`` as ``ns-train`` builds it on the CPU, set up, not trained."""
    config = _method_config(method)
    config.machine.device_type = "cpu"
    config.pipeline.datamanager.data = scene
    config.output_dir = work
    config.timestamp = f"{method}-{intrinsics}"
    config.vis, config.max_num_iterations, config.steps_per_save = "tensorboard", 1000, 1000
    config.steps_per_eval_batch = config.steps_per_eval_image = config.steps_per_eval_all_images = 0
    config.logging.steps_per_log = 10
    model = config.pipeline.model
    if method in NERFACTO_METHODS:
        config.pipeline.datamanager.train_num_rays_per_batch = rays_per_batch
        for name, value in SMALL_FIELD.items():
            setattr(model, name, value)
    if method in S2CAMP_METHODS and method != "s2camp-camp":
        model.camera_optimizer.intrinsics = intrinsics
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def attach_viewer_stand_in(trainer) -> bool:
    """S2CamP's viewer panel attached as nerfstudio's viewer would attach it, with its per-step callback, but no
    panel update during the counted steps (a second's period is far longer than those steps; the update itself is
    the viewer's, once a second). False where the model has no panel."""
    model = trainer.pipeline.model
    panel = getattr(model, "S2CamP", None)
    if panel is None:
        return False
    panel._viewer = SimpleNamespace(trainer=trainer)
    panel.last_update = float("inf")
    panel.shown_refresh_step = model.refinement_status().last_refresh_step
    trainer.callbacks.extend(model.viewer_panel_callbacks())
    return True


def run_callbacks(trainer, step: int, where) -> None:
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=where)


def training_step(trainer, step: int, counter: OpCounter | None = None) -> None:
    """One step of nerfstudio's training loop (``Trainer.train_iteration`` and the callbacks around it), phase by
    phase under ``counter``; with the same calls in the same order as nerfstudio's Trainer."""
    import functools

    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    mark = counter.phase if counter is not None else (lambda label: None)
    pipeline, optimizers = trainer.pipeline, trainer.optimizers
    mark("before")
    run_callbacks(trainer, step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    mark("optimizer")
    optimizers.zero_grad_some(list(optimizers.parameters.keys()))
    with torch.autocast(device_type="cpu", enabled=trainer.mixed_precision):
        mark("rays")
        ray_bundle, batch = pipeline.datamanager.next_train(step)
        mark("forward")
        outputs = pipeline._model(ray_bundle)
        mark("metrics")
        metrics = pipeline.model.get_metrics_dict(outputs, batch)
        mark("loss")
        loss_dict = pipeline.model.get_loss_dict(outputs, batch, metrics)
        loss = functools.reduce(torch.add, loss_dict.values())
    mark("backward")
    trainer.grad_scaler.scale(loss).backward()
    mark("optimizer")
    optimizers.optimizer_scaler_step_some(trainer.grad_scaler, list(optimizers.parameters.keys()))
    scale = trainer.grad_scaler.get_scale()
    trainer.grad_scaler.update()
    if scale <= trainer.grad_scaler.get_scale():
        optimizers.scheduler_step_all(step)
    mark("after")
    run_callbacks(trainer, step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)


def optimizer_step_counts(trainer) -> frozenset[int]:
    """Storage addresses of the optimizers' step counts: torch's Adam keeps them in CPU scalars even for parameters on
    a GPU (without ``capturable`` or ``fused``), so reading them is no device synchronisation."""
    addresses = set()
    for optimizer in trainer.optimizers.optimizers.values():
        for state in optimizer.state.values():
            step = state.get("step")
            if isinstance(step, torch.Tensor):
                addresses.add(step.data_ptr())
    return frozenset(addresses)


def count_step(trainer, step: int) -> dict[str, OpCount]:
    """Run ``step`` uncounted steps, then count step ``step`` phase by phase."""
    for earlier in range(step):
        training_step(trainer, earlier)
    counter = OpCounter(optimizer_step_counts(trainer))
    with counter:
        training_step(trainer, step, counter)
    return counter.counts


def camera_path_function(trainer, method: str, rays_per_batch: int) -> Callable[[], None]:
    """The camera path of one step, forward and backward, as a function: the data manager's rays of one batch
    through the camera optimizer (nerfacto), or one training camera's view matrix (splatting)."""
    pipeline = trainer.pipeline
    model = pipeline.model
    if method in SPLAT_METHODS:
        camera, _ = pipeline.datamanager.next_train(0)

        def splat_path() -> None:
            viewmat = model.view_matrix(camera)
            if viewmat.requires_grad:
                viewmat.sum().backward()

        return splat_path
    datamanager = pipeline.datamanager
    image_batch = next(datamanager.iter_train_image_dataloader)
    sampler = datamanager.train_pixel_sampler
    sampler.set_num_rays_per_batch(rays_per_batch)
    indices = sampler.sample(image_batch)["indices"]

    def nerfacto_path() -> None:
        bundle = datamanager.train_ray_generator(indices)
        model.camera_optimizer.apply_to_raybundle(bundle)
        total = bundle.origins.sum() + bundle.directions.sum()
        if total.requires_grad:
            total.backward()

    return nerfacto_path


def median_seconds(function: Callable[[], None], repeats: int) -> float:
    for _ in range(3):
        function()
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds)


def measure(config: StepCostConfig, scenes: dict[str, Path], work: Path) -> list[dict]:
    rows = []
    for camera_model, scene in scenes.items():
        for method in config.methods:
            layouts = config.intrinsics if method in ("s2camp", "s2camp-splat") else ("-",)
            for intrinsics in layouts:
                for viewer in config.viewer if method in S2CAMP_METHODS else (False,):
                    log(f"step-cost: {method} {camera_model} intrinsics {intrinsics} viewer {viewer}")
                    layout = intrinsics if intrinsics != "-" else "per-camera"
                    trainer = build_trainer(method, scene, work, layout, config.rays_per_batch)
                    if viewer:
                        attach_viewer_stand_in(trainer)
                    counts = count_step(trainer, config.counted_step)
                    path = camera_path_function(trainer, method, config.rays_per_batch)
                    seconds = median_seconds(path, config.timing_repeats)
                    rows.append(_row(method, camera_model, intrinsics, viewer, counts, seconds))
    return with_added(rows)


def _row(method: str, camera_model: str, intrinsics: str, viewer: bool, counts: dict, seconds: float) -> dict:
    whole = OpCount()
    for count in counts.values():
        whole.add(count)
    row = {
        "method": method, "model": "splatfacto" if method in SPLAT_METHODS else "nerfacto",
        "camera_model": camera_model, "intrinsics": intrinsics, "viewer": "on" if viewer else "off",
        "ops": whole.total, "launches": whole.launches, "syncs": whole.num_syncs,
        "sync_ops": ", ".join(f"{name} x{n}" for name, n in sorted(whole.syncs.items())) or "-",
        "camera_path_ms": 1e3 * seconds,
    }  # fmt: skip
    for phase in PHASES:
        count = counts.get(phase, OpCount())
        row[f"ops_{phase}"] = count.total
        row[f"syncs_{phase}"] = count.num_syncs
    return row


def with_added(rows: list[dict]) -> list[dict]:
    """Each row's ops and syncs minus those of its model's "off" row on the same camera model, and ratios of the
    added ops to nerfstudio's SO3xR3's (same model and camera)."""

    def find(method: str, row: dict) -> dict | None:
        matches = [r for r in rows if r["method"] == method and r["camera_model"] == row["camera_model"]]
        return matches[0] if matches else None

    for row in rows:
        splat = row["model"] == "splatfacto"
        off = find("splat-off" if splat else "off", row)
        if off is None:
            continue
        row["added_ops"] = row["ops"] - off["ops"]
        row["added_launches"] = row["launches"] - off["launches"]
        row["added_syncs"] = row["syncs"] - off["syncs"]
    for row in rows:
        reference = find("s2camp-splat-so3xr3" if row["model"] == "splatfacto" else "s2camp-so3xr3", row)
        if reference is not None and reference.get("added_ops"):
            row["added_ops_vs_so3xr3"] = row.get("added_ops", 0) / reference["added_ops"]
        if reference is not None and reference["camera_path_ms"] > 0:
            row["camera_path_vs_so3xr3"] = row["camera_path_ms"] / reference["camera_path_ms"]
    return rows


def run(config: StepCostConfig) -> list[dict]:
    config = config.effective()

    def body(work: Path) -> list[dict]:
        scenes = {}
        for name in config.camera_models:
            scene_config = replace(config.scene, output_dir=work / f"scene-{name}", **CAMERA_MODELS[name])
            scenes[name] = generated_scene(scene_config)
        return measure(config, scenes, work / "runs")

    with contextlib.redirect_stdout(sys.stderr):  # nerfstudio's console notes: stdout stays JSON only (--json)
        if config.scene_dir is not None:
            return body(config.scene_dir)
        with tempfile.TemporaryDirectory(prefix="s2camp-step-cost-") as folder:
            return body(Path(folder))


COLUMNS = (
    "model", "camera_model", "method", "intrinsics", "viewer", "ops", "added_ops", "added_ops_vs_so3xr3",
    "launches", "added_launches", "syncs", "added_syncs", "sync_ops", "camera_path_ms", "camera_path_vs_so3xr3",
)  # fmt: skip


def report(rows: list[dict], config: StepCostConfig) -> Path:
    command = config.command()
    config = config.effective()
    order = {name: i for i, name in enumerate(NERFACTO_METHODS + SPLAT_METHODS)}
    rows = sorted(rows, key=lambda r: (r["model"], r["camera_model"], order[r["method"]], r["intrinsics"], r["viewer"]))
    phases = ["model", "camera_model", "method", "intrinsics", "viewer"]
    phases += [f"{kind}_{phase}" for phase in PHASES for kind in ("ops", "syncs")]
    sections = [
        "What the camera path adds to one training step, counted without a GPU (module docstring of "
        "`benchmarks/s2camp_bench/step_cost.py`; counter: `benchmarks/s2camp_bench/op_count.py`). ops: aten ops of "
        "the whole step, forward and "
        "backward; launches: ops that are not views (the kernel launches on a GPU); syncs: ops that make the host "
        "wait for a CUDA device. added: minus the same model's 'off' row (camera refinement off) on the same camera. "
        f"{config.rays_per_batch} rays per nerfacto step; splatfacto renders one image per step. Camera path: the "
        "data manager's rays of one batch through the camera optimizer, forward and backward (splatting: one training "
        "camera's view matrix), CPU milliseconds, median of "
        f"{config.timing_repeats}; ratios against nerfstudio's SO3xR3 in the same run.",
        "## Per step",
        markdown_table(rows, COLUMNS),
        "## Per phase (ops and syncs)",
        markdown_table(rows, phases),
    ]
    return write_report(
        config.output_dir, "step-cost", "Step cost: aten ops and host syncs per training step",
        command, sections,
    )  # fmt: skip
