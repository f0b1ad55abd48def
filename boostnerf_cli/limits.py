"""Allowed values of settings, declared next to each dataclass field (`limit(default, rule)`).

The recipe sections (`recipe.py`) and the expert families' configs (`fields/dvgo.py`, `tensorf.py`,
`ngp.py`) declare each field's rule in its metadata; `recipe.check_recipe` reads them all, so a value
out of range is refused, with one line naming the key, the value and the rule, when a recipe or a
workspace manifest is read, before anything runs.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

INF = math.inf


def _num(v: float) -> str:
    return "inf" if v == INF else "-inf" if v == -INF else f"{v:g}" if isinstance(v, float) else str(v)


@dataclass(frozen=True)
class Range:
    """lo <= v <= hi, each end open or closed; `also`: single values allowed besides (e.g. 0 = off)."""

    lo: float = -INF
    hi: float = INF
    lo_open: bool = False
    hi_open: bool = False
    also: tuple = ()

    def allows(self, v: Any) -> bool:
        if v in self.also:
            return True
        if v in (INF, -INF):  # every value the code uses is finite, also where the range has no bound
            return False
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return bool(above and below)  # NaN fails both

    def __str__(self) -> str:
        if self.hi == INF:
            text = f"{'>' if self.lo_open else '>='} {_num(self.lo)}"
        else:
            text = f"in {'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}{')' if self.hi_open else ']'}"
        return " or ".join([*map(_num, self.also), text])


@dataclass(frozen=True)
class OneOf:
    choices: tuple[str, ...]

    def allows(self, v: Any) -> bool:
        return v in self.choices

    def __str__(self) -> str:
        return f"one of {', '.join(self.choices)}"


def comma_numbers(v: Any) -> list[float] | None:
    """The numbers of a text "1, 1.5, 2.23" (one or more, separated by commas), or None when it is not such a text."""
    if not isinstance(v, str):
        return None
    try:
        return [float(x) for x in v.split(",")]
    except ValueError:
        return None


@dataclass(frozen=True)
class OneOfOrNumbers:
    """One of `choices`, or numbers separated by commas, each allowed by `each` (explicit per-expert weights)."""

    choices: tuple[str, ...]
    each: Range

    def allows(self, v: Any) -> bool:
        if v in self.choices:
            return True
        numbers = comma_numbers(v)
        return numbers is not None and all(self.each.allows(x) for x in numbers)

    def __str__(self) -> str:
        return f"one of {', '.join(self.choices)}, or numbers {self.each} separated by commas"


def at_least(lo: int | float) -> Range:
    return Range(lo)


POSITIVE = Range(0, lo_open=True)  # > 0 (learning rates, step sizes)
OPEN_UNIT = Range(0, 1, lo_open=True, hi_open=True)  # (0, 1): opacities, growth fractions
THRESHOLD = Range(0, 1, hi_open=True)  # [0, 1): opacity / weight thresholds (0 = keep everything)
NON_NEGATIVE = Range(0)
# loss weights: past this a float32 loss term overflows to inf on the first step (1e39 is finite as a Python float);
# the paper's lambda is 1e-3 and its penalties are about 1 to 3
MAX_LOSS_WEIGHT = 1e6
LOSS_WEIGHT = Range(0, MAX_LOSS_WEIGHT)
# cells along one side of a dense 3D grid (experts, gate, density volume, occupancy): 1024^3 cells of one float32
# channel are 4 GiB, and every grid holds several channels, so a larger value can only fail for lack of memory
MAX_GRID_RES = 1024
GRID_RES = Range(1, MAX_GRID_RES)
# learning rates: Adam moves a parameter by about lr per step; past 10 (100x the grids' default) a grid's values leave
# the range its activations use in the first steps and the model trains to noise with a finite loss (1e30: exit 0)
LEARNING_RATE = Range(0, 10, lo_open=True)
# network sizes: past these a model can only run out of memory (a million layers ended in a MemoryError inside
# Python's own error hook), or, for encoding frequencies, overflow float32: sin(2^k pi x) is inf for k > 127
MLP_WIDTH = Range(1, 4096)  # also a factorisation's ranks and feature widths (TensoRF app_dim, NGP geo_feat, F)
MLP_LAYERS = Range(0, 16)
PE_FREQS = Range(0, 16)
# the render step in voxels of the final grid: at 1e-6 a ray takes millions of samples (out of memory), at 1e6 every
# sample but the first falls past the box (a blank model, exit 0); DVGO's is 0.5
STEP_RATIO = Range(0.05, 4)
# a scene box coordinate in world units: the box's diagonal in float32 overflows at 1e30 (a traceback)
BBOX_COORD = Range(-1e6, 1e6)


def limit(default: Any = dataclasses.MISSING, rule: Range | OneOf | None = None, *, factory: Any = dataclasses.MISSING,
          min_items: int = 0) -> Any:
    """A dataclass field with its allowed values (for a list field: of each item; `min_items`: its length)."""
    return dataclasses.field(default=default, default_factory=factory, metadata={"rule": rule, "min_items": min_items})


def rule_of(f: dataclasses.Field) -> Range | OneOf | None:
    return f.metadata.get("rule")
