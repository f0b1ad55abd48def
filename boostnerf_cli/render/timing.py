"""Where the seconds of rendering go: wall time per part (rays, sampling, skipping, routing, dispatch, each expert's
field, compositing), measured where each part runs.

    with timing.parts() as seconds:      # opens a timer; outside one, `part` costs one integer test
        render_image(...)
    seconds  # {"sampling": 0.012, "expert dvgo-64": 0.031, ...}

`part(name)` is a context manager. Parts nest: time spent in an inner part is counted there, not also in the
part around it (exclusive time), so the parts add up to the whole. On a GPU each boundary waits for the device
(`torch.cuda.synchronize`), so the device's work lands in the part that queued it; a timed render is thus slower
than an untimed one, and only its shares are meaningful (scripts/render_profile.py).
"""

from __future__ import annotations

import time
from contextlib import contextmanager, nullcontext
from typing import Iterator

import torch

_OPEN = 0  # timers open: outside one `part` returns the shared no-op at once (and a compiled step traces nothing)
_TOTALS: dict[str, float] = {}
_STACK: list[list] = []  # [name, start] of the parts entered and not left, innermost last
_SYNC = False


def _now() -> float:
    if _SYNC:
        torch.cuda.synchronize()
    return time.perf_counter()


class _Part:
    __slots__ = ("name",)

    def __init__(self, name: str):
        self.name = name

    def __enter__(self) -> None:
        now = _now()
        if _STACK:  # the outer part pauses
            outer = _STACK[-1]
            _TOTALS[outer[0]] = _TOTALS.get(outer[0], 0.0) + now - outer[1]
        _STACK.append([self.name, now])

    def __exit__(self, *exc) -> None:
        now = _now()
        name, start = _STACK.pop()
        _TOTALS[name] = _TOTALS.get(name, 0.0) + now - start
        if _STACK:  # the outer part resumes
            _STACK[-1][1] = now


_NOTHING = nullcontext()  # what a compiled step traces through (the compiler knows nullcontext, not a class of ours)


def part(name: str) -> _Part | nullcontext:
    """Time what runs inside as `name` (exclusive of the parts nested in it), when a timer is open."""
    return _Part(name) if _OPEN and not torch.compiler.is_compiling() else _NOTHING


@contextmanager
def parts(device: torch.device | str = "cpu") -> Iterator[dict[str, float]]:
    """Open a timer: the dict it yields holds the seconds of each part once the block ends. One at a time."""
    global _OPEN, _SYNC
    if _OPEN:
        raise RuntimeError("a render timer is open already")
    _TOTALS.clear()
    _STACK.clear()
    _SYNC = torch.device(device).type == "cuda"
    _OPEN = 1
    out: dict[str, float] = {}
    try:
        yield out
    finally:
        _OPEN = 0
        _SYNC = False
        out.update(_TOTALS)
