"""What a trained mixture's lattices decide per cell, so that rendering looks a sample's cell up instead of blending
its eight vertices: exact for V_D, the occupancy grid and a Top-1 cell whose vertices agree; taken at the cell's centre
for the gate's other cells (below).

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
  gate (lego M = 3's Top-1: its routing 14 -> 3 ms an image, held-out PSNR -0.010 dB; M = 5 -0.030 dB).
- **Top-2's choice.** A renormalised Top-2's two experts and weights vary inside a cell, so rendering takes them at
  each half-cell's centre (`pair_cells`): one lookup a sample instead of blending the gate, its top two and their
  softmax (lego M = 3's Top-2: 9% faster, held-out PSNR -0.017 dB; M = 5 -0.002 dB).

Both are approximations of a gate that is itself baked onto a lattice (`moe.bake_res`; lego M = 3's Top-1 -0.013 dB
against the gate's own MLP). `eval --exact-gate` routes every sample by the gate itself.

- **Both skips at once.** A sample is kept when its occupancy cell is occupied and it passes V_D. `skip_states` makes
  one table (`SkipCells`) over a lattice that splits each of V_D's cells into f^3 (f at least 2, and at least twice
  as fine as the occupancy grid's cells): a fine cell in occupied cells only whose V_D values (trilinear, so extreme
  at its corners) all pass is PASS; one in empty cells only, or whose V_D values all fail, is FAIL; any other MIXED.
  Rendering looks each sample up once; only the MIXED ones, near V_D's surface or an occupancy edge, are tested by
  the occupancy grid and V_D as before.

A vertex counts only with a margin (`MARGIN` of the values' scale) past the decision, so that float32 rounding in the
blend can never decide otherwise than the cell does: rendering through V_D's and the grid's cells gives the same image,
bit for bit, as testing every sample (tests/test_moe.py), and a sample in a Top-1 cell its vertices decide goes where
the blend would send it.
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


def _centres(values: Tensor) -> Tensor:
    """values (M, X, Y, Z) per vertex -> (M, X-1, Y-1, Z-1): each cell's values at its centre, where a trilinear value
    is the mean of the cell's 8 vertices (summed channels first: a plane's rows stay contiguous)."""
    total = None
    for corner in _vertex_views(values.movedim(0, -1)):
        corner = corner.movedim(-1, 0)
        total = corner.clone() if total is None else total.add_(corner)
    return total.mul_(0.125)


def _top_two(values: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """values (M, ...) channels first, M >= 2 -> the largest and the second largest value and their channels (uint8
    for M <= 256, else int64), each (...): the first of equals first; a pass per channel over contiguous planes."""
    m = values.shape[0]
    kind = torch.uint8 if m <= 256 else torch.long
    first, second = values[0].clone(), values[1].clone()
    i1 = torch.zeros(first.shape, dtype=kind, device=values.device)
    i2 = torch.ones_like(i1)
    swap = second > first
    first, second = torch.maximum(first, second), torch.minimum(first, second)
    i1.masked_fill_(swap, 1)
    i2.masked_fill_(swap, 0)
    for j in range(2, m):
        x = values[j]
        top = x > first
        i2.masked_fill_(x > second, j)
        i2 = torch.where(top, i1, i2)  # a new first: the old one is second
        second = torch.where(top, first, torch.maximum(second, x))
        i1.masked_fill_(top, j)
        first = torch.maximum(first, x)
    return first, i1, second, i2


def _decided(values: Tensor, margin: float, at_centre: bool) -> Tensor:
    """values (M, X, Y, Z) per vertex -> (X-1, Y-1, Z-1) int8: `_agreeing`'s expert per cell; with `at_centre`, a
    cell whose vertices disagree takes the expert leading at its centre (the first of equals), so that no cell is left
    to the blend."""
    agreed = _agreeing(*_leaders(values, margin))
    if not at_centre:
        return agreed
    return torch.where(agreed >= 0, agreed, _leaders(_centres(values), math.inf)[0])


def _margin(table: Tensor) -> float:
    """How far a logit must lead: `MARGIN` of the table's scale."""
    return MARGIN * max(1.0, float(table.abs().max())) if table.numel() else 0.0


@torch.no_grad()
def top1_cells(logits: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """logits (X*Y*Z, M) the baked gate's vertex logits -> (cells,) int8: the expert whose logit is the largest, by
    more than the margin, at all 8 vertices of the cell, or -1. It is then the largest everywhere in the cell (a convex
    combination keeps each difference's sign)."""
    return _decided(logits.T.reshape(logits.shape[-1], *shape), _margin(logits), False).reshape(-1)


# `route_cells` and `pair_cells` halve the gate's cells along every axis while the halves number at most this many,
# and work out at most about SLAB_VALUES logits at a time
MAX_ROUTE_CELLS = 1 << 25
SLAB_VALUES = 1 << 22


def halved(shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """The lattice whose cells halve those of a lattice of `shape` (vertices) along every axis."""
    return tuple(2 * n - 1 for n in shape)  # type: ignore[return-value]


def _route_lattice(logits: Tensor, shape: tuple[int, int, int]):
    """The lattice rendering decides on, and its vertex logits slab by slab: -> (its shape, an iterator of (M, X', Y',
    Z') channels-first values over slabs of whole cells along x, in order). The gate's cells halved along every axis
    while they number at most `MAX_ROUTE_CELLS` (a midpoint's logits the mean of its 2, 4 or 8 vertices: the gate's
    blend there, to float32 rounding), else the gate's own lattice."""
    m = logits.shape[-1]
    grid = logits.T.reshape(m, *shape)  # channels first, as `interpolate` takes it
    fine = halved(shape)
    halve = math.prod(n - 1 for n in fine) <= MAX_ROUTE_CELLS
    slab = max(1, SLAB_VALUES // max(1, (4 if halve else 1) * shape[1] * shape[2] * m))  # gate x-cells a slab covers

    def slabs():
        for a in range(0, shape[0] - 1, slab):
            v = grid[:, a : min(shape[0], a + slab + 1)]
            yield F.interpolate(v[None], size=tuple(2 * n - 1 for n in v.shape[1:]), mode="trilinear",
                                align_corners=True)[0] if halve else v

    return (fine if halve else shape), slabs()


@torch.no_grad()
def route_cells(logits: Tensor, shape: tuple[int, int, int],
                at_centre: bool = False) -> tuple[Tensor, tuple[int, int, int]]:
    """`top1_cells` on the gate's cells halved along every axis (`_route_lattice`), so that more samples lie in a cell
    with one clear expert: -> (cells,) int8, and the lattice's shape (vertices).

    A half-cell lies inside one of the gate's cells, where every logit is trilinear, hence on the half-cell too: its
    differences are extreme at the half-cell's 8 corners, so the test of `top1_cells` holds there as on a whole
    cell."""
    lattice, slabs = _route_lattice(logits, shape)
    margin = _margin(logits)
    return torch.cat([_decided(v, margin, at_centre).reshape(-1) for v in slabs]), lattice


# a Top-2 cell's first weight w, in [1/2, 1], is kept as the byte round((w - 1/2) * WEIGHT_STEPS)
WEIGHT_STEPS = 510


class PairCells:
    """A renormalised Top-2's choice per cell of a lattice (`pair_cells`): its two experts and their weights at the
    cell's centre. `pair` (cells,) the row of `pairs` (M * M, 2) that names the first and the second expert; `weight`
    (cells,) uint8, the first's weight w as round((w - 1/2) * WEIGHT_STEPS) (the second's is 1 - w)."""

    def __init__(self, pair: Tensor, weight: Tensor, m: int):
        self.pair, self.weight = pair, weight
        e = torch.arange(m, device=pair.device)
        self.pairs = torch.stack([e.repeat_interleave(m), e.repeat(m)], -1)  # row a * M + b: (a, b)
        first = torch.arange(256, device=pair.device, dtype=torch.float32) / WEIGHT_STEPS + 0.5
        self.weights = torch.stack([first, 1 - first], -1)  # row q: both weights

    def __call__(self, cell: Tensor) -> tuple[Tensor, Tensor]:
        """(N,) cells -> weights (N, 2) float32, experts (N, 2) int64, as `router.top_k` renormalised gives them."""
        return (self.weights.index_select(0, self.weight.index_select(0, cell).long()),
                self.pairs.index_select(0, self.pair.index_select(0, cell).long()))


@torch.no_grad()
def pair_cells(logits: Tensor, shape: tuple[int, int, int]) -> tuple[PairCells, tuple[int, int, int]]:
    """A renormalised Top-2's experts and weights per cell of the gate's halved lattice (`_route_lattice`), taken at
    the cell's centre: the two largest logits there and the softmax of the two. -> the cells and the lattice's shape.

    Rendering then looks each sample's choice up instead of blending the gate: the weights are constant over a half-cell
    (1/256 of lego's box along an axis at `moe.bake_res` 128) where the blend's vary smoothly, and the pair changes at
    cell faces instead of where the blend's third logit overtakes the second; a sample's colour moves by the weight's
    change times the two experts' difference there (lego M = 3: held-out PSNR -0.017 dB, M = 5 -0.002 dB)."""
    m = logits.shape[-1]
    code = torch.uint8 if m * m <= 256 else torch.int32
    lattice, slabs = _route_lattice(logits, shape)
    pairs, weights = [], []
    for v in slabs:
        v1, i1, v2, i2 = (t.reshape(-1) for t in _top_two(_centres(v)))
        pairs.append(i1.to(code).mul_(m).add_(i2.to(code)))  # under M * M: no overflow in `code`
        first = torch.sigmoid(v1 - v2)  # the softmax of the two, the first's share
        weights.append(first.sub_(0.5).mul_(WEIGHT_STEPS).round_().clamp_(0, 255).to(torch.uint8))
    return PairCells(torch.cat(pairs), torch.cat(weights), m), lattice


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
