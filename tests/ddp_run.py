"""Helper script of tests/test_distributed.py: train with nerfstudio's Trainer in 1 or N gloo processes on the CPU.

    python tests/ddp_run.py --dump-dir DIR [--request-refresh-at STEP] [--snapshot-steps S ...] -- <ns-train args>

Every process writes DIR/rank<r>.pt: its camera parameters (phi_hat, P, P^-1, refresh counters), its field's
parameters, the pixels of its first training batch, the camera errors it computed, the steps at which it refreshed
P, the files it saved with torch.save during training (checkpoints) and its camera parameters after each of the
steps ``--snapshot-steps``. With ``--request-refresh-at`` rank 0 alone asks the model for a refresh before that step,
as the viewer's button does (the viewer runs on rank 0 only). A script rather than a test module, so that the spawned
processes can import it as ``__main__``.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import torch


def train_and_dump(
    local_rank: int,
    world_size: int,
    config,
    global_rank: int = 0,
    dump_dir: Path = Path("."),
    request_refresh_at: int | None = None,
    snapshot_steps: tuple[int, ...] = (),
) -> None:
    """nerfstudio's ``train_loop`` (seed + global rank, the real Trainer) plus a dump of this rank's state."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed

    _set_random_seed(config.machine.seed + global_rank)
    trainer = config.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    pipeline = trainer.pipeline
    model = pipeline.model
    camera_optimizer = model.camera_optimizer

    first_pixels: list[torch.Tensor] = []
    next_train = pipeline.datamanager.next_train

    def recording_next_train(step: int):
        ray_bundle, batch = next_train(step)
        if not first_pixels:
            first_pixels.append(batch["indices"].detach().cpu().clone())
        return ray_bundle, batch

    pipeline.datamanager.next_train = recording_next_train

    refresh_steps: list[int] = []
    refresh = camera_optimizer.refiner.refresh

    def recording_refresh(step: int, *args, **kwargs):
        refresh_steps.append(step)
        return refresh(step, *args, **kwargs)

    camera_optimizer.refiner.refresh = recording_refresh
    if request_refresh_at is not None and global_rank == 0:
        trainer.callbacks.append(
            TrainingCallback(
                where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION],
                iters=(request_refresh_at,),
                func=lambda step: model.request_refresh(),
            )
        )
    snapshots: dict[int, dict[str, torch.Tensor]] = {}

    def latents() -> dict[str, torch.Tensor]:
        """The trained camera parameters: phi_hat (pose, or all K per image) and, with shared intrinsics, theirs."""
        return {
            name: value.detach().cpu().clone()
            for name, value in camera_optimizer.refiner.named_parameters()
            if name in ("whitened_delta", "whitened_intrinsics")
        }

    def snapshot(step: int) -> None:
        snapshots[step] = {**latents(), "camera_deltas": camera_optimizer.refiner.deltas().detach().cpu().clone()}

    if snapshot_steps:  # after the step's other callbacks, the refresh of P included
        trainer.callbacks.append(
            TrainingCallback(
                where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION], iters=snapshot_steps, func=snapshot
            )
        )
    saved: list[str] = []
    save = torch.save

    def recording_save(obj, path, *args, **kwargs):
        saved.append(str(path))
        return save(obj, path, *args, **kwargs)

    torch.save = recording_save  # every file the training run writes with torch.save (checkpoints)
    try:
        trainer.train()
    finally:
        torch.save = save
    state = {
        "saved_files": saved,
        "snapshots": snapshots,
        "latents": latents(),
        "camera_state": {name: value.cpu().clone() for name, value in camera_optimizer.state_dict().items()},
        "precond": camera_optimizer.refiner.precond.cpu().clone(),
        "precond_inv": camera_optimizer.refiner.precond_inv.cpu().clone(),
        "camera_deltas": camera_optimizer.refiner.deltas().detach().cpu().clone(),
        "num_refreshes": int(camera_optimizer.refiner.num_refreshes),
        "refresh_steps": refresh_steps,
        "first_pixels": first_pixels[0],
        "camera_errors": dict(model._camera_errors),
        "world_size": world_size,
        "field": {name: value.detach().cpu().clone() for name, value in model.field.named_parameters()},
    }
    dump_dir.mkdir(parents=True, exist_ok=True)
    torch.save(state, dump_dir / f"rank{global_rank}.pt")


def main(argv: list[str]) -> None:
    import tyro
    from cpu_launcher import launch_cpu
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dump-dir", type=Path, required=True)
    parser.add_argument("--request-refresh-at", type=int, default=None)
    parser.add_argument("--snapshot-steps", type=int, nargs="*", default=[])
    separator = argv.index("--")
    options = parser.parse_args(argv[:separator])
    config = tyro.cli(AnnotatedBaseConfigUnion, args=argv[separator + 1 :])
    config.machine.device_type = "cpu"
    if config.data:
        config.pipeline.datamanager.data = config.data
    config.set_timestamp()
    config.save_config()
    launch_cpu(
        functools.partial(
            train_and_dump,
            dump_dir=options.dump_dir,
            request_refresh_at=options.request_refresh_at,
            snapshot_steps=tuple(options.snapshot_steps),
        ),
        num_devices_per_machine=config.machine.num_devices,
        config=config,
    )


if __name__ == "__main__":
    main(sys.argv[1:])
