"""nerfstudio's Trainer with atomic checkpoints that hold the random state.

Atomic: a checkpoint is written into ``nerfstudio_models.partial/`` (nerfstudio parses every file of
``nerfstudio_models/`` as a checkpoint), fsynced, renamed onto ``step-N.ckpt`` and the folder fsynced; only then are
older checkpoints deleted. It also holds torch's, numpy's and Python's generator states and the step counters of
nerfstudio's ``ProposalNetworkSampler``, so a resumed one-process CPU run is bit-identical to the uninterrupted one.
When training starts it writes the anchors' tracks beside config.yml (``core.anchor_tracks``). A run resumed with
``--load-dir`` records the checkpoint it loaded as ``load_checkpoint`` in its config.yml
(``eval_setup`` keeps ``load_step`` but not ``load_dir``).
"""

from __future__ import annotations

import os
import random
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.model_components.ray_samplers import ProposalNetworkSampler
from nerfstudio.utils import comms
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE

from s2camp_ns.compat import split_per_image_adam_state
from s2camp_ns.core.anchor_tracks import ANCHOR_TRACKS_FILE
from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS
from s2camp_ns.method.pipeline import CheckpointCamerasError
from s2camp_ns.method.schedulers import RunLengthScheduleConfig

PARTIAL_SUFFIX = ".partial"
"""Suffix of the temporary-checkpoint folder (beside the checkpoint folder) and of the files written in it."""


def partial_dir(checkpoint_dir: Path) -> Path:
    """Folder of the temporary checkpoint files: a sibling of ``checkpoint_dir`` (same file system)."""
    return checkpoint_dir.with_name(checkpoint_dir.name + PARTIAL_SUFFIX)


def _fsync_dir(folder: Path) -> None:
    """Flush a folder entry (the rename) to disk, where the platform allows it."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_torch_save(state: Any, path: Path) -> None:
    """``torch.save(state, path)`` such that ``path`` holds either its previous content or all of ``state``."""
    temporary_dir = partial_dir(path.parent)
    temporary_dir.mkdir(parents=True, exist_ok=True)
    temporary = temporary_dir / f"{path.name}.{os.getpid()}{PARTIAL_SUFFIX}"
    try:
        with open(temporary, "wb") as file:
            torch.save(state, file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def random_state() -> dict[str, Any]:
    """State of every generator a training step draws from (torch CPU and CUDA, numpy's global one, Python), as
    tensors and plain values only (``torch.load(weights_only=True)`` must load it)."""
    kind, keys, position, has_gauss, cached_gaussian = np.random.get_state()  # noqa: NPY002
    version, python_state, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": {
            "kind": str(kind),
            "keys": torch.from_numpy(keys.astype(np.int64)),
            "position": int(position),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached_gaussian),
        },
        "python": {"version": version, "state": torch.tensor(python_state, dtype=torch.int64), "gauss": gauss_next},
    }


def set_random_state(state: dict[str, Any]) -> None:
    """Restore what ``random_state`` returned (CUDA generators only on a machine with as many devices)."""
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(state["cuda"])
    numpy_state = state["numpy"]
    np.random.set_state(  # noqa: NPY002
        (
            numpy_state["kind"],
            numpy_state["keys"].numpy().astype(np.uint32),
            numpy_state["position"],
            numpy_state["has_gauss"],
            numpy_state["cached_gaussian"],
        )
    )
    python_state = state["python"]
    random.setstate((python_state["version"], tuple(python_state["state"].tolist()), python_state["gauss"]))


SAMPLER_COUNTERS = ("_step", "_steps_since_update")
"""The ``ProposalNetworkSampler`` attributes that decide whether a step updates the proposal networks."""


def sampler_state(model: torch.nn.Module) -> dict[str, dict[str, int]]:
    """The counters (``SAMPLER_COUNTERS``) of every ``ProposalNetworkSampler`` in ``model``, by module name."""
    return {
        name: {counter: int(getattr(module, counter)) for counter in SAMPLER_COUNTERS}
        for name, module in model.named_modules()
        if isinstance(module, ProposalNetworkSampler)
    }


def set_sampler_state(model: torch.nn.Module, state: dict[str, dict[str, int]]) -> None:
    """Restore what ``sampler_state`` returned; a sampler the state does not name (another model) is refused."""
    samplers = {name: module for name, module in model.named_modules() if isinstance(module, ProposalNetworkSampler)}
    if set(samplers) != set(state):
        raise ValueError(
            f"the checkpoint's proposal samplers {sorted(state)} are not the model's {sorted(samplers)}: the "
            "checkpoint belongs to another model"
        )
    for name, counters in state.items():
        for counter in SAMPLER_COUNTERS:
            setattr(samplers[name], counter, int(counters[counter]))


def latest_checkpoint(checkpoint_dir: Path) -> Path:
    """The ``step-N.ckpt`` with the highest N in ``checkpoint_dir``; other files are ignored."""
    steps = {}
    for path in checkpoint_dir.glob("step-*.ckpt"):
        number = path.stem[len("step-") :]
        if number.isdigit():
            steps[int(number)] = path
    if not steps:
        raise FileNotFoundError(f"--load-dir {checkpoint_dir} holds no step-N.ckpt checkpoint")
    return steps[max(steps)]


@dataclass
class S2CampTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig, training with ``S2CampTrainer`` (atomic checkpoints)."""

    _target: type = field(default_factory=lambda: S2CampTrainer)


def plain_numbers(state: Any) -> Any:
    """``state`` (dicts, lists, tuples) with numpy scalars as Python numbers: nerfstudio's schedules compute their
    rates with numpy, and ``torch.load(weights_only=True)`` (torch's default) refuses numpy scalars."""
    if isinstance(state, np.generic):
        return state.item()
    if isinstance(state, dict):
        return {key: plain_numbers(value) for key, value in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(plain_numbers(value) for value in state)
    return state


def with_run_length(optimizers: dict[str, dict[str, Any]], run_steps: int) -> dict[str, dict[str, Any]]:
    """A copy of ``optimizers`` with ``run_steps`` in every ``RunLengthScheduleConfig`` that has none."""
    resolved = {}
    for name, settings in optimizers.items():
        scheduler = settings.get("scheduler")
        if isinstance(scheduler, RunLengthScheduleConfig) and scheduler.run_steps is None:
            settings = {**settings, "scheduler": replace(scheduler, run_steps=run_steps)}
        resolved[name] = settings
    return resolved


class S2CampTrainer(Trainer):
    """nerfstudio's Trainer: atomic checkpoints with the random state; run-length schedules learn the run's length."""

    config: S2CampTrainerConfig

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        """nerfstudio's setup, then the anchors' tracks written beside config.yml (``save_anchor_tracks``)."""
        super().setup(test_mode)
        self.save_anchor_tracks()

    @check_main_thread
    def save_anchor_tracks(self) -> None:
        """The pipeline's ``anchor_tracks`` as ``ANCHOR_TRACKS_FILE`` in the run's folder: what the export of a loaded
        run reads instead of making the tracks and fitting the anchors again."""
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        tracks = getattr(pipeline, "anchor_tracks", None)
        if tracks is not None:
            self.base_dir.mkdir(parents=True, exist_ok=True)
            tracks.save(self.base_dir / ANCHOR_TRACKS_FILE)

    def setup_optimizers(self) -> Optimizers:
        """nerfstudio's optimizers, with ``--max-num-iterations`` as the length of every run-length schedule."""
        optimizers = with_run_length(self.config.optimizers, self.config.max_num_iterations)
        return Optimizers(optimizers, self.pipeline.get_param_groups())

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """Save the pipeline, optimizers, schedulers and grad scaler as ``step-{step:09d}.ckpt``, atomically."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        # Temporary files of a run killed while saving (never renamed).
        for stale in partial_dir(self.checkpoint_dir).glob(f"*{PARTIAL_SUFFIX}"):
            stale.unlink(missing_ok=True)
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        state = {
            "step": step,
            "pipeline": pipeline.state_dict(),
            "optimizers": {name: plain_numbers(o.state_dict()) for name, o in self.optimizers.optimizers.items()},
            "schedulers": {name: plain_numbers(s.state_dict()) for name, s in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
            "random_state": random_state(),
            "sampler_state": sampler_state(pipeline.model),
        }
        atomic_torch_save(state, path)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("*.ckpt"):
                if old != path:
                    old.unlink()

    def _load_checkpoint(self) -> None:
        """Load everything ``save_checkpoint`` saved (schedulers unless ``--load-scheduler False``); with
        ``--load-dir``, record the checkpoint in config.yml."""
        config = self.config
        if config.load_dir is not None:
            path = (
                latest_checkpoint(config.load_dir)
                if config.load_step is None
                else config.load_dir / f"step-{config.load_step:09d}.ckpt"
            )
        elif config.load_checkpoint is not None:
            path = config.load_checkpoint
        else:
            CONSOLE.print("No Nerfstudio checkpoint to load, so training from scratch.")
            return
        if not path.is_file():
            raise FileNotFoundError(f"checkpoint {path} does not exist")
        state = torch.load(path, map_location="cpu")
        self._start_step = state["step"] + 1
        try:
            self.pipeline.load_pipeline(state["pipeline"], state["step"])
        except CheckpointCamerasError as error:
            raise CheckpointCamerasError(f"checkpoint {path}: {error}") from None
        optimizers = dict(state["optimizers"])
        if "camera_opt" in optimizers:  # written while a per-image latent was one tensor
            optimizers["camera_opt"] = split_per_image_adam_state(optimizers["camera_opt"], NUM_POSE_PARAMS)
        self.optimizers.load_optimizers(optimizers)
        if "schedulers" in state and config.load_scheduler:
            self.optimizers.load_schedulers(state["schedulers"])
        self.grad_scaler.load_state_dict(state["scalers"])
        # Several processes keep nerfstudio's per-rank seeding: the checkpoint holds rank 0's streams only.
        if "random_state" in state and self.world_size == 1:
            set_random_state(state["random_state"])
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        if "sampler_state" in state:
            set_sampler_state(pipeline.model, state["sampler_state"])
        if config.load_dir is not None:
            self.record_loaded_checkpoint(path)
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")

    def record_loaded_checkpoint(self, path: Path) -> None:
        """Rewrite config.yml with ``load_checkpoint = path`` and no ``load_dir`` / ``load_step`` (main process)."""
        config = self.config
        config.load_checkpoint, config.load_dir, config.load_step = path.resolve(), None, None
        if comms.is_main_process():
            config.save_config()


__all__ = [
    "S2CampTrainer", "S2CampTrainerConfig", "atomic_torch_save", "latest_checkpoint", "partial_dir", "plain_numbers",
    "sampler_state", "set_sampler_state", "with_run_length",
]  # fmt: skip
