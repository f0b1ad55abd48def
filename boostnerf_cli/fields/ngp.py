"""Instant-NGP-style expert: a multi-resolution hash encoding and two small MLPs.

    h          = HashEncoding(x)                         (L levels x F features, fields/hashgrid.py)
    raw, g     = density MLP(h)                          (1 + geo_feat outputs, `hidden` units)
    density(x) = softplus(raw + shift) / unit
    color(x,d) = sigmoid(colour MLP([g, PE(d)]))

`res` is the number of levels L (the paper varies L = 6, 8, 10, 16, 24), with the table size 2^T,
F features per level and the per-level growth factor b = exp(ln(N_max / N_min) / (L - 1)), so more
levels means more, and more finely spaced, tables between the same coarsest and finest
resolutions. The hash tables have a fixed size, so the expert does not grow (`grows = False`).
Its occupancy grid (NGP's density bitfield), refreshed by pretrain every `occupancy_every` steps
from the expert's own density, is a lattice of `grid_res` cells along the box's longest side
(`shape`); `unit`, the length in which density is measured and the render step is set, is the
spacing of that lattice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.base import ExpertModule, blockwise
from boostnerf_cli.fields.dvgo import color_mlp, direction_encoding
from boostnerf_cli.fields.hashgrid import MAX_COORD, HashEncoding
from boostnerf_cli.fields.mlp import MLP
from boostnerf_cli.fields.warmstart import fit_density
from boostnerf_cli.limits import (
    GRID_RES,
    MLP_LAYERS,
    MLP_WIDTH,
    NON_NEGATIVE,
    OPEN_UNIT,
    PE_FREQS,
    Range,
    at_least,
    limit,
)


@dataclass
class NGPConfig:
    """Architecture of an Instant-NGP-style expert. `res` is the number of levels L."""

    res: int = limit(16, at_least(1))  # L
    log2_table: int = limit(19, Range(1, 30))  # T: each level's table has at most 2^T rows (hashgrid.py)
    features: int = limit(2, Range(1, 64))  # F per level
    base_res: int = limit(16, at_least(1))  # N_min: cells along the box's longest side at the coarsest level
    max_res: int = limit(1024, Range(1, MAX_COORD - 3))  # N_max (>= base_res): at the finest level
    grid_res: int = limit(128, GRID_RES)  # occupancy grid (and density unit) cells along the longest side
    hidden: int = limit(64, MLP_WIDTH)  # density MLP: one hidden layer
    geo_feat: int = limit(15, Range(0, MLP_WIDTH.hi))  # features passed from the density MLP to the colour MLP
    color_hidden: int = limit(64, MLP_WIDTH)  # width of the colour MLP
    color_layers: int = limit(2, MLP_LAYERS)  # hidden layers of the colour MLP
    view_pe: int = limit(4, PE_FREQS)  # frequencies of the view-direction encoding
    alpha_init: float = limit(1e-4, OPEN_UNIT)  # opacity over one unit before training (where the density MLP gives 0)
    fit_steps: int = limit(200, NON_NEGATIVE)  # Adam steps of the warm start from the coarse geometry


class NGPExpert(ExpertModule):
    """Hash-encoded radiance field; satisfies the Field protocol and the Expert contract."""

    family = "ngp"
    config_type = NGPConfig
    gate_grid = "hash"  # the paper's Instant-NGP mixture gates with a hash grid
    grows = False

    def __init__(self, cfg: NGPConfig, bbox: Tensor, unit: float | None = None,
                 shape: tuple[int, int, int] | None = None):
        if cfg.res < 1:
            raise BoostNerfError(f"an ngp expert needs at least one level, got res={cfg.res}")
        super().__init__(cfg, bbox)
        size = self.bbox[1] - self.bbox[0]
        self.shape = tuple(shape) if shape is not None else tuple(
            max(2, math.ceil(float(s / size.max()) * cfg.grid_res)) for s in size)
        self.unit = float(unit) if unit is not None else float(size.max()) / cfg.grid_res
        self.encoding = HashEncoding(self.bbox, cfg.res, cfg.log2_table, cfg.features, cfg.base_res, cfg.max_res)
        self.sigma_net = MLP([self.encoding.out_dim, cfg.hidden, 1 + cfg.geo_feat])
        self.rgbnet = color_mlp(cfg.geo_feat + 3 + 6 * cfg.view_pe, cfg.color_hidden, cfg.color_layers)

    @property
    def spatial_res(self) -> int:
        """Cells of its occupancy lattice along the longest side (the density volume's default)."""
        return self.cfg.grid_res

    # --- the Field contract -------------------------------------------------------------------
    @blockwise
    def _hidden(self, xyz: Tensor) -> Tensor:
        return self.sigma_net(self.encoding(xyz))

    def raw_density(self, xyz: Tensor) -> Tensor:
        return self._hidden(xyz)[:, 0]

    def _sigma(self, xyz: Tensor, raw: Tensor) -> Tensor:
        return F.softplus(raw + self.shift) / self.unit * self.inside(xyz)

    @blockwise
    def _rgb(self, geo: Tensor, dirs: Tensor) -> Tensor:
        return torch.sigmoid(self.rgbnet(torch.cat([geo, direction_encoding(dirs, self.cfg.view_pe)], -1)))

    def density(self, xyz: Tensor) -> Tensor:
        return self._sigma(xyz, self.raw_density(xyz))

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        return self._rgb(self._hidden(xyz)[:, 1:], dirs)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        h = self._hidden(xyz)
        return self._sigma(xyz, h[:, 0]), self._rgb(h[:, 1:], dirs)

    def batch_view(self, packer=None) -> "NGPBatch":
        """A per-batch view for the renderer: each sample is encoded once for both passes."""
        return NGPBatch(self)

    def regularization(self) -> None:
        return None

    # --- growth and persistence ---------------------------------------------------------------
    def regrid(self, n_voxels: int) -> None:
        raise BoostNerfError("ngp experts have fixed-size hash tables and do not grow")

    def init_density(self, density) -> None:
        """Fit the encoding and the density MLP to `density(xyz) -> sigma` (see fields/warmstart.py)."""
        params = [self.encoding.table] + list(self.sigma_net.parameters())
        fit_density(self, params, density)

    def resize_to(self, shape: tuple[int, int, int]) -> None:
        if tuple(shape) != tuple(self.shape):
            raise BoostNerfError(f"an ngp expert's lattice is fixed at {self.shape}, cannot load one of {shape}")

    def param_groups(self, lr_grid: float, lr_mlp: float) -> list[dict]:
        return [
            {"params": [self.encoding.table], "lr": lr_grid},
            {"params": list(self.sigma_net.parameters()) + list(self.rgbnet.parameters()), "lr": lr_mlp},
        ]

    def config_dict(self) -> dict:
        return {**super().config_dict(), "encoding": self.encoding.config_dict()}


class NGPBatch:
    """A per-batch Field view of an NGP expert that encodes each sample once.

    `density(xyz)` keeps the density MLP's output for those samples (raw density and geometry
    features); the renderer's colour pass then calls `color_rows(rows, dirs)` for a subset `rows` of
    them, which takes their geometry features from it instead of hashing and running the density MLP
    again. The values are those of `color(xyz[rows], dirs)`; the gradients too (the features' gradient
    from both passes meets in the one encoding). Measured in docs/benchmarks.md.
    """

    def __init__(self, expert: NGPExpert):
        self.expert = expert
        self._hidden: Tensor | None = None

    def density(self, xyz: Tensor, live: Tensor | None = None) -> Tensor:
        h = self.expert._hidden(xyz)
        self._hidden = h
        return self.expert._sigma(xyz, h[:, 0])

    def color_rows(self, rows: Tensor, dirs: Tensor, live: Tensor | None = None) -> Tensor:
        if self._hidden is None:
            raise RuntimeError("color_rows needs a density pass first")
        return self.expert._rgb(self._hidden[rows, 1:], dirs)

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        return self.expert.color(xyz, dirs)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        return self.expert.query(xyz, dirs)
