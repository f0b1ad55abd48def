"""Small constants on a compute device, made once.

`torch.tensor([...], device="cuda")` builds the values on the host and copies them to the device, and a copy from
ordinary host memory makes the host wait until the device has finished its queued work: inside a training step,
every such call stalls the GPU. The renderer and the fields read their lattice shapes, strides and offsets through
`constant`, which makes each once per device and keeps it.
"""

from __future__ import annotations

import torch
from torch import Tensor

_MADE: dict[tuple, Tensor] = {}


def constant(values, device: torch.device | str, dtype: torch.dtype = torch.float32) -> Tensor:
    """`torch.tensor(values, dtype=dtype, device=device)`, made on the first call for these values and reused after
    (treat it as read-only). `values`: a number or a (nested) tuple of numbers."""
    key = (values, str(device), dtype)
    made = _MADE.get(key)
    if made is None:
        made = _MADE[key] = torch.tensor(values, dtype=dtype).to(device)
    return made


def from_host(t: Tensor, device: torch.device | str) -> Tensor:
    """A host tensor on `device`, copied without making the host wait: from page-locked memory on a GPU."""
    device = torch.device(device)
    if device.type == "cuda":
        t = t.pin_memory()
    return t.to(device, non_blocking=True)
