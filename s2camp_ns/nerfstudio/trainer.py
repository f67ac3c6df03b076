"""nerfstudio's Trainer with atomic checkpoints: a run killed while saving keeps its last good checkpoint.

nerfstudio's ``Trainer.save_checkpoint`` writes straight to ``nerfstudio_models/step-N.ckpt`` and then deletes the
older checkpoints. A kill during the write leaves a truncated newest file, and ``--load-dir`` (which takes the
highest step) and ``eval_setup`` then fail on it while the good checkpoint may already be gone. Here the checkpoint
is written to a temporary file, flushed to disk (fsync), renamed onto ``step-N.ckpt`` (``os.replace``, atomic within
one file system) and the folder entry flushed; only then are older checkpoints deleted.

The temporary file lives in the hidden sibling folder ``nerfstudio_models.partial/`` on the same file system, not in
``nerfstudio_models/`` itself: nerfstudio parses every file name in that folder as ``step-N.ckpt``
(``Trainer._load_checkpoint``, ``eval_utils.eval_load_checkpoint``), so a temporary file left there by a kill would
break both resuming and evaluation.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.decorators import check_main_thread

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


@dataclass
class S2CampTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig, training with ``S2CampTrainer`` (atomic checkpoints)."""

    _target: type = field(default_factory=lambda: S2CampTrainer)


class S2CampTrainer(Trainer):
    """nerfstudio's Trainer; checkpoints are written atomically (see the module docstring)."""

    config: S2CampTrainerConfig

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
        }
        atomic_torch_save(state, path)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("*.ckpt"):
                if old != path:
                    old.unlink()


__all__ = ["S2CampTrainer", "S2CampTrainerConfig", "atomic_torch_save", "partial_dir"]
