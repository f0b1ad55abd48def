"""How long a stage takes to start: from its command (or the previous model it trained) to its first training step or
rendered view, and the parts of that time (reading the scene, building the rays, loading or building the models,
computing digests).

The CLI starts the clock for each command (`begin`); the code that does each part times it (`part`); the training
loop and the first rendered view call `ready`, which says once per model `ready in 3.1 s (scene 1.2 s, rays 0.9 s,
models 0.6 s, digests 0.2 s)` on the tool's log and returns the seconds, which training reports keep as
`startup_seconds`.
"""

from __future__ import annotations

import functools
import logging
import time
from contextlib import contextmanager
from typing import Iterator

log = logging.getLogger("boostnerf_cli")

PARTS = ("scene", "rays", "models", "digests")


class Clock:
    """One command's start-up: since `since`, the seconds spent in each part; `said` once `ready` has spoken."""

    def __init__(self) -> None:
        self.begin()

    def begin(self) -> None:
        """Start timing a model's start-up (a command's start, or the end of the model before it)."""
        self.since = time.perf_counter()
        self.parts: dict[str, float] = {}
        self.said = False
        self.depth = 0

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        """Time the block as part `name` of the start-up (a part inside another counts once, in the outer one)."""
        self.depth += 1
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.depth -= 1
            if self.depth == 0:
                self.parts[name] = self.parts.get(name, 0.0) + time.perf_counter() - t0

    def ready(self, what: str = "") -> float:
        """The seconds since `begin`; said once (`what`: whose start-up, e.g. the model's name)."""
        seconds = time.perf_counter() - self.since
        if not self.said:
            self.said = True
            parts = ", ".join(f"{name} {self.parts[name]:.1f} s" for name in PARTS if name in self.parts)
            log.info(f"{what + ': ' if what else ''}ready in {seconds:.1f} s" + (f" ({parts})" if parts else ""))
        return seconds


CLOCK = Clock()  # this process's: a process runs one command at a time (the CLI restarts it for each)


def timed(name: str):
    """A decorator: every call of the function is start-up part `name` (`Clock.part` of this process's clock)."""

    def wrap(fn):
        @functools.wraps(fn)
        def timed_fn(*args, **kwargs):
            with CLOCK.part(name):
                return fn(*args, **kwargs)

        return timed_fn

    return wrap
