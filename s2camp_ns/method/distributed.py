"""The one collective S2CamP adds to a training step, and the number of processes.

With several processes every rank refreshes P at the same steps: a refresh requested from the viewer (rank 0 only)
is agreed by an all-reduce every ``refresh_request_every`` steps (``model_hooks.CameraOptimizerHooks``). On CUDA
``ns-train s2camp --machine.num-devices N`` uses nerfstudio's launcher; ``S2CampPipeline`` wraps the model in DDP.
"""

from __future__ import annotations

import torch
import torch.distributed as dist


def world_size() -> int:
    """Number of training processes (1 without a process group)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def any_rank(flag: bool, device: torch.device | str) -> bool:
    """True on every rank if ``flag`` is on any rank: one all-reduce (MAX); ``flag`` itself without a process
    group. ``device``: the rank's own device under NCCL, the CPU under gloo."""
    if world_size() == 1:
        return flag
    value = torch.tensor([int(flag)], dtype=torch.int64, device=device)
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item())


__all__ = ["any_rank", "world_size"]
