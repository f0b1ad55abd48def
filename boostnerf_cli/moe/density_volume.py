"""The density volume V_D: a frozen dense density grid that filters samples before the gate.

sigma_D(x) = softplus(interp(V_D, x) + shift) / unit (the paper's Eq. 3); samples whose opacity over
one render step, 1 - exp(-sigma_D * step), is below the threshold T are dropped. V_D is initialised
from the smallest expert, whatever its family, by sampling its density at the lattice vertices.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from boostnerf_cli.fields import grid as G
from boostnerf_cli.fields.dvgo import raw_from_sigma


class DensityVolume(nn.Module):
    def __init__(self, bbox: Tensor, res: int, shape: tuple[int, int, int] | None = None, unit: float | None = None):
        super().__init__()
        self.register_buffer("bbox", bbox.detach().clone().float())
        self.res = res
        self.shape = tuple(shape) if shape is not None else G.lattice_shape(self.bbox, res ** 3)
        size = self.bbox[1] - self.bbox[0]
        self.unit = float(unit) if unit is not None else float((size / (torch.tensor(self.shape) - 1).to(size)).mean())
        self.shift = math.log(1.0 / (1.0 - 1e-2) - 1.0)
        self.register_buffer("table", torch.zeros(math.prod(self.shape), 1))

    def inside(self, xyz: Tensor) -> Tensor:
        """(N, 3) -> (N,) bool: in the box, faces included (outside it V_D is empty)."""
        return G.inside_box(xyz, self.bbox)

    def density(self, xyz: Tensor) -> Tensor:
        return F.softplus(G.blend(self.table, xyz, self.bbox, self.shape)[:, 0] + self.shift) / self.unit * \
            self.inside(xyz)

    @torch.no_grad()
    def init_from(self, density) -> None:
        """Fit the grid to `density(xyz) -> sigma` at the lattice vertices (exact there)."""
        pts = G.lattice_points(self.bbox, self.shape)
        sigma = torch.cat([density(pts[i : i + (1 << 18)]) for i in range(0, pts.shape[0], 1 << 18)])
        self.table.copy_(raw_from_sigma(sigma, self.unit, self.shift)[:, None])

    def config_dict(self) -> dict:
        return {"res": self.res, "shape": list(self.shape), "unit": self.unit}

    @classmethod
    def from_config(cls, meta: dict, bbox: Tensor) -> "DensityVolume":
        return cls(bbox, meta["res"], tuple(meta["shape"]), meta["unit"])
