"""Dense voxel grids with trilinear interpolation, channels-last, as gathered lookups.

A grid of shape (X, Y, Z) with C channels is stored as a table (X*Y*Z, C); values sit on lattice
vertices that span the box exactly (vertex 0 at the min corner, vertex X-1 at the max corner, like
`grid_sample(align_corners=True)`). A point's value is the trilinear blend of its 8 surrounding
vertices: `corners` gives their table rows and weights, `lookup` blends. The lookup is an
`embedding_bag` forward with a scatter-add backward into the table (measured faster on CPU than
`grid_sample`'s backward, and it never touches the position gradient, which training never needs).
Points outside the box are clamped to it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from boostnerf_cli import flops
from boostnerf_cli.device import constant


def lattice_shape(bbox: Tensor, n_voxels: int) -> tuple[int, int, int]:
    """Grid sides with about `n_voxels` vertices and isotropic spacing over the box (DVGO's rule).

    A side is at least 2 vertices. A side that the rule would give fewer (a box flatter than the lattice is
    fine) is set to 2 and the other sides share the rest of the budget, still isotropic among themselves: a
    [3, 3, 1e-6] box at 8^3 gets 16 x 16 x 2, where the plain rule gave 2.7 M vertices."""
    size = (bbox[1] - bbox[0]).double().cpu()  # a few numbers: on the CPU, whatever device the box is on
    fixed = torch.zeros(3, dtype=torch.bool)
    while True:
        free = ~fixed
        voxel = (size[free].prod() / (n_voxels / 2 ** int(fixed.sum()))) ** (1.0 / int(free.sum()))
        sides = torch.where(fixed, 2, (size / voxel).round().long())
        thin = free & (sides < 2)
        if not thin.any() or bool(thin.eq(free).all()):  # every side left is thin too: each gets 2
            break
        fixed |= thin
    sides = torch.clamp(sides, min=2)
    return tuple(int(v) for v in sides)  # type: ignore[return-value]


def by_axis(xyz: Tensor) -> bool:
    """Whether point arithmetic goes axis by axis (`axis_coords`): on the CPU, where an operation broadcast along a last
    axis of 3 runs element by element and one over a column with a number runs vectorised (622k points: 5.8 -> 2 ms),
    the same operations on the same numbers. A GPU has no trouble with the broadcast and pays per operation launched:
    it keeps one operation over all three axes."""
    return xyz.device.type == "cpu"


def box_frame(xyz: Tensor, bbox: Tensor, scale) -> Tensor:
    """The points (..., 3) in the box's frame, over all three axes at once: (xyz - lo) / (hi - lo) * scale (`scale` a
    number or one per axis). `axis_coords` works it out axis by axis where `by_axis`."""
    return (xyz - bbox[0]) / (bbox[1] - bbox[0]) * scale


def axis_coords(xyz: Tensor, bbox: Tensor, scale) -> list[Tensor]:
    """`box_frame` as three (...) tensors, one per axis, worked out axis by axis where `by_axis`, else over (..., 3) at
    once; the same values, to the bit, either way."""
    if not by_axis(xyz):
        return list(box_frame(xyz, bbox, scale).unbind(-1))
    lo, size = bbox[0], bbox[1] - bbox[0]
    xyz = xyz.to(torch.promote_types(xyz.dtype, bbox.dtype))  # as against a (3,) row: a one-number box would not
    return [(xyz[..., a] - lo[a]) / size[a] * (scale[a] if isinstance(scale, Tensor) else scale) for a in range(3)]


def inside_box(xyz: Tensor, bbox: Tensor) -> Tensor:
    """(..., 3) -> (...) bool: in the box, faces included (axis by axis where `by_axis`)."""
    if not by_axis(xyz):
        return ((xyz >= bbox[0]) & (xyz <= bbox[1])).all(dim=-1)
    xyz = xyz.to(torch.promote_types(xyz.dtype, bbox.dtype))  # compared as against a (3,) row
    inside = (xyz[..., 0] >= bbox[0, 0]) & (xyz[..., 0] <= bbox[1, 0])
    for a in (1, 2):
        inside &= (xyz[..., a] >= bbox[0, a]) & (xyz[..., a] <= bbox[1, a])
    return inside


def flat_cells(xyz: Tensor, bbox: Tensor, scale: Tensor, top: Tensor, strides: Tensor) -> Tensor:
    """(N, 3) points -> (N,) the flat index of their cells, in the strides' dtype (floating point, exact for whole
    numbers of its precision): each axis' coordinate in the box's frame times `scale` (3,), floored, clamped into [0,
    `top`] (3,), times its stride (3,), summed over the axes (axis by axis where `by_axis`)."""
    if not by_axis(xyz):  # the same operations over all three axes at once
        return torch.minimum(box_frame(xyz, bbox, scale).floor_().clamp_min_(0), top).to(strides.dtype) @ strides
    index = None
    for a, p in enumerate(axis_coords(xyz, bbox, scale)):
        cell = torch.minimum(p.floor_().clamp_min_(0), top[a]).to(strides.dtype).mul_(strides[a])
        index = cell if index is None else index.add_(cell)
    return index


def corners(xyz: Tensor, bbox: Tensor, shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """Trilinear support of points: (N, 3) -> row indices (N, 8) int64, weights (N, 8)."""
    flops.add("interp", flops.CORNER_FLOPS * xyz.shape[0])
    res = constant(tuple(shape), xyz.device, xyz.dtype)
    sy, sz = shape[1] * shape[2], shape[2]
    if by_axis(xyz):
        base, f = None, []
        for a, (p, stride) in enumerate(zip(axis_coords(xyz, bbox, res - 1), (sy, sz, 1))):
            p = torch.minimum(p.clamp_min_(0), res[a] - 1)
            p0 = torch.minimum(p.floor(), res[a] - 2)
            f.append(p - p0)
            i0 = p0.long()
            base = i0 * stride if base is None else base.add_(i0 * stride if stride > 1 else i0)
        fx, fy, fz = f
    else:  # the same operations over all three axes at once
        p = torch.minimum(box_frame(xyz, bbox, res - 1).clamp_min_(0), res - 1)
        p0 = torch.minimum(p.floor(), res - 2)
        i0 = p0.long()
        base = i0[:, 0] * sy + i0[:, 1] * sz + i0[:, 2]
        fx, fy, fz = (p - p0).unbind(-1)
    # corner k = dx*4 + dy*2 + dz; weights built from contiguous (N,) vectors (fast on CPU)
    offs = constant((0, 1, sz, sz + 1, sy, sy + 1, sy + sz, sy + sz + 1), xyz.device, torch.long)
    gx, gy, gz = 1 - fx, 1 - fy, 1 - fz
    xy = (gx * gy, gx * fy, fx * gy, fx * fy)
    w = torch.stack([c for pair in xy for c in (pair * gz, pair * fz)], dim=1)
    return base[:, None] + offs, w


class _Lookup(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor, w: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(idx, w)
        ctx.rows = table.shape[0]
        return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        idx, w = ctx.saved_tensors
        channels = grad.shape[1]
        if channels > 4 and ctx.rows >= idx.numel() and grad.device.type == "cpu":
            # A grid of many channels and more rows than the batch has corners (DVGO's feature grids): the products
            # added row by row straight into the table's (rows, C) layout, with no transposed copy of the grid
            # after (80^3 rows x 12 channels, 19.5k points: 21-39 -> 12-18 ms, one thread; 73^3 rows, 8k points:
            # 8.2 -> 4.4 ms). The same products, each row's in the same order: the same sums.
            src = (w[:, :, None] * grad[:, None, :]).reshape(-1, channels)
            grad_table = torch.zeros(ctx.rows, channels, dtype=grad.dtype, device=grad.device)
            return grad_table.index_add_(0, idx.reshape(-1), src), None, None
        # Channels-first scatter-add: one pass per channel plane keeps the random writes in cache
        # (measured 3-4x faster than a channels-last index_add for 3-12 channels on CPU, for small grids).
        # (C, N, K) written in that order: with the weights as the first operand the product's layout is
        # (C, N, K) and the reshape is free (grad first made it (N, C, K) plus a copy: 0.46 against 1.7 ms
        # for 13k points x 8 corners x 8 channels, one thread). `grad.T.contiguous()` is free when the
        # gradient arrives channels-first (fields/mlp.py's backward delivers it so).
        src = (w[None, :, :] * grad.T.contiguous()[:, :, None]).reshape(channels, -1)
        if channels == 1 or 4 * idx.numel() >= ctx.rows:
            grad_table = torch.zeros(channels, ctx.rows, dtype=grad.dtype, device=grad.device)
            grad_table.index_add_(1, idx.reshape(-1), src)
            return grad_table.T, None, None  # (rows, 1) is already in the table's layout
        # Several channels and a batch that touches few rows (a large grid: DVGO's feature grid):
        # accumulate over the touched rows only, then copy them into a zeroed gradient in the table's
        # own (rows, C) layout. Accumulating over the whole grid channels-first and transposing it back
        # cost ~4x more on CPU (an 80^3 grid's 12 channels, 7k samples x 8 corners: 38 ms against 9 ms,
        # one thread), the transpose most of it. When the batch's corners are a quarter of the rows or
        # more (hash tables, the gate's small grid) the sort in `unique` costs more than it saves.
        rows, inv = torch.unique(idx.reshape(-1), return_inverse=True)
        compact = torch.zeros(channels, rows.numel(), dtype=grad.dtype, device=grad.device)
        compact.index_add_(1, inv, src)
        grad_table = torch.zeros(ctx.rows, channels, dtype=grad.dtype, device=grad.device)
        return grad_table.index_copy_(0, rows, compact.T.contiguous()), None, None


def lookup(table: Tensor, idx: Tensor, w: Tensor) -> Tensor:
    """Blend table rows: table (V, C), idx (N, K), w (N, K) -> (N, C) (K = 8 trilinear, 4 bilinear, 2 linear)."""
    if idx.shape[0] == 0:
        return table.new_zeros(0, table.shape[1])
    flops.add("interp", 2 * idx.shape[1] * table.shape[1] * idx.shape[0])  # K corners x C multiply-adds
    if torch.compiler.is_compiling():  # a gather and a weighted sum, which the compiler fuses (and its backward)
        return (table[idx] * w[..., None].to(table.dtype)).sum(1)
    if table.requires_grad and torch.is_grad_enabled():
        return _Lookup.apply(table, idx, w)
    return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")


def blend(table: Tensor, xyz: Tensor, bbox: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """`lookup(table, *corners(xyz, bbox, shape))` -> (N, C): for a one-channel table that needs no gradient (rendering)
    through `grid_sample`, which blends without listing the 8 corners (2x faster on the CPU for 8192 points, 4x for
    300k; the same blend to float32 rounding of the position); else as `lookup` does.

    On the CPU grid_sample shares out its batch among the threads, not its points: the points go as a batch of one
    part per thread over the same volume (expanded, not copied), the same values to the bit, in 1/threads the time."""
    n = xyz.shape[0]
    if table.shape[1] != 1 or (table.requires_grad and torch.is_grad_enabled()) or torch.compiler.is_compiling() \
            or n == 0:
        return lookup(table, *corners(xyz, bbox, shape))
    flops.add("interp", (flops.CORNER_FLOPS + 16) * n)  # as corners and lookup count it
    # grid_sample's volume is (B, C, D, H, W) with D, H, W the lattice's x, y, z, its points (x, y, z) as (W, H, D)
    # in [-1, 1]; align_corners: vertex 0 at -1, the last at 1; border: a point outside the box clamped to it
    q = torch.stack([c - 1 for c in reversed(axis_coords(xyz, bbox, 2))], -1).to(table.dtype)
    parts = min(torch.get_num_threads(), max(1, n // 1024)) if xyz.device.type == "cpu" else 1
    if n % parts:  # padded to equal parts (the pads' values are dropped)
        q = torch.cat([q, q.new_zeros(parts - n % parts, 3)])
    volume = table.reshape(1, 1, *shape).expand(parts, -1, -1, -1, -1)
    out = F.grid_sample(volume, q.reshape(parts, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out.reshape(-1, 1)[:n]


def lattice_points(bbox: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """World positions of every lattice vertex, (prod(shape), 3), in table row order."""
    axes = [torch.linspace(float(bbox[0, a]), float(bbox[1, a]), shape[a], device=bbox.device, dtype=bbox.dtype)
            for a in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)


def resample(table: Tensor, old_shape: tuple[int, int, int], old_bbox: Tensor,
             new_shape: tuple[int, int, int], new_bbox: Tensor) -> Tensor:
    """Trilinearly resample a grid's values onto a new lattice and box: -> (prod(new_shape), C)."""
    pts = lattice_points(new_bbox.to(table.device), new_shape)
    out = []
    for i in range(0, pts.shape[0], 1 << 20):
        idx, w = corners(pts[i : i + (1 << 20)], old_bbox, old_shape)
        out.append(F.embedding_bag(idx, table.detach(), per_sample_weights=w, mode="sum"))
    return torch.cat(out)
