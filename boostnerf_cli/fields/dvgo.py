"""DVGO-style expert: a dense density grid and a dense feature grid over the scene box.

density(x) = softplus(interp(V_density, x) + shift) / unit            (post-activation, per world unit)
color(x,d) = sigmoid(MLP([interp(V_feat, x), PE(d)]))                 (or sigmoid(interp) with no MLP)

`shift = log(1/(1 - alpha_init) - 1)` makes every voxel start with opacity `alpha_init` over one
`unit` of length; `unit` is the voxel size of the final grid and stays fixed while the grid grows
(progressive upscaling), so the meaning of the density does not change when the grid is resampled.
Outside its box the expert is empty (density 0), so experts with different boxes can be mixed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from boostnerf_cli.fields import grid as G
from boostnerf_cli.fields.base import ExpertModule, blockwise
from boostnerf_cli.fields.mlp import MLP
from boostnerf_cli.limits import (
    GRID_RES,
    MLP_LAYERS,
    MLP_WIDTH,
    OPEN_UNIT,
    PE_FREQS,
    Range,
    limit,
)


@dataclass
class DVGOConfig:
    """Architecture of a DVGO-style expert. `res`: the final grid has res^3 voxels."""

    res: int = limit(128, GRID_RES)
    # feature channels of the colour grid (with hidden 0: 3, the colour itself)
    feat_dim: int = limit(12, Range(1, 512))
    # width of the colour MLP; 0 = no MLP, colour = sigmoid of 3 grid channels
    hidden: int = limit(128, Range(0, MLP_WIDTH.hi))
    layers: int = limit(2, MLP_LAYERS)  # hidden layers of the colour MLP
    view_pe: int = limit(4, PE_FREQS)  # frequencies of the view-direction encoding
    # opacity over one voxel before training (the density's shift is log(1/(1 - a) - 1))
    alpha_init: float = limit(1e-2, OPEN_UNIT)


def direction_encoding(dirs: Tensor, n_freq: int) -> Tensor:
    """(N, C) -> (N, C (1 + 2 n_freq)): d, sin(2^k d), cos(2^k d) (directions, C = 3, or features)."""
    if n_freq == 0:
        return dirs
    if G.by_axis(dirs) and not (dirs.requires_grad and torch.is_grad_enabled()):
        # on the CPU a product broadcast along the short last axis runs element by element: one product with each
        # number (exact: powers of two), the same values (38k directions: 2.2 -> 1.6 ms, one thread); an input that
        # needs a gradient (TensoRF's features in training) keeps the one product, whose gradient sums in its order
        x = torch.cat([dirs * float(2 ** k) for k in range(n_freq)], dim=-1)
    else:
        freqs = 2.0 ** torch.arange(n_freq, device=dirs.device, dtype=dirs.dtype)
        x = (dirs[:, None, :] * freqs[:, None]).reshape(dirs.shape[0], dirs.shape[1] * n_freq)
    return torch.cat([dirs, torch.sin(x), torch.cos(x)], dim=-1)


def raw_from_sigma(sigma: Tensor, unit: float, shift: float) -> Tensor:
    """Inverse of sigma = softplus(raw + shift) / unit (sigma clamped to a tiny positive floor)."""
    y = (sigma * unit).clamp_min(1e-8)
    return torch.where(y > 20, y, torch.log(torch.expm1(y))) - shift


def color_mlp(in_dim: int, hidden: int, layers: int) -> MLP:
    mlp = MLP([in_dim] + [hidden] * layers + [3])
    nn.init.zeros_(mlp[-1].bias)
    return mlp


class DVGOExpert(ExpertModule):
    """Dense-grid radiance field; satisfies the Field protocol."""

    family = "dvgo"
    config_type = DVGOConfig
    grows = True

    def __init__(self, cfg: DVGOConfig, bbox: Tensor, unit: float | None = None,
                 shape: tuple[int, int, int] | None = None):
        super().__init__(cfg, bbox)
        final_shape = G.lattice_shape(self.bbox, cfg.res ** 3)
        self.unit = float(unit) if unit is not None else self.spacing(final_shape)
        self.shape = tuple(shape) if shape is not None else final_shape
        n = math.prod(self.shape)
        channels = cfg.feat_dim if cfg.hidden > 0 else 3
        self.density_table = nn.Parameter(torch.zeros(n, 1))
        self.feature_table = nn.Parameter(torch.zeros(n, channels))
        self.rgbnet = (
            color_mlp(cfg.feat_dim + 3 + 6 * cfg.view_pe, cfg.hidden, cfg.layers) if cfg.hidden > 0 else None
        )

    @property
    def voxel_size(self) -> float:
        return self.spacing(self.shape)

    @property
    def spatial_res(self) -> int:
        """Voxels per side of the final lattice (the density volume's default resolution)."""
        return self.cfg.res

    # --- the Field contract -------------------------------------------------------------------
    def _sigma(self, xyz: Tensor, raw: Tensor) -> Tensor:
        """(N,) the density of the points `xyz` from their blended raw values `raw` (none outside the box)."""
        return F.softplus(raw + self.shift) / self.unit * self.inside(xyz)

    def _rgb(self, idx: Tensor, w: Tensor, dirs: Tensor) -> Tensor:
        feat = G.lookup(self.feature_table, idx, w)
        if self.rgbnet is None:
            return torch.sigmoid(feat)
        return torch.sigmoid(self.rgbnet(torch.cat([feat, direction_encoding(dirs, self.cfg.view_pe)], -1)))

    def density(self, xyz: Tensor) -> Tensor:  # a blend and a few per-point steps: all rows at once (no MLP to block)
        return self._sigma(xyz, G.blend(self.density_table, xyz, self.bbox, self.shape)[:, 0])

    @blockwise
    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        idx, w = G.corners(xyz, self.bbox, self.shape)
        return self._rgb(idx, w, dirs)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        idx, w = G.corners(xyz, self.bbox, self.shape)
        return self._sigma(xyz, G.lookup(self.density_table, idx, w)[:, 0]), self._rgb(idx, w, dirs)

    def regularization(self) -> None:
        return None

    # --- growth and persistence ---------------------------------------------------------------
    @torch.no_grad()
    def regrid(self, n_voxels: int, bbox: Tensor | None = None) -> None:
        """Resample both grids onto about `n_voxels` voxels over `bbox` (default: the same box)."""
        new_bbox = self.bbox if bbox is None else bbox.to(self.bbox)
        new_shape = G.lattice_shape(new_bbox, n_voxels)
        for name in ("density_table", "feature_table"):
            table = getattr(self, name)
            setattr(self, name, nn.Parameter(G.resample(table, self.shape, self.bbox, new_shape, new_bbox)))
        self.bbox.copy_(new_bbox)
        self.shape = new_shape

    @torch.no_grad()
    def init_density(self, density) -> None:
        """Set the density grid so that it reproduces `density(xyz) -> sigma` at the lattice vertices."""
        pts = G.lattice_points(self.bbox, self.shape)
        sigma = torch.cat([density(pts[i : i + (1 << 18)]) for i in range(0, pts.shape[0], 1 << 18)])
        self.density_table.copy_(raw_from_sigma(sigma, self.unit, self.shift)[:, None])

    def resize_to(self, shape: tuple[int, int, int]) -> None:
        """Reallocate both grids for a lattice `shape` (values are then loaded from a state dict)."""
        n = math.prod(shape)
        self.density_table = nn.Parameter(self.density_table.new_zeros(n, 1))
        self.feature_table = nn.Parameter(self.feature_table.new_zeros(n, self.feature_table.shape[1]))
        self.shape = tuple(shape)

    def param_groups(self, lr_grid: float, lr_mlp: float) -> list[dict]:
        groups = [{"params": [self.density_table, self.feature_table], "lr": lr_grid}]
        if self.rgbnet is not None:
            groups.append({"params": list(self.rgbnet.parameters()), "lr": lr_mlp})
        return groups

