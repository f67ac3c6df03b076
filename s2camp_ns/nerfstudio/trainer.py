"""nerfstudio's Trainer with atomic checkpoints (a run killed while saving keeps its last good checkpoint) that also
hold the random number generators' state (a resumed run continues as the uninterrupted one would).

nerfstudio's ``Trainer.save_checkpoint`` writes straight to ``nerfstudio_models/step-N.ckpt`` and then deletes the
older checkpoints. A kill during the write leaves a truncated newest file, and ``--load-dir`` (which takes the
highest step) and ``eval_setup`` then fail on it while the good checkpoint may already be gone. Here the checkpoint
is written to a temporary file, flushed to disk (fsync), renamed onto ``step-N.ckpt`` (``os.replace``, atomic within
one file system) and the folder entry flushed; only then are older checkpoints deleted.

The temporary file lives in the hidden sibling folder ``nerfstudio_models.partial/`` on the same file system, not in
``nerfstudio_models/`` itself: nerfstudio parses every file name in that folder as ``step-N.ckpt``
(``Trainer._load_checkpoint``, ``eval_utils.eval_load_checkpoint``), so a temporary file left there by a kill would
break both resuming and evaluation.

nerfstudio's checkpoints do not hold the state of the random number generators, and its ``train.py`` seeds them
afresh on every start: a resumed run then samples the rays and the proposal samples of its first steps again,
and drifts from the uninterrupted run. The checkpoint also holds the state of torch's (CPU and CUDA), numpy's and
Python's generators, restored after loading. nerfstudio's proposal sampler (``ProposalNetworkSampler``) keeps the
step counters of its update schedule in plain attributes, outside every state dict: a resumed run would restart them
at 0, update the proposal networks at every step of its first ten (the sampler's warm-up) and split from the
uninterrupted run at its first step. The checkpoint holds them too (``sampler_state``), restored after loading. With
both, a resumed CPU run on one thread is bit-identical to the uninterrupted one: every tensor of the pipeline and of
the optimizers (tests/test_e2e.py checks it past the sampler's warm-up and across a P refresh). Loading takes the
highest ``step-N.ckpt`` and ignores other files in the folder.

config.yml. nerfstudio's ``eval_setup`` (ns-eval, ns-render, s2camp-eval, s2camp-export-cameras) loads a run's own
checkpoints: it replaces ``load_dir`` by the run's checkpoint folder but keeps ``load_step``, which for a run resumed
with ``--load-dir D --load-step N`` names a step of D, not of the run. A resumed run therefore records the
checkpoint it loaded as ``load_checkpoint`` in its config.yml, with ``load_dir`` and ``load_step`` cleared
(``record_loaded_checkpoint``): the file says exactly where the run came from, ``ns-train --load-config`` resumes
from the same checkpoint, and every tool that evaluates the run loads its latest checkpoint.
"""

from __future__ import annotations

import os
import random
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.model_components.ray_samplers import ProposalNetworkSampler
from nerfstudio.utils import comms
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE

from s2camp_ns.camera_optimizer import split_per_image_adam_state
from s2camp_ns.nerfstudio.pipeline import CheckpointCamerasError
from s2camp_ns.nerfstudio.schedulers import RunLengthScheduleConfig

PARTIAL_SUFFIX = ".partial"
"""Suffix of the temporary-checkpoint folder (beside the checkpoint folder) and of the files written in it."""


def partial_dir(checkpoint_dir: Path) -> Path:
    """Folder of the temporary checkpoint files: a sibling of ``checkpoint_dir``, so on the same file system."""
    return checkpoint_dir.with_name(checkpoint_dir.name + PARTIAL_SUFFIX)


def _fsync_dir(folder: Path) -> None:
    """Flush a folder entry (the rename) to disk; not possible on every platform, and not needed for atomicity."""
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
    """State of every random number generator a training step draws from (torch CPU and CUDA, numpy, Python).

    Only tensors and plain Python values, so that ``torch.load(weights_only=True)`` (nerfstudio's eval_setup under
    torch >= 2.6) still loads the checkpoint. numpy's is its global legacy generator: the one nerfstudio seeds.
    """
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
"""The attributes of nerfstudio's ``ProposalNetworkSampler`` that decide whether a step updates the proposal networks
(``generate_ray_samples``: always while ``_step < 10``, then when ``_steps_since_update`` exceeds the schedule)."""


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


def with_run_length(optimizers: dict[str, dict[str, Any]], run_steps: int) -> dict[str, dict[str, Any]]:
    """A copy of nerfstudio's optimizer settings in which every ``RunLengthScheduleConfig`` without a run length gets
    ``run_steps``; the others are returned as they are."""
    resolved = {}
    for name, settings in optimizers.items():
        scheduler = settings.get("scheduler")
        if isinstance(scheduler, RunLengthScheduleConfig) and scheduler.run_steps is None:
            settings = {**settings, "scheduler": replace(scheduler, run_steps=run_steps)}
        resolved[name] = settings
    return resolved


class S2CampTrainer(Trainer):
    """nerfstudio's Trainer; checkpoints are written atomically and hold the random state, and run-length schedules
    learn the run's length (module docstring)."""

    config: S2CampTrainerConfig

    def setup_optimizers(self) -> Optimizers:
        """nerfstudio's optimizers, with ``--max-num-iterations`` as the length of every run-length schedule."""
        optimizers = with_run_length(self.config.optimizers, self.config.max_num_iterations)
        return Optimizers(optimizers, self.pipeline.get_param_groups())

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """Save the pipeline, optimizers, schedulers and grad scaler as ``step-{step:09d}.ckpt``, atomically."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        # Temporary files of a run killed while saving: never renamed, so never a checkpoint.
        for stale in partial_dir(self.checkpoint_dir).glob(f"*{PARTIAL_SUFFIX}"):
            stale.unlink(missing_ok=True)
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        state = {
            "step": step,
            "pipeline": pipeline.state_dict(),
            "optimizers": {name: optimizer.state_dict() for name, optimizer in self.optimizers.optimizers.items()},
            "schedulers": {name: scheduler.state_dict() for name, scheduler in self.optimizers.schedulers.items()},
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
        """Load pipeline, optimizers, schedulers (unless ``--load-scheduler False``), grad scaler, random state and
        proposal sampler counters; a run resumed with ``--load-dir`` records the checkpoint in its config.yml."""
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
            optimizers["camera_opt"] = split_per_image_adam_state(optimizers["camera_opt"])
        self.optimizers.load_optimizers(optimizers)
        if "schedulers" in state and config.load_scheduler:
            self.optimizers.load_schedulers(state["schedulers"])
        self.grad_scaler.load_state_dict(state["scalers"])
        # One process: continue the saved random streams (bit-identical resume). Several processes: the checkpoint
        # holds rank 0's streams only; restoring them on every rank would make all ranks draw the same rays, so each
        # keeps nerfstudio's own per-rank seeding (seed + rank) and the resumed run redraws its rays.
        if "random_state" in state and self.world_size == 1:
            set_random_state(state["random_state"])
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        if "sampler_state" in state:
            set_sampler_state(pipeline.model, state["sampler_state"])
        if config.load_dir is not None:
            self.record_loaded_checkpoint(path)
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")

    def record_loaded_checkpoint(self, path: Path) -> None:
        """Rewrite the run's config.yml with ``load_checkpoint`` = ``path`` (the checkpoint loaded) and no
        ``load_dir`` / ``load_step`` (module docstring, config.yml); the main process only."""
        config = self.config
        config.load_checkpoint, config.load_dir, config.load_step = path.resolve(), None, None
        if comms.is_main_process():
            config.save_config()


__all__ = [
    "S2CampTrainer",
    "S2CampTrainerConfig",
    "atomic_torch_save",
    "latest_checkpoint",
    "partial_dir",
    "sampler_state",
    "set_sampler_state",
    "with_run_length",
]
