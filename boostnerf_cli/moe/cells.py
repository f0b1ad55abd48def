"""What a trained mixture's lattices decide per cell, so that rendering looks a sample's cell up instead of blending
its eight vertices (exact, not an approximation).

A trilinear value inside a lattice cell is a convex combination of the cell's 8 vertex values (`grid.corners`). So:

- **V_D's test.** A sample passes V_D when its opacity over one step exceeds T, i.e. when its blended raw density
  exceeds one number r* (softplus and the opacity are increasing). A cell whose 8 vertices all lie above r* passes
  every sample in it; one whose vertices all lie below fails every sample; only the cells in between (`MIXED`: where
  V_D's surface crosses) need the blend. `vd_states` marks each cell.
- **Top-1's choice.** The baked gate's logits are blended the same way, and a convex combination keeps a strict
  order that holds at every vertex: where one expert's logit is the largest at all 8 vertices, it is the largest
  everywhere in the cell. A renormalised Top-1 mixture routes with weight 1, so the choice is all it needs. `top1_cells`
  gives each cell its expert, or -1 where the vertices disagree (the cell is blended as before).

A vertex counts only with a margin (`MARGIN` of the values' scale) past the decision, so that float32 rounding in the
blend can never decide otherwise than the cell does: rendering through the cells gives the same image, bit for bit, as
blending every sample (tests/test_moe.py).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

FAIL, PASS, MIXED = 0, 1, 2
MARGIN = 1e-4  # of max(1, |value|): far past float32's rounding of an 8-term blend (~1e-6 of it)


def cell_index(xyz: Tensor, bbox: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """(N, 3) -> (N,) the index of the lattice cell whose 8 vertices `grid.corners` blends for each point (the same
    clamping), in C order over the (X-1, Y-1, Z-1) cells."""
    res = torch.tensor(shape, device=xyz.device, dtype=xyz.dtype)
    p = (xyz - bbox[0]) / (bbox[1] - bbox[0]) * (res - 1)
    p0 = torch.minimum(torch.minimum(p.clamp_min(0), res - 1).floor(), res - 2).long()
    return (p0[:, 0] * (shape[1] - 1) + p0[:, 1]) * (shape[2] - 1) + p0[:, 2]


def _corner_views(table: Tensor, shape: tuple[int, int, int]) -> list[Tensor]:
    """The 8 vertices of every cell: 8 views (X-1, Y-1, Z-1, C) of the table (X*Y*Z, C)."""
    v = table.reshape(*shape, table.shape[-1])
    return [v[dx : shape[0] - 1 + dx, dy : shape[1] - 1 + dy, dz : shape[2] - 1 + dz]
            for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


@torch.no_grad()
def vd_states(raw: Tensor, shape: tuple[int, int, int], threshold_raw: float) -> Tensor:
    """raw (X*Y*Z, 1) V_D's vertex values, `threshold_raw` r* -> (cells,) uint8 PASS / FAIL / MIXED."""
    lo = hi = None
    for corner in _corner_views(raw, shape):
        lo = corner if lo is None else torch.minimum(lo, corner)
        hi = corner if hi is None else torch.maximum(hi, corner)
    lo, hi = lo.reshape(-1).double(), hi.reshape(-1).double()
    margin = MARGIN * max(1.0, abs(threshold_raw))
    state = torch.full(lo.shape, MIXED, dtype=torch.uint8, device=raw.device)
    state[lo > threshold_raw + margin] = PASS
    state[hi < threshold_raw - margin] = FAIL
    return state


def threshold_raw(threshold: float, step: float, unit: float, shift: float) -> float:
    """The raw value r* at which V_D's opacity over one `step`, -expm1(-softplus(r* + shift) / unit * step), is T."""
    sigma = -math.log1p(-threshold) / step
    y = sigma * unit  # softplus(r* + shift) = y
    return (y if y > 20 else math.log(math.expm1(y))) - shift


@torch.no_grad()
def top1_cells(logits: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """logits (X*Y*Z, M) the baked gate's vertex logits -> (cells,) int8: the expert whose logit is the largest,
    with the margin, at all 8 vertices of the cell, or -1."""
    table = logits
    margin = MARGIN * max(1.0, float(table.abs().max())) if table.numel() else 0.0
    expert = None
    agree = None
    for corner in _corner_views(table, shape):
        top2 = corner.topk(min(2, corner.shape[-1]), dim=-1)
        best = top2.indices[..., 0]
        clear = (top2.values[..., 0] - top2.values[..., -1] > margin) if corner.shape[-1] > 1 else torch.ones_like(
            best, dtype=torch.bool)
        if expert is None:
            expert, agree = best, clear
        else:
            agree = agree & clear & (best == expert)
    return torch.where(agree, expert, -1).reshape(-1).to(torch.int8)
