"""nerfstudio's multi-process training on the CPU, for the tests: one gloo process per "device".

nerfstudio 1.1.5 cannot train in several processes on the CPU (its worker asserts CUDA). ``launch_cpu`` spawns the
processes as nerfstudio's ``scripts.train.launch`` does, with a gloo process group, each running ``main_func``
(``tests/ddp_run.py``); ``S2CampPipeline`` wraps the model in DDP itself (no ``device_ids`` on the CPU).
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from datetime import timedelta
from typing import Any

import torch.distributed as dist
import torch.multiprocessing as mp
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.utils import comms, profiler
from nerfstudio.utils.rich_utils import CONSOLE

DEFAULT_TIMEOUT = timedelta(minutes=30)


def _cpu_worker(
    local_rank: int,
    main_func: Callable,
    world_size: int,
    num_devices_per_machine: int,
    machine_rank: int,
    dist_url: str,
    config: TrainerConfig,
    timeout: timedelta,
) -> Any:
    """nerfstudio's ``_distributed_worker`` for the CPU: a gloo process group, no CUDA assertion."""
    global_rank = machine_rank * num_devices_per_machine + local_rank
    dist.init_process_group(
        backend="gloo", init_method=dist_url, world_size=world_size, rank=global_rank, timeout=timeout
    )
    assert comms.LOCAL_PROCESS_GROUP is None
    for machine in range(world_size // num_devices_per_machine):
        ranks = list(range(machine * num_devices_per_machine, (machine + 1) * num_devices_per_machine))
        group = dist.new_group(ranks)
        if machine == machine_rank:
            comms.LOCAL_PROCESS_GROUP = group
    try:
        output = main_func(local_rank, world_size, config, global_rank)
        comms.synchronize()
    finally:
        dist.destroy_process_group()
    return output


def launch_cpu(
    main_func: Callable,
    num_devices_per_machine: int,
    num_machines: int = 1,
    machine_rank: int = 0,
    dist_url: str = "auto",
    config: TrainerConfig | None = None,
    timeout: timedelta = DEFAULT_TIMEOUT,
) -> None:
    """nerfstudio's ``scripts.train.launch`` on the CPU: one gloo process per "device" (one runs in this process)."""
    if config is None:
        raise ValueError("config must be a TrainerConfig, got None")
    if config.machine.device_type != "cpu":
        raise ValueError(
            f"machine.device_type must be 'cpu' for launch_cpu, got {config.machine.device_type!r} "
            "(on CUDA use ns-train, nerfstudio's own launcher)"
        )
    world_size = num_machines * num_devices_per_machine
    if world_size < 1:
        raise ValueError(f"num_machines * num_devices_per_machine must be >= 1, got {world_size}")
    try:
        if world_size == 1:
            main_func(local_rank=0, world_size=1, config=config)
            return
        if dist_url == "auto":
            if num_machines != 1:
                raise ValueError(f"dist_url 'auto' works on one machine only, got num_machines = {num_machines}")
            from nerfstudio.scripts.train import _find_free_port

            dist_url = f"tcp://127.0.0.1:{_find_free_port()}"
        mp.spawn(
            _cpu_worker,
            nprocs=num_devices_per_machine,
            join=True,
            args=(main_func, world_size, num_devices_per_machine, machine_rank, dist_url, config, timeout),
        )
    except KeyboardInterrupt:
        CONSOLE.print(traceback.format_exc())
    finally:
        profiler.flush_profiler(config.logging)
