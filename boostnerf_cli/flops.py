"""Floating-point operations of rendering, counted per image.

`torch.utils.flop_counter.FlopCounterMode` counts matrix products only (the MLPs). Everything else
that scales with the number of samples is counted analytically where it is computed, into the
counter that `count_flops()` opens (a context manager, like FlopCounterMode itself; outside one,
counting costs a single ContextVar lookup):

  trilinear corners   40 flops per point   (normalise 3x3, floor/clamp 3x3, 8 weights x 2 + 6)
  trilinear blend     16 C per point       (8 corners x C channels x multiply-add)
  hash indices        see fields that hash (documented there)
  compositing          8 per sample slot   (tau, expm1, cumsum, exp, weight, opacity sum, depth
                                            multiply-add; the 3-channel colour's 6 multiply-adds are an
                                            einsum, which FlopCounterMode counts: 14 in all)
  softmax / top-k     4 M per routed sample
Method documented in docs/flops.md.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Iterator

from torch.utils.flop_counter import FlopCounterMode

CORNER_FLOPS = 40
COMPOSITE_FLOPS = 8  # the other 6 of a slot's 14, the colour's weighted sum, is a matrix product FlopCounterMode counts


@dataclass
class FlopCount:
    analytic: dict[str, int] = field(default_factory=dict)
    matmul: int = 0

    @property
    def total(self) -> int:
        return self.matmul + sum(self.analytic.values())


_ACTIVE: ContextVar[FlopCount | None] = ContextVar("boostnerf_flops", default=None)
_OPEN = 0  # counters open in any context: outside them `add` returns at once (and a compiled step traces nothing)


def add(kind: str, flops: int) -> None:
    """Record `flops` of kind `kind` in the open counter, if any."""
    if not _OPEN:
        return
    counter = _ACTIVE.get()
    if counter is not None:
        counter.analytic[kind] = counter.analytic.get(kind, 0) + int(flops)


@contextmanager
def count_flops() -> Iterator[FlopCount]:
    global _OPEN
    counter = FlopCount()
    token = _ACTIVE.set(counter)
    _OPEN += 1
    try:
        with FlopCounterMode(display=False) as mode:
            yield counter
    finally:
        _OPEN -= 1
        _ACTIVE.reset(token)
    counter.matmul = int(mode.get_total_flops())
