"""The Field contract: everything that answers "what is at point x, seen from direction d?".

Every expert family and the mixture of experts satisfy it; the renderer knows nothing else.
Shapes: N points; xyz (N, 3) world coordinates; dirs (N, 3) unit view directions (pointing from
the camera into the scene). Density sigma (N,) is non-negative, per world unit; rgb (N, 3) in [0, 1].

Optional, for fields that share work between the renderer's two passes (the mixture of experts
routes each sample once): `routed()` returns a per-batch view whose `color_rows(rows, dirs)` gives
the colour of the samples `rows` of its last `density` call. The renderer uses them when present.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import Tensor


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
