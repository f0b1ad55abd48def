"""Packing the samples a filter keeps into a list, with or without the host waiting for the device.

The renderer and the mixture evaluate fields on the samples that pass a filter (occupied cells, V_D, a colour
threshold, the samples routed to one expert). `Packer.pack(name, mask)` lists them:

- `DYNAMIC` (the CPU default): `mask.nonzero()`, exactly the kept samples. On a GPU this makes the host wait for
  the device, since the list's length is read back before anything can be queued after it.
- `Budgets` (static shapes, the GPU default): every filter `name` has a budget, a fixed number of slots sized from
  the counts it has seen (`margin` over the largest, rounded up to `quantum`); ``pack_static` fills the
  slots with the kept samples in order and pads the rest, so nothing waits and every shape is known ahead (what a
  compiled step needs). The budget is set by one wait on its first use; after that the largest count and whether it
  overflowed are kept on the device and read only by `settle` (the training loop calls it on its logging steps,
  the image renderer after each image), which resizes the budgets. A filter that keeps more samples than its
  budget holds packs the first ones only: the caller treats the result as invalid (a training step is skipped, an
  image rendered again), so a result never silently misses a sample.

A `Packed` list gathers with `rows` (pads read row 0, whose value is then dropped) and scatters back with
`scatter` (pads land in a spare row past the end, which is cut off).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor


@dataclass
class Packed:
    """The kept entries of a mask of length `n`: `rows` (P,) their indices in order, `live` (P,) bool which slots
    hold one (None: every slot does, the dynamic packing)."""

    rows: Tensor
    live: Tensor | None
    n: int

    def __len__(self) -> int:
        return self.rows.shape[0]

    @property
    def dest(self) -> Tensor:
        """Where each slot's value goes in `scatter`: its row, or the spare row `n` for a pad."""
        return self.rows if self.live is None else torch.where(self.live, self.rows, self.n)

    def scatter(self, values: Tensor, fill: float = 0.0) -> Tensor:
        """(P, ...) values of the slots -> (n, ...): each kept entry's value at its row, `fill` elsewhere.
        Differentiable with respect to `values` (a pad's gradient is 0)."""
        if self.live is None:
            out = values.new_full((self.n, *values.shape[1:]), fill)
            return out.index_put((self.rows,), values)
        out = values.new_full((self.n + 1, *values.shape[1:]), fill)
        return out.index_put((self.dest,), values)[: self.n]

    def mask(self, values: Tensor) -> Tensor:
        """`values` (P, ...) with the pads' entries set to 0 (False): a pad's value, weight or count must not count."""
        if self.live is None:
            return values
        return torch.where(self.live.reshape(-1, *([1] * (values.dim() - 1))), values, values.new_zeros(()))

    keep = mask  # of a bool mask over the slots: the live slots where it holds

    def count(self) -> int | Tensor:
        """How many entries are kept: an int (dynamic), or a device count (static, read without waiting later)."""
        return self.rows.shape[0] if self.live is None else self.live.sum()

    def add(self, out: Tensor, values: Tensor) -> Tensor:
        """out (n, ...) + each slot's value (P, ...) at its row (a pad adds nothing); differentiable."""
        return out.index_add(0, self.rows, self.mask(values))

    def sub(self, inner: "Packed") -> "Packed":
        """The entries of this list's slots that `inner` (a packing of a mask over those slots) keeps, as rows of the
        original length-`n` mask."""
        rows = self.rows[inner.rows]
        if inner.live is None and self.live is None:
            return Packed(rows, None, self.n)
        live = inner.live if self.live is None else (self.live[inner.rows] if inner.live is None
                                                     else inner.live & self.live[inner.rows])
        return Packed(rows, live, self.n)


class Packer:
    """How a renderer user packs the samples its filters keep; see the module docstring."""

    static = False

    def pack(self, name: str, mask: Tensor) -> Packed:
        """mask (N,) bool -> the kept entries. `name` tells filters apart (each has its own budget)."""
        return Packed(mask.nonzero().squeeze(-1), None, mask.shape[0])

    def keep_where(self, test: Callable[[Tensor], Tensor], points: Tensor, keep: Tensor) -> Tensor:
        """keep & test(points), points (N, 3), keep (N,) bool: only the kept points are tested (fewer; listing them
        costs nothing on the CPU). A static packer tests every point instead, so nothing waits for the device."""
        return self.where_kept(test, points, keep, False)

    def where_kept(self, fn: Callable[[Tensor], Tensor], points: Tensor, keep: Tensor, fill) -> Tensor:
        """(N,) fn(points) where `keep`, `fill` elsewhere: fn runs on the kept points only (a static packer runs it
        on every point instead, so nothing waits for the device)."""
        rows = keep.nonzero().squeeze(-1)  # listed once, for the lookup and the write back
        values = fn(points[rows])
        return torch.full(keep.shape, fill, dtype=values.dtype, device=keep.device).index_put((rows,), values)

    def overflowed(self) -> Tensor | None:
        """Whether a filter since `begin` kept more than its budget (a device bool), or None (nothing can)."""
        return None

    def begin(self) -> None:
        """A new batch (a training step, an image chunk): `overflowed` restarts."""

    def settle(self) -> bool:
        """Resize the budgets to the counts seen (reads them from the device). -> whether one overflowed since the
        last `settle`."""
        return False


DYNAMIC = Packer()


def pack_static(mask: Tensor, size: int, count: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """mask (N,) bool -> (rows (size,): the indices of its first `size` True entries in order, then 0;
    live (size,) bool: which slots hold one). `count`: mask.sum(), when the caller has it. An exclusive prefix sum
    gives each kept entry its slot, and one scatter writes them (what `torch.nonzero_static` computes, in operators
    every device and the compiler have)."""
    n = mask.shape[0]
    slot = torch.cumsum(mask, 0) - 1
    slot = torch.where(mask & (slot < size), slot, size)  # dropped entries go to a spare slot, cut off below
    rows = torch.zeros(size + 1, dtype=torch.long, device=mask.device)
    rows = rows.scatter(0, slot, torch.arange(n, device=mask.device))[:size]
    live = torch.arange(size, device=mask.device) < (mask.sum() if count is None else count)
    return rows, live


class Budget:
    """A fixed number of slots for one filter's kept samples (see `Budgets`)."""

    def __init__(self, margin: float, quantum: int):
        self.margin, self.quantum = margin, quantum
        self.size: int | None = None
        self.peak: Tensor | None = None  # the largest count since the last settle, on the device

    def fit(self, count: int) -> int:
        return max(self.quantum, self.quantum * math.ceil(count * self.margin / self.quantum))

    def pack(self, mask: Tensor) -> tuple[Packed, Tensor]:
        """-> (the packed entries, whether they overflowed the budget: a device bool)."""
        count = mask.sum()
        if self.size is None:
            self.size = self.fit(int(count))  # the one wait: a budget's first use
        self.peak = count if self.peak is None else torch.maximum(self.peak, count)
        return Packed(*pack_static(mask, self.size, count), mask.shape[0]), count > self.size

    def settle(self) -> bool:
        if self.peak is None:
            return False
        peak, self.peak = int(self.peak), None
        over = peak > (self.size or 0)
        if over or self.fit(peak) * 2 < (self.size or 0):  # grow past the peak, or shrink when twice too large
            self.size = self.fit(peak)
        return over


class Budgets(Packer):
    """Static packing: one `Budget` per filter name, `margin` over the largest count seen, in steps of `quantum`."""

    static = True

    def __init__(self, margin: float = 1.25, quantum: int = 1024):
        self.margin, self.quantum = margin, quantum
        self.budgets: dict[str, Budget] = {}
        self._over: Tensor | None = None

    def pack(self, name: str, mask: Tensor) -> Packed:
        budget = self.budgets.get(name)
        if budget is None:
            budget = self.budgets[name] = Budget(self.margin, self.quantum)
        packed, over = budget.pack(mask)
        self._over = over if self._over is None else self._over | over
        return packed

    def keep_where(self, test: Callable[[Tensor], Tensor], points: Tensor, keep: Tensor) -> Tensor:
        return keep & test(points)

    def where_kept(self, fn: Callable[[Tensor], Tensor], points: Tensor, keep: Tensor, fill) -> Tensor:
        values = fn(points)
        return torch.where(keep, values, torch.full((), fill, dtype=values.dtype, device=values.device))

    def overflowed(self) -> Tensor | None:
        return self._over

    def begin(self) -> None:
        self._over = None

    def settle(self) -> bool:
        return any([b.settle() for b in self.budgets.values()])  # a list: settle every budget

    def sizes(self) -> dict[str, int | None]:
        return {name: b.size for name, b in self.budgets.items()}


def packer_for(device: torch.device | str, static: bool = False) -> Packer:
    """How to pack on `device`: static budgets on a GPU, where a wait stalls the device, and wherever `static` asks
    for them (a compiled step needs fixed shapes); the dynamic packing on the CPU, where nothing waits and the exact
    lists cost least."""
    return Budgets() if static or torch.device(device).type != "cpu" else DYNAMIC
