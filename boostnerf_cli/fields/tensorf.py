"""TensoRF-style expert: vector-matrix (VM) factorised density and appearance grids.

density(x) = softplus(sum(VM_sigma(x)) + shift) / unit            (3 * density_rank components)
color(x,d) = sigmoid(MLP([B VM_app(x), PE(B VM_app(x)), PE(d)]))   (B: linear basis to app_dim)

As in `dvgo.py`, `unit` is the voxel size of the final res^3 lattice and stays fixed while the
planes and lines grow (`regrid`), and the expert is empty outside its box. The training loss adds
`l1_weight` x the mean absolute value of the density planes and lines (`regularization`), which
pushes empty space to zero density. TensoRF's alpha mask, the grid of cells whose opacity is
above a threshold, is the occupancy grid that pretrain refreshes from the expert's own density
every `occupancy_every` steps and at every growth step; samples in masked cells are never
evaluated.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from boostnerf_cli.fields import grid as G
from boostnerf_cli.fields.base import ExpertModule, blockwise
from boostnerf_cli.fields.dvgo import color_mlp, direction_encoding
from boostnerf_cli.fields.vm import VMGrid
from boostnerf_cli.fields.warmstart import fit_density
from boostnerf_cli.limits import (
    GRID_RES,
    LOSS_WEIGHT,
    MLP_LAYERS,
    MLP_WIDTH,
    NON_NEGATIVE,
    OPEN_UNIT,
    PE_FREQS,
    limit,
)


@dataclass
class TensoRFConfig:
    """Architecture of a TensoRF-style expert. `res`: the final lattice has res^3 voxels."""

    res: int = limit(128, GRID_RES)
    density_rank: int = limit(8, MLP_WIDTH)  # components per mode (TensoRF-VM uses 16)
    app_rank: int = limit(24, MLP_WIDTH)  # components per mode (TensoRF-VM uses 48)
    app_dim: int = limit(27, MLP_WIDTH)  # appearance feature after the basis matrix
    hidden: int = limit(128, MLP_WIDTH)  # width of the shading MLP
    layers: int = limit(2, MLP_LAYERS)  # hidden layers of the shading MLP
    view_pe: int = limit(2, PE_FREQS)  # frequencies of the view-direction encoding
    feat_pe: int = limit(2, PE_FREQS)  # frequencies of the appearance-feature encoding
    alpha_init: float = limit(1e-4, OPEN_UNIT)  # opacity over one unit where the density components are zero
    l1_weight: float = limit(8e-5, LOSS_WEIGHT)  # weight of the L1 density regularisation in the training loss
    fit_steps: int = limit(200, NON_NEGATIVE)  # Adam steps of the warm start from the coarse geometry


class TensoRFExpert(ExpertModule):
    """VM-factorised radiance field; satisfies the Field protocol and the Expert contract."""

    family = "tensorf"
    config_type = TensoRFConfig
    gate_grid = "tensorf"  # the paper's TensoRF mixture gates with a VM-factorised grid
    grows = True

    def __init__(self, cfg: TensoRFConfig, bbox: Tensor, unit: float | None = None,
                 shape: tuple[int, int, int] | None = None):
        super().__init__(cfg, bbox)
        final_shape = G.lattice_shape(self.bbox, cfg.res ** 3)
        self.unit = float(unit) if unit is not None else self.spacing(final_shape)
        shape = tuple(shape) if shape is not None else final_shape
        self.density_vm = VMGrid(shape, cfg.density_rank)
        self.app_vm = VMGrid(shape, cfg.app_rank)
        self.basis = nn.Linear(3 * cfg.app_rank, cfg.app_dim, bias=False)
        in_dim = cfg.app_dim * (1 + 2 * cfg.feat_pe) + 3 + 6 * cfg.view_pe
        self.rgbnet = color_mlp(in_dim, cfg.hidden, cfg.layers)

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.density_vm.shape

    @property
    def spatial_res(self) -> int:
        """Voxels per side of the final lattice (the density volume's default resolution)."""
        return self.cfg.res

    # --- the Field contract -------------------------------------------------------------------
    def raw_density(self, xyz: Tensor) -> Tensor:
        return self.density_vm(xyz, self.bbox).sum(-1)

    @blockwise
    def density(self, xyz: Tensor) -> Tensor:
        return F.softplus(self.raw_density(xyz) + self.shift) / self.unit * self.inside(xyz)

    @blockwise
    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        feat = self.basis(self.app_vm(xyz, self.bbox))
        h = torch.cat([direction_encoding(feat, self.cfg.feat_pe), direction_encoding(dirs, self.cfg.view_pe)], -1)
        return torch.sigmoid(self.rgbnet(h))

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        return self.density(xyz), self.color(xyz, dirs)

    def regularization(self) -> Tensor:
        """TensoRF's L1 sparsity term on the density planes and lines (already weighted)."""
        return self.cfg.l1_weight * self.density_vm.l1()

    # --- growth and persistence ---------------------------------------------------------------
    @torch.no_grad()
    def regrid(self, n_voxels: int) -> None:
        """Resample the planes and lines onto a lattice of about `n_voxels` voxels over the box."""
        new_shape = G.lattice_shape(self.bbox, n_voxels)
        self.density_vm.resample(new_shape)
        self.app_vm.resample(new_shape)

    def init_density(self, density) -> None:
        """Fit the density planes and lines to `density(xyz) -> sigma` (see fields/warmstart.py)."""
        fit_density(self, list(self.density_vm.parameters()), density)

    def resize_to(self, shape: tuple[int, int, int]) -> None:
        self.density_vm.resize_to(shape)
        self.app_vm.resize_to(shape)

    def param_groups(self, lr_grid: float, lr_mlp: float) -> list[dict]:
        return [
            {"params": list(self.density_vm.parameters()) + list(self.app_vm.parameters()), "lr": lr_grid},
            {"params": list(self.basis.parameters()) + list(self.rgbnet.parameters()), "lr": lr_mlp},
        ]

