"""What a piece of torch code costs on a launch-bound device, counted without one: its aten ops and host syncs.

On a GPU every aten op that computes is a kernel launch, and every op whose result the host must read before it can
go on is a synchronisation (the CPU waits for the GPU queue to drain). ``OpCounter`` is a ``TorchDispatchMode`` that
sees every aten op below autograd, forward and backward, and counts as ``syncs``: host reads (``_local_scalar_dense``:
``.item()``, ``bool(t)``; ``equal``, ``is_nonzero``), ops whose output size depends on the data (``nonzero``,
``unique`` and its variants, ``masked_select``, ``repeat_interleave`` without ``output_size``, ``bincount``, indexing
with a boolean mask) and copies from a CUDA tensor to the CPU. Reads of the tensors in ``host_resident`` (storage
addresses of tensors that stay on the CPU when a model trains on a GPU, as Adam's step counts) are not syncs. Views
launch nothing: they are counted apart, and ``launches`` = ops - views is the closer proxy of kernel launches.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

aten = torch.ops.aten

SYNC_PACKETS = {
    aten._local_scalar_dense, aten.equal, aten.is_nonzero, aten.nonzero, aten.argwhere, aten._unique, aten._unique2,
    aten.unique_dim, aten.unique_consecutive, aten.masked_select, aten.bincount,
}  # fmt: skip
"""Ops that synchronise a CUDA device whatever their arguments."""

MASK_INDEX_PACKETS = {aten.index, aten.index_put, aten.index_put_, aten._index_put_impl_}
"""Advanced indexing: a sync when an index is a boolean mask."""

COPY_PACKETS = {aten._to_copy, aten.copy_, aten.copy}
"""Copies: a sync when they move a CUDA tensor to the CPU."""


def _packet(func) -> object:
    return getattr(func, "overloadpacket", func)


def _is_view(func) -> bool:
    schema = getattr(func, "_schema", None)
    if schema is None or not schema.returns:
        return False
    alias = schema.returns[0].alias_info
    return alias is not None and not alias.is_write


def _to_cpu_from_cuda(func, args, kwargs) -> bool:
    tensors = [value for value in tree_flatten((args, kwargs))[0] if isinstance(value, torch.Tensor)]
    if not tensors or tensors[0].device.type != "cuda":
        return False
    if _packet(func) is aten._to_copy:
        target = kwargs.get("device")
        return target is not None and torch.device(target).type == "cpu"
    # copy_(destination, source): the destination is the first argument
    return len(tensors) > 1 and tensors[0].device.type == "cpu" and tensors[1].device.type == "cuda"


def is_sync(func, args: tuple, kwargs: dict, host_resident: frozenset[int] = frozenset()) -> bool:
    """Whether the aten op ``func`` on ``args``, ``kwargs`` synchronises a CUDA device (module docstring)."""
    packet = _packet(func)
    if packet is aten._local_scalar_dense and args[0].data_ptr() in host_resident:
        return False
    if packet in SYNC_PACKETS:
        return True
    if packet is aten.repeat_interleave:
        return isinstance(args[0], torch.Tensor) and kwargs.get("output_size") is None and len(args) < 3
    if packet in MASK_INDEX_PACKETS:
        indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
        return any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in indices or ())
    if packet in COPY_PACKETS:
        if packet is aten.copy_ and len(args) > 1:
            return args[0].device.type == "cpu" and isinstance(args[1], torch.Tensor) and args[1].device.type == "cuda"
        return _to_cpu_from_cuda(func, args, kwargs)
    return False


@dataclass
class OpCount:
    """Ops counted under one label: every op by name, the views among them and the syncs by name."""

    ops: Counter = field(default_factory=Counter)
    views: int = 0
    syncs: Counter = field(default_factory=Counter)

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def launches(self) -> int:
        return self.total - self.views

    @property
    def num_syncs(self) -> int:
        return sum(self.syncs.values())

    def add(self, other: OpCount) -> None:
        self.ops.update(other.ops)
        self.views += other.views
        self.syncs.update(other.syncs)


class OpCounter(TorchDispatchMode):
    """Counts the aten ops run under it, into the count of the current ``label`` (``phase`` changes it)."""

    def __init__(self, host_resident: frozenset[int] = frozenset()) -> None:
        super().__init__()
        self.counts: dict[str, OpCount] = {}
        self.label = "all"
        self.host_resident = host_resident
        """Storage addresses of tensors that live on the host even when the model trains on a GPU."""

    def phase(self, label: str) -> OpCounter:
        """Count what follows under ``label`` (until the next call)."""
        self.label = label
        return self

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        count = self.counts.setdefault(self.label, OpCount())
        name = str(_packet(func)).removeprefix("aten.")
        count.ops[name] += 1
        if _is_view(func):
            count.views += 1
        if is_sync(func, args, kwargs, self.host_resident):
            count.syncs[name] += 1
        return func(*args, **kwargs)

    def total(self) -> OpCount:
        """Every label together."""
        whole = OpCount()
        for count in self.counts.values():
            whole.add(count)
        return whole


__all__ = ["OpCount", "OpCounter", "is_sync"]
