"""What a trained mixture's lattices decide per cell, so that rendering looks a sample's cell up instead of blending
its eight vertices (exact, but for Top-1's cells that no expert holds whole; below).

A trilinear value inside a lattice cell is a convex combination of the cell's 8 vertex values (`grid.corners`). So:

- **V_D's test.** A sample passes V_D when its opacity over one step exceeds T, i.e. when its blended raw density
  exceeds one number r* (softplus and the opacity are increasing). A cell whose 8 vertices all lie above r* passes
  every sample in it; one whose vertices all lie below fails every sample; only the cells in between (`MIXED`: where
  V_D's surface crosses) need the blend. `vd_states` marks each cell.
- **Top-1's choice.** The baked gate's logits are blended the same way, and a convex combination keeps a strict
  order that holds at every vertex: where one expert's logit is the largest at all 8 vertices, it is the largest
  everywhere in the cell. A renormalised Top-1 mixture routes with weight 1, so the choice is all it needs. `top1_cells`
  gives each cell its expert, or -1 where the vertices disagree. Rendering decides on the gate's cells halved along
  every axis (`route_cells`): a half-cell lies inside one cell, where the logits are trilinear, so the test holds on it
  alike, and more samples lie in a half-cell with one clear expert (lego's Top-1: 60% of the kept samples, against 29%
  by whole cells). A half-cell whose vertices disagree (the gate's border between two experts crosses it: the other
  40% of lego's samples) goes whole to the expert leading at its centre (`at_centre`), so that no sample blends the
  gate: the one approximation here, of a gate that is itself baked onto a lattice (lego M = 3's Top-1: its routing
  14 -> 2 ms an image, held-out PSNR -0.010 dB; the baking itself -0.013 dB; docs/performance.md). `eval --exact-gate`
  routes every sample by the gate itself.
- **Top-2's lone choice.** Rendering a renormalised Top-2 leaves out a second choice that weighs less than w
  (`moe.render_min_weight`): its weight is sigmoid(l2 - l1), under w where the first expert's logit leads every other
  by more than ln((1 - w) / w). Where it leads by that at all 8 vertices (`route_cells` with that lead), it does so
  everywhere in the cell, and every sample there goes to that expert alone, with weight 1, as the blend would send it.

- **Both skips at once.** A sample is kept when its occupancy cell is occupied and it passes V_D. `skip_states` makes
  one table (`SkipCells`) over a lattice that splits each of V_D's cells into f^3 (f at least 2, and at least twice
  as fine as the occupancy grid's cells): a fine cell in occupied cells only whose V_D values (trilinear, so extreme
  at its corners) all pass is PASS; one in empty cells only, or whose V_D values all fail, is FAIL; any other MIXED.
  Rendering looks each sample up once; only the MIXED ones, near V_D's surface or an occupancy edge, are tested by
  the occupancy grid and V_D as before.

A vertex counts only with a margin (`MARGIN` of the values' scale) past the decision, so that float32 rounding in the
blend can never decide otherwise than the cell does: rendering through V_D's and the grid's cells gives the same image,
bit for bit, as testing every sample (tests/test_moe.py); a sample in a Top-1 cell its vertices decide goes where the
blend would send it; through Top-2's lone choice, the same image to float32 rounding (the alpha mix's weight sum is
exactly 1 there, a blend's 1 to rounding).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from boostnerf_cli.device import constant
from boostnerf_cli.fields import grid as G
from boostnerf_cli.render.occupancy import OccupancyGrid

FAIL, PASS, MIXED = 0, 1, 2
MARGIN = 1e-4  # of max(1, |value|): far past float32's rounding of an 8-term blend (~1e-6 of it)


def cell_index(xyz: Tensor, bbox: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """(N, 3) -> (N,) the index of the lattice cell whose 8 vertices `grid.corners` blends for each point (the same
    clamping), in C order over the (X-1, Y-1, Z-1) cells."""
    res = constant(tuple(shape), xyz.device, xyz.dtype)  # made once per device: no copy to it per call
    # floor, then into [0, res - 2]: what clamping into [0, res - 1], flooring and capping at res - 2 gives; the flat
    # index a sum over the axes, exact in float32 below 2^24 cells (in float64 above)
    exact = torch.float32 if (shape[0] - 1) * (shape[1] - 1) * (shape[2] - 1) < 1 << 24 else torch.float64
    strides = constant(((shape[1] - 1) * (shape[2] - 1), shape[2] - 1, 1), xyz.device, exact)
    return G.flat_cells(xyz, bbox, res - 1, res - 2, strides).long()


def _vertex_views(v: Tensor) -> list[Tensor]:
    """The 8 vertices of every cell: 8 views (X-1, Y-1, Z-1, ...) of values (X, Y, Z, ...) per vertex."""
    X, Y, Z = v.shape[:3]
    return [v[dx : X - 1 + dx, dy : Y - 1 + dy, dz : Z - 1 + dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


def _corner_views(table: Tensor, shape: tuple[int, int, int]) -> list[Tensor]:
    """The 8 vertices of every cell: 8 views (X-1, Y-1, Z-1, C) of the table (X*Y*Z, C)."""
    return _vertex_views(table.reshape(*shape, table.shape[-1]))


def _extremes(table: Tensor, shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """table (X*Y*Z, 1) vertex values -> the smallest and largest of each cell's 8 vertices, (X-1, Y-1, Z-1) each."""
    lo = hi = None
    for corner in _corner_views(table, shape):
        lo = corner if lo is None else torch.minimum(lo, corner)
        hi = corner if hi is None else torch.maximum(hi, corner)
    return lo[..., 0], hi[..., 0]


@torch.no_grad()
def vd_states(raw: Tensor, shape: tuple[int, int, int], threshold_raw: float) -> Tensor:
    """raw (X*Y*Z, 1) V_D's vertex values, `threshold_raw` r* -> (cells,) uint8 PASS / FAIL / MIXED."""
    lo, hi = _extremes(raw, shape)
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


def _leaders(table: Tensor, margin: float) -> tuple[Tensor, Tensor]:
    """table (M, ...) channels first -> each vertex's largest expert (...,) int8 (the first of equals) and whether it
    leads every other by more than `margin` (never, among equals)."""
    first = table[0].clone()
    best = torch.zeros(first.shape, dtype=torch.int8, device=table.device)
    second = torch.full_like(first, -math.inf)
    for j in range(1, table.shape[0]):
        x = table[j]
        second = torch.maximum(second, torch.minimum(x, first))
        best.masked_fill_(x > first, j)
        first = torch.maximum(first, x)
    return best, first - second > margin


def _agreeing(best: Tensor, clear: Tensor) -> Tensor:
    """best, clear (X, Y, Z) per vertex -> (X-1, Y-1, Z-1) int8: the expert all 8 vertices of a cell name clearly,
    or -1."""
    bests, clears = _vertex_views(best), _vertex_views(clear)
    expert, agree = bests[0], clears[0].clone()
    for b, c in zip(bests[1:], clears[1:]):
        agree &= c & (b == expert)
    return torch.where(agree, expert, -1).to(torch.int8)


def _margin(table: Tensor, lead: float) -> float:
    """How far a logit must lead: `lead`, and `MARGIN` of the table's scale."""
    return lead + MARGIN * max(1.0, float(table.abs().max())) if table.numel() else 0.0


def _decided(values: Tensor, margin: float, at_centre: bool) -> Tensor:
    """values (M, X, Y, Z) per vertex -> (X-1, Y-1, Z-1) int8: `_agreeing`'s expert per cell; with `at_centre`, a
    cell whose vertices disagree takes the expert leading at its centre (where a trilinear value is the mean of the
    cell's 8 vertices; the first of equals), so that no cell is left to the blend."""
    agreed = _agreeing(*_leaders(values, margin))
    if not at_centre:
        return agreed
    centre = None
    for corner in _vertex_views(values.movedim(0, -1)):
        centre = corner.clone() if centre is None else centre.add_(corner)
    return torch.where(agreed >= 0, agreed, centre.argmax(-1).to(torch.int8))


@torch.no_grad()
def top1_cells(logits: Tensor, shape: tuple[int, int, int], lead: float = 0.0, at_centre: bool = False) -> Tensor:
    """logits (X*Y*Z, M) the baked gate's vertex logits -> (cells,) int8: the expert whose logit is the largest,
    by more than `lead` and the margin, at all 8 vertices of the cell, or -1 (`at_centre`: the expert leading at the
    cell's centre). The lead holds everywhere in the cell then, for each other expert's logit (a convex combination
    keeps it)."""
    return _decided(logits.T.reshape(logits.shape[-1], *shape), _margin(logits, lead), at_centre).reshape(-1)


# `route_cells` halves the gate's cells along every axis while the halves number at most this many (an int8 each), and
# works out at most about SLAB_VALUES logits at a time
MAX_ROUTE_CELLS = 1 << 25
SLAB_VALUES = 1 << 22


def halved(shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """The lattice whose cells halve those of a lattice of `shape` (vertices) along every axis."""
    return tuple(2 * n - 1 for n in shape)  # type: ignore[return-value]


@torch.no_grad()
def route_cells(logits: Tensor, shape: tuple[int, int, int], lead: float = 0.0,
                at_centre: bool = False) -> tuple[Tensor, tuple[int, int, int]]:
    """`top1_cells` on the gate's cells halved along every axis (while they number at most `MAX_ROUTE_CELLS`), so
    that more samples lie in a cell with one clear expert: -> (cells,) int8, and the lattice's shape (vertices).

    A half-cell lies inside one of the gate's cells, where every logit is trilinear, hence on the half-cell too: its
    differences are extreme at the half-cell's 8 corners, so the test of `top1_cells` holds there as on a whole cell.
    The corners' logits are the gate's blend there: a vertex's own, the mean of 2, 4 or 8 (to float32 rounding,
    far under the margin). Made in slabs along x, a few million values at a time."""
    fine = halved(shape)
    if math.prod(n - 1 for n in fine) > MAX_ROUTE_CELLS:
        return top1_cells(logits, shape, lead, at_centre), shape
    margin = _margin(logits, lead)
    m = logits.shape[-1]
    grid = logits.T.reshape(1, m, *shape)  # channels first, as `interpolate` takes it
    slab = max(1, SLAB_VALUES // max(1, 4 * shape[1] * shape[2] * m))  # the gate's x-cells a slab covers
    out = []
    for a in range(0, shape[0] - 1, slab):
        v = grid[:, :, a : min(shape[0], a + slab + 1)]
        size = tuple(2 * n - 1 for n in v.shape[2:])  # each midpoint the mean of its 2, 4 or 8 vertices
        out.append(_decided(F.interpolate(v, size=size, mode="trilinear", align_corners=True)[0], margin, at_centre))
    return torch.cat(out).reshape(-1), fine


# `lone_share`: below this share of the kept space in cells with a lone expert, Top-2's per-cell lookup costs more than
# the blends it saves (one thread: 8 ms an image more on lego at M = 5, where none has one; 2 ms an image less on lego
# at M = 3 with 41% of the kept samples in such cells; fern's routing 183 -> 118 ms with 42%)
LONE_SHARE = 1 / 3


@torch.no_grad()
def lone_share(lone: Tensor, bbox: Tensor, shape: tuple[int, int, int], kept, n: int = 1 << 16) -> float:
    """The share of the space where samples are kept that lies in cells with a lone expert: `lone` (cells,) per cell
    of a lattice of `shape` over `bbox`, -1 where none; `kept` a `SkipCells` (its PASS cells) or an `OccupancyGrid`
    (its occupied cells): the share of at most `n` of their centres, evenly spread through them, whose cell of the
    lattice has one (the share of all cells without `kept`)."""
    if kept is None:
        return float((lone >= 0).float().mean()) if lone.numel() else 0.0
    where = (kept.state == PASS) if isinstance(kept, SkipCells) else kept.occupied.bool()
    cells = where.reshape(-1).nonzero().squeeze(-1)
    if not len(cells):
        return 0.0
    cells = cells[:: -(-len(cells) // n)]  # every ceil(len / n)-th: at most n
    dims = torch.tensor(where.shape, device=cells.device)
    ijk = torch.stack([cells // (dims[1] * dims[2]), cells // dims[2] % dims[1], cells % dims[2]], -1)
    box = kept.bbox.to(cells.device)
    centres = box[0] + (ijk.float() + 0.5) / dims * (box[1] - box[0])
    return float((lone.index_select(0, cell_index(centres, bbox.to(cells.device), shape)) >= 0).float().mean())


# a fine cell is compared with every coarse cell it touches grown by this much of the box (float32 rounding of a
# sample's cell coordinates is ~1e-7 of it), so that a sample never lands in a coarse cell its fine cell did not see
REACH = 1e-5


def _touched(fine: int, lo: float, hi: float, coarse_lo: float, coarse_hi: float,
             coarse: int) -> tuple[Tensor, Tensor, Tensor]:
    """Along one axis, fine cells i (of `fine` over [lo, hi]), each grown by REACH of the box -> the first and last
    coarse cells (of `coarse` over [coarse_lo, coarse_hi]) it touches (clamped into [0, coarse - 1]), and whether it
    lies inside [coarse_lo, coarse_hi] (past it, the coarse lattice calls space empty)."""
    edges = torch.linspace(lo, hi, fine + 1, dtype=torch.float64)
    grow = REACH * (hi - lo)
    start, end = edges[:-1] - grow, edges[1:] + grow
    size = (coarse_hi - coarse_lo) / coarse
    first = ((start - coarse_lo) / size).floor().clamp(0, coarse - 1).long()
    last = ((end - coarse_lo) / size).floor().clamp(0, coarse - 1).long()
    return first, last, (start >= coarse_lo) & (end <= coarse_hi)


def _all_over(values: Tensor, ranges: list[tuple[Tensor, Tensor]]) -> Tensor:
    """values (A, B, C) bool on a coarse lattice -> (a, b, c) bool: for each fine cell, whether the values of every
    coarse cell in its ranges (one (first, last) pair of (n,) per axis) are all True."""
    out = values
    for axis, (first, last) in enumerate(ranges):
        span = int((last - first).max()) + 1 if len(first) else 1
        acc = None
        for off in range(span):
            idx = torch.minimum(first + off, last)  # past the range: its last cell again
            taken = out.index_select(axis, idx)
            acc = taken if acc is None else acc & taken
        out = acc
    return out


class SkipCells:
    """Per fine cell of a box, PASS / FAIL / MIXED for the occupancy grid and V_D together (`skip_states`). Looked up
    as the occupancy grid is (its cells [x, y, z] of `shape` over `bbox`, its padded rows), a point outside the box
    FAIL."""

    def __init__(self, state: Tensor, bbox: Tensor):
        self.state = state
        self._cells = OccupancyGrid(state != FAIL, bbox)  # the same cells: its lookup's rows
        self._padded = F.pad(state, (1, 1, 1, 1, 1, 1), value=FAIL).reshape(-1)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.state.shape)  # type: ignore[return-value]

    @property
    def bbox(self) -> Tensor:
        return self._cells.bbox

    @property
    def cells(self) -> OccupancyGrid:
        """The cells that are not FAIL, as an occupancy grid over the same cells."""
        return self._cells

    def __call__(self, xyz: Tensor) -> Tensor:
        """(N, 3) -> (N,) uint8 each point's state."""
        return self._padded.index_select(0, self._cells.padded_rows(xyz))

    def within(self, xyz: Tensor) -> Tensor:
        """`__call__` for points inside the box (`OccupancyGrid.within`: one rounded just past a face counts in the cell
        at that face, which never passes: FAIL, or MIXED and then tested as every MIXED sample is)."""
        return self._padded.index_select(0, self._cells.padded_rows_within(xyz))


@torch.no_grad()
def skip_states(raw: Tensor, vd_shape: tuple[int, int, int], vd_bbox: Tensor, threshold_raw: float, occupancy=None,
                fineness: int = 2) -> SkipCells:
    """V_D's vertex values `raw` (X*Y*Z, 1) over `vd_bbox`, its threshold r* (`threshold_raw`) and an occupancy grid
    (render/occupancy.py, or None) -> one table over V_D's box whose cells split each of V_D's into f^3, f the
    smallest that makes them at most 1 / `fineness` of an occupancy cell and of V_D's along every axis. V_D is
    trilinear inside each of its cells, so over a fine cell its extremes lie at the fine cell's 8 corners; a fine cell
    passes V_D when all 8 lie above r* (with `MARGIN` and a slack for a sample rounded into its neighbour), fails when
    all lie below. The occupancy grid's cells are boolean: a fine cell is occupied (empty) when every cell it touches
    (grown by `REACH`) is. A fine cell on the box's faces never passes (a sample just past a face is outside V_D)."""
    cells = [n - 1 for n in vd_shape]
    lo, hi = [float(v) for v in vd_bbox[0]], [float(v) for v in vd_bbox[1]]
    f = fineness
    if occupancy is not None:
        for a in range(3):
            vd_cell = (hi[a] - lo[a]) / cells[a]
            occ_cell = float(occupancy.bbox[1, a] - occupancy.bbox[0, a]) / occupancy.shape[a]
            f = max(f, math.ceil(fineness * vd_cell / occ_cell))
    fine = [c * f for c in cells]
    table = raw.reshape(1, 1, *vd_shape).double().cpu()
    values = F.interpolate(table, size=tuple(n + 1 for n in fine), mode="trilinear", align_corners=True)[0, 0]
    lo_v, hi_v = _extremes(values.reshape(-1, 1), tuple(n + 1 for n in fine))
    coarse_lo, coarse_hi = _extremes(raw.double().cpu(), tuple(vd_shape))  # each fine cell's V_D cell's: the slack
    spread = (coarse_hi - coarse_lo).repeat_interleave(f, 0).repeat_interleave(f, 1).repeat_interleave(f, 2)
    margin = MARGIN * max(1.0, abs(threshold_raw)) + 1e-3 * spread
    sure_pass = lo_v > threshold_raw + margin
    sure_fail = hi_v < threshold_raw - margin
    face = torch.zeros(fine, dtype=torch.bool)
    face[0], face[-1], face[:, 0], face[:, -1], face[:, :, 0], face[:, :, -1] = (True,) * 6
    sure_pass &= ~face
    if occupancy is not None:
        occ = occupancy.occupied.bool().cpu()
        olo, ohi = [float(v) for v in occupancy.bbox[0]], [float(v) for v in occupancy.bbox[1]]
        touched = [_touched(fine[a], lo[a], hi[a], olo[a], ohi[a], occupancy.shape[a]) for a in range(3)]
        ranges = [(first, last) for first, last, _ in touched]
        inside = [t[2] for t in touched]
        within = inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
        sure_pass &= _all_over(occ, ranges) & within
        sure_fail |= _all_over(~occ, ranges)
    state = torch.full(tuple(fine), MIXED, dtype=torch.uint8)
    state[sure_pass] = PASS
    state[sure_fail] = FAIL
    return SkipCells(state.to(raw.device), vd_bbox.to(raw.device))
