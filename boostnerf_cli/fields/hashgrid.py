"""Multi-resolution hash encoding (Instant-NGP, Mueller et al. 2022), in pure PyTorch.

L levels; level l is a lattice of N_l = floor(N_min * b^l) cells along the box's longest side
(isotropic cells: shorter sides get proportionally fewer), b = exp(ln(N_max / N_min) / (L - 1)) the
per-level growth factor. Each level owns a table of at most 2^T rows of F features; a point's
feature at level l is the trilinear blend of the rows of its 8 surrounding lattice vertices, and
the encoding is the L blends concatenated, (N, L * F).

Indexing of vertex (x, y, z) (non-negative integers) at level l:
  * dense, when the level's whole lattice fits its table (coarse levels):
        row = x + y * V_x + z * V_x * V_y            (V_a vertices along axis a; no collisions)
  * hashed otherwise (the spatial hash of Instant-NGP, Teschner et al. 2003):
        row = (x * 1  XOR  y * 2654435761  XOR  z * 805459861)  mod 2^T
All of it is computed in int64: coordinates are below 2^24 and the primes below 2^32, so every
product is below 2^56 and nothing overflows. Reducing mod 2^T keeps only the low T <= 30 bits, which
no overflow could have touched, so the rows are exactly those of the usual uint32 implementation
(tests compare with a slow pure-Python reference that uses unbounded integers and reduces
mod 2^32 first). The level's rows are then offset into one shared table (sum of level sizes, F).

Index arithmetic is counted as flops (docs/flops.md): 40 per point and level for the corners and
weights (as a dense trilinear lookup), 6 for the per-axis prime products, 4 per corner for the
XORs, the modulo and the level offset; plus the blend, 16 F per point and level.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from boostnerf_cli import flops
from boostnerf_cli.device import constant
from boostnerf_cli.fields import grid as G

PRIMES = (1, 2654435761, 805459861)
HASH_EXTRA_FLOPS = 6 + 8 * 4  # per point and hashed level, on top of the corners (blend: grid.lookup)
MAX_COORD = 1 << 24


def level_resolutions(levels: int, base_res: int, max_res: int) -> list[int]:
    """N_l = floor(N_min * b^l), b = exp(ln(N_max / N_min) / (L - 1)) (Instant-NGP's Eq. 2-3)."""
    if levels == 1:
        return [base_res]
    b = growth_factor(levels, base_res, max_res)
    return [math.floor(base_res * b ** lv + 1e-6) for lv in range(levels)]


def growth_factor(levels: int, base_res: int, max_res: int) -> float:
    return math.exp((math.log(max_res) - math.log(base_res)) / max(1, levels - 1))


class HashEncoding(nn.Module):
    """xyz (N, 3) in a box -> features (N, L * F). One parameter: `table` (sum of level rows, F)."""

    def __init__(self, bbox: Tensor, levels: int, log2_table: int, features: int, base_res: int, max_res: int,
                 init_std: float = 1e-4):
        super().__init__()
        if not 1 <= log2_table <= 30:
            raise ValueError(f"log2 table size must be in 1..30, got {log2_table}")
        if max_res < base_res or base_res < 1:
            raise ValueError(f"need 1 <= base_res <= max_res, got {base_res}, {max_res}")
        self.levels, self.log2_table, self.features = levels, log2_table, features
        self.base_res, self.max_res = base_res, max_res
        size = (bbox[1] - bbox[0]).double()
        self.extent = float(size.max())  # the box's longest side: cells are isotropic
        self.rel = [float(v) for v in size / size.max()]
        self.resolutions = level_resolutions(levels, base_res, max_res)
        if max(self.resolutions) + 2 >= MAX_COORD:
            raise ValueError(f"level resolution {max(self.resolutions)} is too large for the int64 hash")
        cap = 1 << log2_table
        self.verts: list[tuple[int, int, int]] = []  # vertices per axis and level
        self.dense: list[bool] = []
        self.sizes: list[int] = []
        for n in self.resolutions:
            v = tuple(math.ceil(r * n - 1e-9) + 1 for r in self.rel)
            self.verts.append(v)  # type: ignore[arg-type]
            dense = math.prod(v) <= cap
            self.dense.append(dense)
            self.sizes.append(math.prod(v) if dense else cap)
        self.offsets = [0]
        for s in self.sizes:
            self.offsets.append(self.offsets[-1] + s)
        self.register_buffer("bbox", bbox.detach().clone().float())
        self.table = nn.Parameter(torch.empty(self.offsets[-1], features).uniform_(-init_std, init_std) if init_std > 0
                                  else torch.zeros(self.offsets[-1], features))

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def corners(self, xyz: Tensor) -> tuple[Tensor, Tensor]:
        """-> table rows (L, N, 8) int64 and trilinear weights (L, N, 8); corner k = dx*4 + dy*2 + dz.

        Computed level-major, one contiguous (L, N) vector per axis and corner choice, each corner
        written into its slot: measured several times faster on CPU than broadcasting over small
        trailing (2, 2, 2) corner dimensions.
        """
        n, dev, L = xyz.shape[0], xyz.device, self.levels
        res = constant(tuple(self.resolutions), dev, xyz.dtype)[:, None]  # (L, 1)
        hi = constant(tuple(tuple(v - 1 for v in vs) for vs in self.verts), dev, xyz.dtype)  # (L, 3): last vertex
        u = ((xyz - self.bbox[0]) / self.extent).clamp_min(0).T.contiguous()  # (3, N), in [0, rel_a]
        i0, f = [], []
        for a in range(3):
            p = torch.minimum(u[a][None, :] * res, hi[:, a : a + 1])  # (L, N) lattice coordinate
            p0 = torch.minimum(p.floor(), (hi[:, a : a + 1] - 1).clamp_min(0))
            f.append(p - p0)
            i0.append(p0.long())
        # into preallocated slots on the CPU (fastest); stacked when compiled (the compiler cannot trace `out=` into
        # a strided slot, and fuses the stack itself)
        stacked = torch.compiler.is_compiling()
        wx = (1 - f[0], f[0])
        wy = (1 - f[1], f[1])
        wz = (1 - f[2], f[2])
        w = _corners(wx, wy, wz, torch.mul, None if stacked else torch.empty(L, n, 8, dtype=xyz.dtype, device=dev))
        rows = None if stacked else torch.empty(L, n, 8, dtype=torch.long, device=dev)
        parts = []  # the dense levels' rows, the hashed levels' rows (when stacked)
        offs = constant(tuple(self.offsets[:-1]), dev, torch.long)[:, None]  # (L, 1)
        nd = sum(self.dense)  # levels grow finer, so the dense ones come first
        if nd > 0:  # dense rows: x + y V_x + z V_x V_y (+ the level's offset, folded into x)
            v = constant(tuple(self.verts[:nd]), dev, torch.long)
            sy, sz = v[:, 0, None], (v[:, 0] * v[:, 1])[:, None]
            x0, y0, z0 = i0[0][:nd] + offs[:nd], i0[1][:nd] * sy, i0[2][:nd] * sz
            parts.append(_corners((x0, x0 + 1), (y0, y0 + sy), (z0, z0 + sz), torch.add,
                                  None if rows is None else rows[:nd]))
        if nd < L:  # hashed rows: (x p0 XOR y p1 XOR z p2) mod 2^T, then + the level's offset
            mask = (1 << self.log2_table) - 1
            hx, hy, hz = ([(i0[a][nd:] + d) * PRIMES[a] for d in (0, 1)] for a in range(3))
            hashed = _corners(hx, hy, hz, torch.bitwise_xor, None if rows is None else rows[nd:])
            hashed &= mask
            hashed += offs[nd:, :, None]
            parts.append(hashed)
        flops.add("hash", (flops.CORNER_FLOPS * L + HASH_EXTRA_FLOPS * (L - nd)) * n)
        return (torch.cat(parts) if rows is None else rows), w

    def forward(self, xyz: Tensor) -> Tensor:
        if xyz.shape[0] == 0:
            return xyz.new_zeros(0, self.out_dim)
        rows, w = self.corners(xyz)
        feat = G.lookup(self.table, rows.reshape(-1, 8), w.reshape(-1, 8).to(self.table.dtype))  # (L N, F)
        return feat.reshape(self.levels, xyz.shape[0], self.features).transpose(0, 1).reshape(xyz.shape[0], -1)

    def config_dict(self) -> dict:
        return {"levels": self.levels, "log2_table": self.log2_table, "features": self.features,
                "base_res": self.base_res, "max_res": self.max_res, "resolutions": self.resolutions,
                "growth_factor": growth_factor(self.levels, self.base_res, self.max_res),
                "dense_levels": sum(self.dense)}


def _corners(xs, ys, zs, op, out: Tensor | None) -> Tensor:
    """(..., 8) with corner dx*4 + dy*2 + dz = op(op(xs[dx], ys[dy]), zs[dz]): written into `out`'s slots, or
    stacked when `out` is None (the same values)."""
    if out is None:
        return torch.stack([op(op(xs[dx], ys[dy]), zs[dz]) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], -1)
    for dx in (0, 1):
        for dy in (0, 1):
            xy = op(xs[dx], ys[dy])
            for dz in (0, 1):
                op(xy, zs[dz], out=out[..., dx * 4 + dy * 2 + dz])
    return out
