"""Slow, obvious references that the tests compare the vectorised production code with.

They live here, not in boostnerf_cli: nothing in the tool uses them.
"""

from __future__ import annotations

import math
from typing import Callable

from torch import Tensor

from boostnerf_cli.fields.hashgrid import PRIMES, HashEncoding


def dispatch_dense_reference(
    x_rows: int, idx: Tensor, vals: Tensor, m: int, run_all: Callable[[int], Tensor], out_dim: int, like: Tensor
) -> Tensor:
    """The obvious version of `router.dispatch`: every expert on every sample, masked by the routing."""
    out = like.new_zeros(x_rows, out_dim)
    for e in range(m):
        weight = (vals * (idx == e)).sum(-1)  # (N,)
        out = out + weight[:, None] * run_all(e).reshape(x_rows, out_dim)
    return out


def reference_encoding(table: list[list[float]], enc: HashEncoding, point: list[float]) -> list[float]:
    """Slow pure-Python reference of `HashEncoding.forward` for one point.

    Unbounded Python integers, the hash reduced as the uint32 implementation does (mod 2^32, then
    mod 2^T), trilinear weights from scratch.
    """
    lo = [float(v) for v in enc.bbox[0]]
    out: list[float] = []
    for lv, n in enumerate(enc.resolutions):
        vx = enc.verts[lv]
        feats = [0.0] * enc.features
        base, frac = [], []
        for a in range(3):
            p = max(0.0, (point[a] - lo[a]) / enc.extent) * n
            p = min(p, vx[a] - 1)
            p0 = min(math.floor(p), max(0, vx[a] - 2))
            base.append(p0)
            frac.append(p - p0)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    x, y, z = base[0] + dx, base[1] + dy, base[2] + dz
                    wgt = (frac[0] if dx else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1]) * (
                        frac[2] if dz else 1 - frac[2])
                    if enc.dense[lv]:
                        row = x + y * vx[0] + z * vx[0] * vx[1]
                    else:
                        h = ((x * PRIMES[0]) ^ (y * PRIMES[1]) ^ (z * PRIMES[2])) % (1 << 32)
                        row = h % (1 << enc.log2_table)
                    for c in range(enc.features):
                        feats[c] += wgt * table[enc.offsets[lv] + row][c]
        out += feats
    return out
