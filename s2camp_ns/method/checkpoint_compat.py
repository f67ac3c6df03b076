"""Checkpoints of earlier layouts of the camera optimizer, loaded into today's.

- ``refiner_keys``: a load hook renaming the refiner's tensors saved as the optimizer's own (``<prefix>precond``) to
  the submodule's (``<prefix>refiner.precond``);
- ``split_per_image_adam_state``: Adam's moments of a per-image latent saved as one tensor [n, K], split into the
  pose [n, 6] and intrinsics [n, K - 6] latents.
"""

from __future__ import annotations

from torch import nn

from s2camp_ns.core.shared_intrinsics import NUM_POSE_PARAMS


def split_per_image_adam_state(state: dict) -> dict:
    """Adam's state of the ``camera_opt`` group written while a per-image latent was one tensor [n, K]: the same
    moments for the pose [n, 6] and intrinsics [n, K - 6] latents that store it now (a state of two or more tensors
    is returned as it is)."""
    group = state["param_groups"][0]
    if len(state["param_groups"]) != 1 or len(group["params"]) != 1:
        return state
    old = state["state"].get(group["params"][0])
    if old is None or old["exp_avg"].shape[-1] <= NUM_POSE_PARAMS:
        return state
    parts = [{**old}, {**old}]
    for key in ("exp_avg", "exp_avg_sq"):
        parts[0][key], parts[1][key] = old[key][:, :NUM_POSE_PARAMS], old[key][:, NUM_POSE_PARAMS:]
    return {"state": {0: parts[0], 1: parts[1]}, "param_groups": [{**group, "params": [0, 1]}]}


def refiner_keys(
    module: nn.Module, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
) -> None:
    """Checkpoints written while the refiner's tensors were the optimizer's own (``<prefix>precond``) load as the
    submodule's (``<prefix>refiner.precond``)."""
    names = set(module.refiner.state_dict()) | {"whitened_delta"}
    for name in names:
        if prefix + name in state_dict and prefix + "refiner." + name not in state_dict:
            state_dict[prefix + "refiner." + name] = state_dict.pop(prefix + name)


__all__ = ["refiner_keys", "split_per_image_adam_state"]
