"""Fake CUDA for the device audit: tensors that say they are on "cuda" while their values live on the CPU.

Why not ``torch._subclasses.fake_tensor.FakeTensorMode`` alone: fake tensors carry no values, so every op whose
result depends on the data stops it (``DataDependentOutputException`` on ``.item()`` / ``bool(t)`` / ``int(t)``,
``DynamicOutputShapeException`` on ``torch.unique`` / ``nonzero`` / boolean masks). The camera optimizer does
these everywhere: the input checks of ``core.validation`` (``bool((x < low).any())``), ``torch.unique`` of the
step's camera indices, the refresh schedule's ``int(self.last_refresh_step)``; and no backward pass runs on a fake
"cuda" tensor (the autograd engine looks for a CUDA context). FakeTensorMode is still used where it can go
(tests/test_device_audit.py: nerfacto's field forward, the preconditioner's float64 algebra, and as the reference
for the device rules below).

``fake_cuda()`` is the "equivalent that executes every op and fails on a mismatch": inside it,
- a tensor created with ``device="cuda"`` (factories, ``.to("cuda")``, ``.cuda()``, ``module.to("cuda")``) is a
  ``FakeCudaTensor``: ``.device`` is ``cuda:0``, ``.is_cuda`` is True, its values are a real CPU tensor;
- every aten op (forward and backward) is dispatched here first, checks its tensor arguments' devices with
  CUDA's rules and then runs on the CPU values; outputs of a CUDA op are ``FakeCudaTensor`` again;
- ``.cpu()`` / ``.to("cpu")`` give plain CPU tensors; ``.item()``, ``bool``, ``.tolist()`` work as on CUDA (a
  synchronisation there); ``.numpy()`` of a fake CUDA tensor fails as it does on CUDA.

CUDA's device rules, as torch's FakeTensor models them (``FakeTensor._find_common_device`` and the multi-device
op implementations of ``torch._subclasses.fake_impls``), plus the generator rule of CUDA's random kernels:
- all tensor arguments of an op on one device, except CPU tensors with zero dimensions (scalars);
- ``copy_`` / ``_to_copy`` move between devices;
- indexing a CUDA tensor accepts CPU index tensors; a CPU tensor indexed by a CUDA index fails;
- a random op on CUDA needs a CUDA generator (a CPU ``torch.Generator()`` fails).
A violation raises ``DeviceMismatchError``, a subclass of torch's ``FakeTensorDeviceMismatchError`` where torch has
it (``MISMATCH_BASE``), whose message reads like FakeTensorMode's ("Expected all tensors to be on the same device,
but found at least two devices, cuda:0 and cpu!") followed by the op and its tensor arguments, or ``RuntimeError``
for the index and generator rules.

How it is built, and its limits:
- a ``FakeCudaTensor``'s C++ metadata says CPU (see the class), so C++ code that copies a tensor's options (autograd's
  formulas: ``new_zeros(..., device=cpu)``, ``grad.to(self.options())``) asks for "cpu" where CUDA code would get
  "cuda": such requests on a CUDA tensor are taken as its own device. Python's moves (``.to``, ``.cpu()``,
  ``.cuda()``, ``.type_as``) are intercepted before C++ (``_Moves``), so a deliberate ``.cpu()`` is still a move;
  an explicit ``device="cpu"`` in ``new_*`` / ``*_like`` of a CUDA tensor would be missed (the library has none);
- ``torch.cuda.is_available()`` stays False, and nothing CUDA-specific runs: CUDA generators and their state
  (``torch.cuda.get_rng_state``, ``fork_rng`` on CUDA), pinned memory, streams, NCCL, CUDA kernels (tiny-cuda-nn,
  gsplat). Those are for a real GPU (``pytest -m cuda``).
"""

from __future__ import annotations

import contextlib
import weakref
from collections import Counter
from collections.abc import Iterator
from typing import Any

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten, tree_map

try:
    from torch._subclasses.fake_tensor import FakeTensorDeviceMismatchError
except ImportError:  # torch 2.11 (the GPU machines' image) has no such class: the emulation's error is then its own
    FakeTensorDeviceMismatchError = None
MISMATCH_BASE: type[RuntimeError] = FakeTensorDeviceMismatchError or RuntimeError
"""What FakeTensorMode raises on a device mismatch in this torch (its own class where it has one, else a plain
``RuntimeError``): the base of ``DeviceMismatchError``, so this module and the tests that import it are collected
under every torch version the ``cuda`` tests run with."""

aten = torch.ops.aten

CUDA = torch.device("cuda", 0)
CPU = torch.device("cpu")

MOVE_OPS = {aten._to_copy.default, aten.copy_.default, aten.copy.default, aten._foreach_copy_.default}
"""Ops that copy between devices (the destination, or the ``device`` keyword, decides)."""
INDEX_OPS = {
    aten.index.Tensor,
    aten.index_put.default,
    aten.index_put_.default,
    aten._index_put_impl_.default,
    aten._unsafe_index.Tensor,
    aten._unsafe_index_put.default,
}
"""Advanced indexing: the indexed tensor's device decides; index tensors may also be on the CPU."""


class FakeCudaTensor(torch.Tensor):
    """A tensor that says it is on ``cuda:0`` (``.device``, ``.is_cuda``) whose values are the CPU tensor ``elem``.

    Its C++ metadata says CPU, so that autograd's engine runs its backward on the calling thread: the engine would
    otherwise look for a CUDA context (``hasPrimaryContext``), which FakeTensorMode cannot run without either.
    The device checks never look at that metadata, only at the type.
    """

    elem: torch.Tensor

    @staticmethod
    def __new__(cls, elem: torch.Tensor) -> FakeCudaTensor:
        if isinstance(elem, FakeCudaTensor) or elem.device.type != "cpu":
            raise AssertionError(f"FakeCudaTensor wraps a plain CPU tensor, got {type(elem).__name__} on {elem.device}")
        wrapper = torch.Tensor._make_wrapper_subclass(
            cls,
            elem.size(),
            strides=elem.stride(),
            storage_offset=elem.storage_offset(),
            dtype=elem.dtype,
            layout=elem.layout,
            device=CPU,
            requires_grad=elem.requires_grad,
        )
        wrapper.elem = elem
        return wrapper

    @property
    def device(self) -> torch.device:  # type: ignore[override]
        return CUDA

    @property
    def is_cuda(self) -> bool:  # type: ignore[override]
        return True

    @property
    def is_cpu(self) -> bool:  # type: ignore[override]
        return False

    def __repr__(self, *, tensor_contents: Any = None) -> str:
        return f"FakeCudaTensor({self.elem!r})"

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        # Reached only outside ``fake_cuda()`` (inside it, the mode handles every op first).
        return _run(func, args, kwargs or {})


class _ToCuda(torch.autograd.Function):
    """CPU -> fake CUDA copy whose gradient goes back to the CPU (as ``.to("cuda")``'s does)."""

    @staticmethod
    def forward(ctx, tensor: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        ctx.dtype = tensor.dtype
        return FakeCudaTensor(tensor.detach().to(dtype=dtype, copy=True))

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return _unwrap(grad).to(ctx.dtype), None


class _ToCpu(torch.autograd.Function):
    """Fake CUDA -> CPU copy whose gradient goes back to (fake) CUDA."""

    @staticmethod
    def forward(ctx, tensor: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        ctx.dtype = tensor.dtype
        return _unwrap(tensor).detach().to(dtype=dtype, copy=True)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return FakeCudaTensor(_unwrap(grad).to(ctx.dtype)), None


def _move(tensor: torch.Tensor, device: torch.device | None, dtype: torch.dtype | None, copy: bool) -> torch.Tensor:
    """``tensor.to(device, dtype)`` by the tensors' claimed devices (C++ would compare their CPU metadata)."""
    source = _device_of(tensor)
    target = source if device is None else torch.device(device)
    if target.type == "cuda" and target.index is None:
        target = CUDA
    dtype = tensor.dtype if dtype is None else dtype
    if target == source:
        if dtype == tensor.dtype and not copy:
            return tensor
        return torch.Tensor.to(tensor, dtype=dtype, copy=copy)  # an op on one device: dispatched and checked
    if target.type == "cuda":
        return _ToCuda.apply(tensor, dtype)
    if target.type == "cpu":
        return _ToCpu.apply(tensor, dtype)
    raise RuntimeError(f"fake CUDA: cannot move a tensor to {target}")


class _Moves(TorchFunctionMode):
    """Device moves by the claimed devices: ``.to(...)``, ``.cpu()``, ``.cuda()``, ``.type_as(...)``."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is torch.Tensor.to:
            tensor, rest = args[0], list(args[1:])
            copy = bool(kwargs.pop("copy", False))
            other = kwargs.pop("other", None)
            if other is None and rest and isinstance(rest[0], torch.Tensor):
                other = rest.pop(0)
            if other is not None:
                return _move(tensor, _device_of(other), other.dtype, copy)
            device, dtype, _, _ = torch._C._nn._parse_to(*rest, **kwargs)
            return _move(tensor, device, dtype, copy)
        if func is torch.Tensor.cpu:
            return _move(args[0], CPU, None, False)
        if func is torch.Tensor.cuda:
            return _move(args[0], CUDA, None, False)
        if func is torch.Tensor.type_as:
            return _move(args[0], _device_of(args[1]), args[1].dtype, False)
        if func is torch.Tensor.tolist and isinstance(args[0], FakeCudaTensor):
            return args[0].elem.tolist()  # a synchronising read, allowed on CUDA
        if func in (torch.Tensor.numpy, torch.Tensor.__array__) and isinstance(args[0], FakeCudaTensor):
            raise TypeError(
                "can't convert cuda:0 device type tensor to numpy. Use Tensor.cpu() to copy the tensor to host "
                "memory first. (fake CUDA)"
            )
        return func(*args, **kwargs)


class DeviceMismatchError(MISMATCH_BASE):
    """FakeTensorMode's device-mismatch error (``MISMATCH_BASE``), its message extended by the op and its tensor
    arguments."""

    def __init__(self, func, common_device: torch.device, device: torch.device, tensors: list[torch.Tensor]) -> None:
        self.func, self.common_device, self.device = func, common_device, device
        described = ", ".join(f"{_device_of(t)} {t.dtype} {tuple(t.shape)}" for t in tensors)
        RuntimeError.__init__(
            self,
            "Expected all tensors to be on the same device, but found at least two devices, "
            f"{common_device} and {device}! (fake CUDA: {func} on tensors [{described}])",
        )


def _device_of(value: Any) -> torch.device | None:
    if isinstance(value, FakeCudaTensor):
        return CUDA
    if isinstance(value, torch.Tensor):
        return value.device
    return None


def _is_cpu_scalar(value: Any) -> bool:
    return isinstance(value, torch.Tensor) and not isinstance(value, FakeCudaTensor) and value.dim() == 0


def _requested_device(kwargs: dict) -> torch.device | None:
    device = kwargs.get("device")
    return None if device is None else torch.device(device)


def _common_device(func, tensors: list[torch.Tensor]) -> torch.device | None:
    """The device an op runs on, raising on CUDA's forbidden mixes (FakeTensor's rule: CPU scalars go anywhere)."""
    common = None
    common_is_scalar = False
    for tensor in tensors:
        if _is_backward_fill(tensor):
            continue
        device = _device_of(tensor)
        scalar = _is_cpu_scalar(tensor)
        if common is None:
            common, common_is_scalar = device, scalar
            continue
        if device == common:
            common_is_scalar = common_is_scalar and scalar
            continue
        if scalar:
            continue
        if common_is_scalar:
            common, common_is_scalar = device, scalar
            continue
        raise DeviceMismatchError(func, common, device, tensors)
    return common


def _check_generator(func, kwargs: dict, device: torch.device | None) -> None:
    generator = kwargs.get("generator")
    if generator is not None and device is not None and device.type == "cuda" and generator.device.type != "cuda":
        raise RuntimeError(
            f"{func}: Expected a 'cuda' device type for generator but found '{generator.device.type}' (fake CUDA)"
        )


def _op_device(func, args: tuple, kwargs: dict) -> torch.device | None:
    """Device of the op's outputs after checking CUDA's device rules on its arguments."""
    requested = _requested_device(kwargs)
    if func in MOVE_OPS:
        if func is aten._to_copy.default:
            source = _device_of(args[0])
            if requested is None or (requested.type == "cpu" and source.type == "cuda"):
                return source  # Python's moves to the CPU went through ``_Moves``: this one is C++ (see below)
            return requested
        destination = args[0]
        return _device_of(destination[0] if isinstance(destination, (list, tuple)) else destination)
    if func in INDEX_OPS:
        indexed, indices = args[0], args[1]
        device = _device_of(indexed)
        for index in indices:
            index_device = _device_of(index)
            if index_device is not None and index_device != device and index_device != CPU:
                raise RuntimeError(
                    f"{func}: indices should be either on cpu or on the same device as the indexed tensor "
                    f"({device}), got an index on {index_device} (fake CUDA)"
                )
        rest = [value for value in args[2:] if isinstance(value, torch.Tensor)]
        _common_device(func, [indexed, *rest])
        return device
    tensors = [value for value in tree_flatten((args, kwargs))[0] if isinstance(value, torch.Tensor)]
    device = _common_device(func, tensors)
    if requested is not None and not (requested.type == "cpu" and device is not None and device.type == "cuda"):
        device = requested
    # else: an op on a CUDA tensor asking for the CPU (``new_zeros(..., device=cpu)``) comes from C++ code that took
    # the options of a FakeCudaTensor, whose metadata says CPU (autograd's formulas do): it means the tensor's own
    # device. Python code asking for the CPU that way would be missed here (``new_zeros`` / ``*_like`` with an
    # explicit ``device="cpu"``); the library has no such call.
    _check_generator(func, kwargs, device)
    return device


def _in_backward() -> bool:
    """Whether the autograd engine is running a backward node on this thread."""
    return torch._C._current_autograd_node() is not None


BACKWARD_FILL: dict[int, weakref.ref] = {}
"""CPU tensors a backward formula built without a tensor argument, and their views (``unbind``'s and ``split``'s fill
the gradients of their unused outputs with ``at::zeros(sizes, options).expand(...)``): their options come from a
FakeCudaTensor's CPU metadata, where on CUDA they would be the graph's device. They take the device of the tensors
they meet (``_is_backward_fill``; by identity: a tensor's ``==`` compares values)."""


def _is_backward_fill(tensor: torch.Tensor) -> bool:
    entry = BACKWARD_FILL.get(id(tensor))
    return entry is not None and entry() is tensor


def _mark_backward_fill(tensor: torch.Tensor) -> None:
    key = id(tensor)
    BACKWARD_FILL[key] = weakref.ref(tensor, lambda _: BACKWARD_FILL.pop(key, None))


def _unwrap(value: Any) -> Any:
    return value.elem if isinstance(value, FakeCudaTensor) else value


def _wrap(value: Any) -> Any:
    if isinstance(value, torch.Tensor) and not isinstance(value, FakeCudaTensor) and value.device.type == "cpu":
        return FakeCudaTensor(value)
    return value


def _run(func, args: tuple, kwargs: dict) -> Any:
    device = _op_device(func, args, kwargs)
    kwargs = dict(kwargs)
    if "device" in kwargs and kwargs["device"] is not None and torch.device(kwargs["device"]).type == "cuda":
        kwargs["device"] = CPU
    out = func(*tree_map(_unwrap, args), **tree_map(_unwrap, kwargs))
    inputs = [value for value in tree_flatten((args, kwargs))[0] if isinstance(value, torch.Tensor)]
    if _in_backward() and all(_is_backward_fill(value) for value in inputs):  # a fill built, or viewed (expand)
        for value in tree_flatten(out)[0]:
            if isinstance(value, torch.Tensor) and value.device.type == "cpu":
                _mark_backward_fill(value)
    if func in (aten.copy_.default, aten._foreach_copy_.default) or (
        isinstance(func, torch._ops.OpOverload) and func._schema.is_mutable and out is _unwrap(args[0])
    ):
        return args[0]  # in place: the (wrapped) destination itself
    if device is not None and device.type == "cuda":
        return tree_map(_wrap, out)
    return out


class FakeCudaMode(TorchDispatchMode):
    """Routes every aten op through the CUDA device checks (see the module docstring); counts the ops run per device
    and dtype in ``ops`` (key ``(op name, device type, dtype of the first output)``), so a test can say where the
    work ran."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[tuple[str, str, torch.dtype | None]] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = _run(func, args, kwargs or {})
        first = next((value for value in tree_flatten(out)[0] if isinstance(value, torch.Tensor)), None)
        device = "none" if first is None else _device_of(first).type
        self.ops[(func.overloadpacket.__name__, device, None if first is None else first.dtype)] += 1
        return out

    def count(self, op: str, device: str = "cuda", dtype: torch.dtype | None = None) -> int:
        """How many times the aten op ``op`` (e.g. "linalg_eigh") ran with outputs on ``device`` (and ``dtype``)."""
        return sum(
            n for (name, where, kind), n in self.ops.items()
            if name == op and where == device and (dtype is None or kind == dtype)
        )  # fmt: skip


@contextlib.contextmanager
def fake_cuda() -> Iterator[FakeCudaMode]:
    """Run the body as if a CUDA device existed: ``device="cuda"`` gives ``FakeCudaTensor``s, every op checks its
    devices. ``torch.cuda.is_available()`` stays False (code must take the device from its tensors, not probe)."""
    cuda_module = torch.cuda
    was_initialized = cuda_module._initialized
    # Factory functions with a CUDA device first initialise CUDA (no driver here); mark it initialised so the call
    # reaches the mode, and let device guards be no-ops (what FakeTensorMode does on a machine without CUDA).
    # ``torch.tensor(data, device="cuda")`` copies outside the dispatcher unless only CPU tensors are lifted (then
    # the copy to CUDA is an op the mode sees), as under FakeTensorMode.
    torch._C._ensureCUDADeviceGuardSet()
    only_lift_cpu = torch._C._only_lift_cpu_tensors()
    torch._C._set_only_lift_cpu_tensors(True)
    cuda_module._initialized = True
    # ``module.to("cuda")`` must give parameters that are FakeCudaTensors, not CPU parameters whose ``.data`` is one.
    overwrite_params = torch.__future__.get_overwrite_module_params_on_conversion()
    torch.__future__.set_overwrite_module_params_on_conversion(True)
    try:
        with FakeCudaMode() as mode, _Moves():
            yield mode
    finally:
        cuda_module._initialized = was_initialized
        torch.__future__.set_overwrite_module_params_on_conversion(overwrite_params)
        torch._C._set_only_lift_cpu_tensors(only_lift_cpu)


def is_fake_cuda(tensor: Any) -> bool:
    """True for a tensor on (fake) CUDA."""
    return isinstance(tensor, FakeCudaTensor)


def values(tensor: torch.Tensor) -> torch.Tensor:
    """The CPU values of a fake CUDA tensor (a CPU tensor unchanged), detached, for assertions outside the mode."""
    return _unwrap(tensor).detach()
