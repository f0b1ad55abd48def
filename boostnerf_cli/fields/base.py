"""The Field contract: everything that answers "what is at point x, seen from direction d?";
and the Expert contract: what an expert family adds so that the stages can train and save it.

Every expert family and the mixture of experts satisfy the Field contract; the renderer knows nothing else.
Shapes: N points; xyz (N, 3) world coordinates; dirs (N, 3) unit view directions (pointing from
the camera into the scene). Density sigma (N,) is non-negative, per world unit; rgb (N, 3) in [0, 1].

Optional, for fields that share work between the renderer's two passes (the mixture of experts
routes each sample once; an Instant-NGP-style expert encodes each sample once): `batch_view(packer)`
returns a per-batch view whose `density(xyz, live)` works as the field's and `color_rows(rows, dirs, live)` gives
the colour of the samples `rows` of its last `density` call; `live` (None, or a bool per sample) tells the samples
from the pads of a static packing (render/packing.py), which must not count. The renderer uses them when present.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict
from typing import Callable, Protocol, TypeVar, runtime_checkable

import torch
from torch import Tensor, nn

from boostnerf_cli.fields import grid as G

# Rows per block when a field is evaluated without gradients on the CPU (`blockwise`): a block's widest activations
# (8192 rows of a 128-wide hidden layer: 4 MB) stay near the core's cache instead of streaming through memory layer
# after layer. A DVGO expert's colour over 100k samples, one thread: 148 -> 80 ms (128 wide), 93 -> 47 ms (64 wide);
# 4096 rows give the same.
BLOCK_ROWS = 8192

F_ = TypeVar("F_", bound=Callable)


def blockwise(method: F_) -> F_:
    """A method of (N, ...) row-aligned tensors -> a tensor, or a tuple of them, of N rows each: run block by block
    of `BLOCK_ROWS` rows when nothing needs its gradient on the CPU (rendering), the values concatenated (the same to
    float32 rounding: a matrix product over fewer rows may sum in another order). With gradients, on a GPU, or while
    compiling it runs once over all rows."""

    @functools.wraps(method)
    def run(self, *args: Tensor):
        n = args[0].shape[0]
        if n <= BLOCK_ROWS or torch.is_grad_enabled() or args[0].device.type != "cpu" or \
                torch.compiler.is_compiling():
            return method(self, *args)
        blocks = [method(self, *(a[i : i + BLOCK_ROWS] for a in args)) for i in range(0, n, BLOCK_ROWS)]
        if isinstance(blocks[0], tuple):  # several outputs: each concatenated
            return tuple(torch.cat(parts) for parts in zip(*blocks))
        return torch.cat(blocks)

    return run  # type: ignore[return-value]


@runtime_checkable
class Field(Protocol):
    """A radiance field: density and colour at points seen from directions."""

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        """(N, 3), (N, 3) -> sigma (N,), rgb (N, 3)."""
        ...

    def density(self, xyz: Tensor) -> Tensor:
        """(N, 3) -> sigma (N,), without computing colour (used to skip empty space)."""
        ...

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        """(N, 3), (N, 3) -> rgb (N, 3) only: called on the samples that survive the density pass."""
        ...


@runtime_checkable
class Expert(Field, Protocol):
    """What the stages need of an expert family beyond the Field contract (dvgo, tensorf, ngp).

    `bbox` (2, 3) is a buffer in the state dict; outside it the expert is empty. `unit` is the fixed
    length density is measured in (sigma = softplus(raw + shift) / unit) and sets the render step;
    `shape` is the expert's lattice (its occupancy grid follows it); `spatial_res` its final lattice
    side (the default resolution of a mixture's density volume when it is the smallest expert).
    """

    family: str
    grows: bool  # False: `regrid` is never called (fixed-size tables)
    unit: float

    @property
    def shape(self) -> tuple[int, int, int]: ...

    @property
    def spatial_res(self) -> int: ...

    def regrid(self, n_voxels: int) -> None:
        """Grow (resample) onto a lattice of about `n_voxels` voxels over the same box."""
        ...

    def resize_to(self, shape: tuple[int, int, int]) -> None:
        """Reallocate for a lattice `shape` before loading a checkpoint's state dict."""
        ...

    def init_density(self, density) -> None:
        """Warm start: make the expert's density follow `density(xyz) -> sigma` (the coarse geometry)."""
        ...

    def param_groups(self, lr_grid: float, lr_mlp: float) -> list[dict]: ...

    def regularization(self) -> Tensor | None:
        """A family-specific term added to the training loss (already weighted), or None."""
        ...

    def config_dict(self) -> dict:
        """JSON metadata with `family`, `config`, `unit`, `shape`; `from_config(meta, bbox)` inverts it."""
        ...


class ExpertModule(nn.Module):
    """The set-up every expert family shares (subclass it and set `family`, `config_type`, and `gate_grid` where a
    dense one does not fit): its config `cfg`, its box `bbox` (a buffer, saved in the state dict), the density shift
    (sigma = softplus(raw + shift) / unit has opacity `cfg.alpha_init` over one unit where raw = 0), and
    `config_dict` / `from_config`."""

    family = ""
    config_type: type
    gate_grid = "dense"  # the gate's feature grid for a mixture of this family's experts (moe.gate_grid: auto)

    def __init__(self, cfg, bbox: Tensor):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("bbox", bbox.detach().clone().float())
        # log(1/(1-a) - 1), finite for any a in (0, 1)
        self.shift = math.log(cfg.alpha_init) - math.log1p(-cfg.alpha_init)

    def spacing(self, shape: tuple[int, int, int]) -> float:
        """Mean distance between the vertices of a lattice `shape` spanning the box."""
        size = self.bbox[1] - self.bbox[0]
        return float((size / (torch.tensor(shape, device=size.device) - 1)).mean())

    def inside(self, xyz: Tensor) -> Tensor:
        """(N, 3) -> (N,) bool: in the box, faces included."""
        return G.inside_box(xyz, self.bbox)

    def config_dict(self) -> dict:
        return {"family": self.family, "config": asdict(self.cfg), "unit": self.unit, "shape": list(self.shape)}

    @classmethod
    def from_config(cls, meta: dict, bbox: Tensor):
        return cls(cls.config_type(**meta["config"]), bbox, unit=meta["unit"], shape=tuple(meta["shape"]))


class BareField:
    """`field` through the Field contract alone, without its optional per-batch view, so each of the
    renderer's passes computes from scratch; `regularization` passes through for training. What the
    per-batch view saves is measured (scripts/measure_costs.py) and tested against it."""

    def __init__(self, field):
        self.field = field

    def density(self, xyz: Tensor) -> Tensor:
        return self.field.density(xyz)

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        return self.field.color(xyz, dirs)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        return self.field.query(xyz, dirs)

    def regularization(self):
        return self.field.regularization()
