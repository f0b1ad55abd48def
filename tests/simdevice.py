"""A simulated accelerator for machines with no GPU: tensors that live on the CPU but say `meta`.

A CPU-only PyTorch cannot create a tensor that reports `cuda` (the CUDA device guard is not linked in),
so the simulated GPU takes the name of PyTorch's `meta` device, whose guard exists. Under
`simulated_gpu()`, every tensor moved to or created on `meta` is a `SimTensor`: a wrapper that holds
real CPU data and reports device `meta`. Every operator then checks what a real GPU's kernels check:
all tensor arguments on one device (0-dim CPU tensors excepted, as on CUDA; copies between devices
allowed), else the same "Expected all tensors to be on the same device" error a GPU raises. The tool's
device resolution is patched so that `--device cuda` and `--device auto` pick it. So a tensor that a
stage leaves on the CPU next to the model's is caught on a CPU-only machine, through the whole pipeline.

`SyncCounter` counts, inside it, the operators that would make the host wait for a real GPU (`is_sync`): on the
simulated device a copy to or from the host dispatches like any operator, so a step's waits can be counted on a
CPU (scripts/step_profile.py, tests/test_syncs.py).

Test-only: it proves device placement, not CUDA kernels (those are scripts/gpu-check.sh's job).
"""

from __future__ import annotations

import importlib
from collections import Counter
from contextlib import ExitStack, contextmanager
from typing import Iterator
from unittest import mock

import torch
from torch.utils._python_dispatch import TorchDispatchMode

GPU = torch.device("meta")
aten = torch.ops.aten

# Operators that legitimately see two devices: copies between them, and metadata-only calls.
_CROSS_DEVICE = {aten.copy_.default, aten._to_copy.default, aten._has_compatible_shallow_copy_type.default,
                 aten.detach.default, aten._local_scalar_dense.default}


class SimTensor(torch.Tensor):
    """A CPU tensor that reports the simulated GPU as its device."""

    elem: torch.Tensor

    @staticmethod
    def __new__(cls, elem: torch.Tensor):
        r = torch.Tensor._make_wrapper_subclass(cls, elem.shape, strides=elem.stride(),
                                                storage_offset=elem.storage_offset(), dtype=elem.dtype,
                                                layout=elem.layout, device=GPU, requires_grad=False)
        r.elem = elem
        return r

    def __repr__(self) -> str:
        return f"SimTensor({self.elem!r})"

    @property
    def is_meta(self) -> bool:  # it holds data: load_state_dict must copy into it, not skip it as a meta tensor
        return False

    def tolist(self):  # allowed on a GPU tensor (it copies to the host)
        return self.elem.tolist()

    def __reduce_ex__(self, proto):
        # torch.save of a GPU tensor, loaded with map_location="cpu", gives its CPU copy: the same here.
        return torch.Tensor.__reduce_ex__(self.elem.detach().clone(), proto)

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        return _dispatch(func, args, kwargs or {})


def _device_of(t: torch.Tensor) -> str | None:
    if isinstance(t, SimTensor):
        return "gpu"
    if t.device.type == "cpu" and t.dim() == 0:
        return None  # CPU scalars are accepted by GPU kernels
    return str(t.device)


def _tensors(obj, out: list) -> list:
    """The tensors in an operator's arguments (nested lists, tuples and dicts): what `tree_flatten` finds, faster."""
    if isinstance(obj, torch.Tensor):
        out.append(obj)
    elif isinstance(obj, (list, tuple)):
        for x in obj:
            _tensors(x, out)
    elif isinstance(obj, dict):
        for x in obj.values():
            _tensors(x, out)
    return out


def _map_tensors(fn, obj):
    """`obj` (an operator's arguments or outputs: nested lists, tuples and dicts) with `fn` applied to each tensor
    (`tree_map`'s result, faster). A sequence keeps its type: list, tuple, named tuple or torch.return_types."""
    if isinstance(obj, torch.Tensor):
        return fn(obj)
    if isinstance(obj, dict) and obj:
        return {k: _map_tensors(fn, v) for k, v in obj.items()}
    if not isinstance(obj, (list, tuple)) or not obj:
        return obj
    items = [_map_tensors(fn, x) for x in obj]
    if isinstance(obj, list) or type(obj) is tuple:
        return items if isinstance(obj, list) else tuple(items)
    return type(obj)(*items) if hasattr(obj, "_fields") else type(obj)(items)


def _plain(t: torch.Tensor) -> torch.Tensor:
    return t.elem if isinstance(t, SimTensor) else t


def _on_gpu(t: torch.Tensor) -> torch.Tensor:
    return t if isinstance(t, SimTensor) else SimTensor(t)


def _dispatch(func, args, kwargs):
    devices = {d for d in map(_device_of, _tensors((args, kwargs), [])) if d is not None}
    if len(devices) > 1 and func not in _CROSS_DEVICE:
        raise RuntimeError("Expected all tensors to be on the same device, but found at least two devices, "
                           f"{' and '.join(sorted(d.replace('gpu', 'the simulated GPU') for d in devices))} "
                           f"(in {func})")
    on_gpu = "gpu" in devices
    if func in (aten._to_copy.default, aten.copy_.default):
        on_gpu = isinstance(args[0], SimTensor)
    if kwargs.get("device") is not None:
        on_gpu = torch.device(kwargs["device"]).type == GPU.type
        kwargs = {**kwargs, "device": torch.device("cpu")}
    plain_args, plain_kwargs = _map_tensors(_plain, args), _map_tensors(_plain, kwargs)
    out = func(*plain_args, **plain_kwargs)
    if args and isinstance(args[0], torch.Tensor) and out is plain_args[0]:
        return args[0]  # in-place operators return their argument
    if func is aten._local_scalar_dense.default or not on_gpu:
        return out
    return _map_tensors(_on_gpu, out)


class _Mode(TorchDispatchMode):
    """Factory calls and moves of plain tensors (no SimTensor argument yet) pass through here."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        return _dispatch(func, args, kwargs or {})


def _moved(make):
    def wrapper(data, *args, device=None, **kwargs):
        t = make(data, *args, **kwargs)
        return t if device is None else t.to(device)

    return wrapper


@contextmanager
def simulated_gpu() -> Iterator[str]:
    """Run the block as if a GPU were present; -> the device name the tool resolves to."""
    from boostnerf_cli.stages import common

    autocast, autocast_enabled = torch.autocast, torch.is_autocast_enabled
    # The compiler lists torch's functions when it is first imported (`torch.is_autocast_enabled` among those it
    # folds): imported inside the block, it would list the stand-ins below for good, and a compiled step traced later
    # would break at torch's own.
    importlib.import_module("torch._dynamo.variables.torch")

    def resolve(name: str) -> str:
        if name not in ("auto", "cuda", "cpu"):
            raise AssertionError(f"unexpected device {name!r}")
        return "cpu" if name == "cpu" else GPU.type

    with ExitStack() as stack:
        stack.enter_context(mock.patch.object(common, "resolve_device", resolve))
        # autocast knows no `meta` device type: the simulated GPU's autocast is the CPU's.
        stack.enter_context(mock.patch.object(
            torch, "autocast",
            lambda device_type, *a, **k: autocast("cpu" if device_type == GPU.type else device_type, *a, **k)))
        stack.enter_context(mock.patch.object(
            torch, "is_autocast_enabled", lambda *a: autocast_enabled(*("cpu" if d == GPU.type else d for d in a))))
        # torch.tensor / as_tensor with a device move the data in C++, past the dispatch mode: build on
        # the CPU, then move through it.
        for name in ("tensor", "as_tensor"):
            make = getattr(torch, name)
            stack.enter_context(mock.patch.object(torch, name, _moved(make)))
        from torch.optim import optimizer

        fused = optimizer._get_fused_kernels_supported_devices
        stack.enter_context(mock.patch.object(optimizer, "_get_fused_kernels_supported_devices",
                                              lambda: [*fused(), GPU.type]))
        stack.enter_context(_Mode())
        yield GPU.type


# Operators that make the host wait for the device when their inputs are on a GPU: their output's size or value is
# read on the host (nerfacc's coding notes; PyTorch's own torch.cuda.set_sync_debug_mode flags them).
SYNC_OPS = {
    aten._local_scalar_dense.default,  # .item(), float(t), bool(t), int(t)
    aten.is_nonzero.default,
    aten.equal.default,
    aten.nonzero.default,
    aten.argwhere.default,
    aten.masked_select.default,
    aten._unique.default,
    aten._unique2.default,
    aten.unique_dim.default,
    aten.unique_consecutive.default,
    aten.bincount.default,  # its length is max + 1, read on the host
    aten.histogram.bin_ct,
}
_REPEAT = {aten.repeat_interleave.Tensor, aten.repeat_interleave.self_Tensor}  # without output_size: reads the total
_INDEXING = {aten.index.Tensor, aten.index_put.default, aten.index_put_.default, aten._index_put_impl_.default}
_COPIES = {aten._to_copy.default, aten.copy_.default}


def _on_device(t) -> bool:
    return isinstance(t, torch.Tensor) and t.device.type != "cpu"


def is_sync(func, args, kwargs) -> bool:
    """Whether operator `func` on these arguments makes the host wait for a GPU: a `SYNC_OPS` operator, indexing
    with a boolean mask (turned into indices by nonzero), repeat_interleave without output_size, on device tensors;
    or a copy between host and device that is not `non_blocking` (a 0-dim host scalar going into a kernel is not a
    copy)."""
    flat = _tensors((args, kwargs), [])
    if func in _COPIES:
        if func is aten._to_copy.default:
            src, dst = args[0].device, torch.device(kwargs.get("device") or args[0].device)
            scalar = args[0].dim() == 0 and src.type == "cpu"
        else:
            dst, src = args[0].device, args[1].device
            scalar = args[1].dim() == 0 and src.type == "cpu"
        if (src.type == "cpu") == (dst.type == "cpu") or scalar:
            return False
        return not (kwargs.get("non_blocking") or (len(args) > 2 and args[2] is True))
    if not any(_on_device(t) for t in flat):
        return False
    if func in SYNC_OPS:
        return True
    if func in _REPEAT:
        return kwargs.get("output_size") is None
    if func in _INDEXING:
        indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (indices or ()))
    return False


class SyncCounter(TorchDispatchMode):
    """Counts, by operator, what would make the host wait for a GPU (`is_sync`) while `active`; also a device
    tensor's `tolist()`, which copies it to the host past the dispatcher. Use it inside `simulated_gpu()`."""

    def __init__(self):
        super().__init__()
        self.syncs: Counter = Counter()
        self.active = True
        self._tolist = None

    def __enter__(self):
        self._tolist = SimTensor.tolist
        counter = self

        def tolist(tensor):
            if counter.active:
                counter.syncs["Tensor.tolist"] += 1
            return counter._tolist(tensor)

        SimTensor.tolist = tolist
        return super().__enter__()

    def __exit__(self, *exc):
        SimTensor.tolist = self._tolist
        return super().__exit__(*exc)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if self.active and is_sync(func, args, kwargs):
            self.syncs[str(func)] += 1
        return func(*args, **kwargs)

    @property
    def total(self) -> int:
        return sum(self.syncs.values())
