"""Vector-matrix (VM) factorised grids (TensoRF, Chen et al. 2022).

A 3D grid of shape (X, Y, Z) with R components per mode is stored as three planes and three lines:

    mode 0: plane over (x, y) (X*Y, R),  line along z (Z, R)
    mode 1: plane over (x, z) (X*Z, R),  line along y (Y, R)
    mode 2: plane over (y, z) (Y*Z, R),  line along x (X, R)

and a point's components are plane_m(bilinear) * line_m(linear), (N, 3R) concatenated over the
modes. Values sit on lattice vertices spanning the box (vertex 0 at the min corner, as in
`grid.py`), looked up as gathered blends through `grid.lookup` (4 corners per plane, 2 per line).
Growth resamples planes and lines separately (bilinear / linear, vertex-aligned).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from boostnerf_cli import flops
from boostnerf_cli.device import constant
from boostnerf_cli.fields import grid as G

PLANE_AXES = ((0, 1), (0, 2), (1, 2))
LINE_AXIS = (2, 1, 0)
CORNER2_FLOPS = 18  # normalise 2x3, floor/clamp 2x3, 4 weights + 2 complements
CORNER1_FLOPS = 7  # normalise 3, floor/clamp 3, 1 complement


def _norm(xyz: Tensor, bbox: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """World points -> continuous lattice coordinates (N, 3), clamped to the lattice."""
    res = constant(tuple(shape), xyz.device, xyz.dtype)
    p = (xyz - bbox[0]) / (bbox[1] - bbox[0]) * (res - 1)
    return torch.minimum(p.clamp_min(0), res - 1)


def _axis(p: Tensor, n: int) -> tuple[Tensor, Tensor]:
    p0 = torch.minimum(p.floor(), torch.full_like(p, n - 2))
    return p0.long(), p - p0


def plane_corners(p: Tensor, a: int, b: int, shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """Bilinear support on the (a, b) plane: rows (N, 4) of a (shape[a] * shape[b]) table, weights (N, 4)."""
    i, fi = _axis(p[:, a], shape[a])
    j, fj = _axis(p[:, b], shape[b])
    nb = shape[b]
    base = i * nb + j
    idx = torch.stack([base, base + 1, base + nb, base + nb + 1], dim=1)
    gi, gj = 1 - fi, 1 - fj
    w = torch.stack([gi * gj, gi * fj, fi * gj, fi * fj], dim=1)
    return idx, w


def line_corners(p: Tensor, a: int, shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    i, fi = _axis(p[:, a], shape[a])
    return torch.stack([i, i + 1], dim=1), torch.stack([1 - fi, fi], dim=1)


class VMGrid(nn.Module):
    """Three planes and three lines with `rank` components each; xyz -> (N, 3 * rank)."""

    def __init__(self, shape: tuple[int, int, int], rank: int, init_std: float = 0.1):
        super().__init__()
        self.shape = tuple(shape)
        self.rank = rank
        self.planes = nn.ParameterList(
            [nn.Parameter(init_std * torch.randn(shape[a] * shape[b], rank)) for a, b in PLANE_AXES])
        self.lines = nn.ParameterList([nn.Parameter(init_std * torch.randn(shape[c], rank)) for c in LINE_AXIS])

    @property
    def out_dim(self) -> int:
        return 3 * self.rank

    def forward(self, xyz: Tensor, bbox: Tensor) -> Tensor:
        if xyz.shape[0] == 0:
            return xyz.new_zeros(0, self.out_dim)
        p = _norm(xyz, bbox, self.shape)
        flops.add("interp", (3 * (CORNER2_FLOPS + CORNER1_FLOPS) + 3 * self.rank) * xyz.shape[0])
        outs = []
        for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXIS)):
            pi, pw = plane_corners(p, a, b, self.shape)
            li, lw = line_corners(p, c, self.shape)
            outs.append(G.lookup(self.planes[m], pi, pw) * G.lookup(self.lines[m], li, lw))
        return torch.cat(outs, dim=-1)

    @torch.no_grad()
    def resample(self, new_shape: tuple[int, int, int]) -> None:
        """Resample every plane and line onto a new lattice (vertex-aligned, same box)."""
        old = self.shape
        for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXIS)):
            plane = self.planes[m].detach().T.reshape(1, self.rank, old[a], old[b])
            plane = F.interpolate(plane, size=(new_shape[a], new_shape[b]), mode="bilinear", align_corners=True)
            self.planes[m] = nn.Parameter(plane.reshape(self.rank, -1).T.contiguous())
            line = self.lines[m].detach().T.reshape(1, self.rank, old[c])
            line = F.interpolate(line, size=new_shape[c], mode="linear", align_corners=True)
            self.lines[m] = nn.Parameter(line.reshape(self.rank, -1).T.contiguous())
        self.shape = tuple(new_shape)

    def resize_to(self, shape: tuple[int, int, int]) -> None:
        """Reallocate for a lattice `shape` (values are then loaded from a state dict)."""
        for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXIS)):
            self.planes[m] = nn.Parameter(self.planes[m].new_zeros(shape[a] * shape[b], self.rank))
            self.lines[m] = nn.Parameter(self.lines[m].new_zeros(shape[c], self.rank))
        self.shape = tuple(shape)

    def l1(self) -> Tensor:
        """Mean absolute value of every plane and line entry (TensoRF's L1 sparsity term)."""
        total = sum(p.abs().sum() for p in self.parameters())
        return total / sum(p.numel() for p in self.parameters())
