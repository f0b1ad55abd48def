"""Gates: a probability field G(x) over the M experts.

grid    (paper): G(x) = softmax(MLP(interp(V_G, x))), V_G a low-resolution feature grid,
        MLP with `layers` hidden ReLU layers of `hidden` units (2 x 64 in the paper)
linear  : softmax(W interp(V_G, x) + b)              (the paper's "linear" ablation)
The feature grid V_G follows the experts' family, as in the paper (`grid`):
  dense   a res^3 lattice of `channels` features (DVGO)
  tensorf a VM-factorised res^3 lattice, `channels` components per mode -> 3 x channels (TensoRF)
  hash    a small multi-resolution hash grid: `levels` levels (6 in the paper) from res/8 to res
          cells, 2 features each, tables of at most 2^`log2_table` rows (Instant-NGP)
switch  : softmax(MLP_4x128(PE(x)))                  (Switch-NeRF-style, no grid)
uniform : G(x)_i = 1/M                               (the ensemble; no parameters)
The dense feature grid starts random (unit-scale features), or, `init` expert, as a copy of a pretrained
expert's feature grid (`init_grid_from`; the official code copies its lowest-resolution model's, see
build_moe.gate_source).
baked   : softmax(interp(L, x)), L the logits of a trained gate sampled at the vertices of a
          `res`^3 lattice (`Gate.baked`): what rendering uses, so the gate MLP does not run on
          every sample of every image (its error is measured in docs/results.md)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from boostnerf_cli.fields import grid as G
from boostnerf_cli.fields.hashgrid import HashEncoding
from boostnerf_cli.fields.mlp import MLP
from boostnerf_cli.fields.vm import VMGrid

GATE_TYPES = ("grid", "linear", "switch", "uniform", "baked")
TRAINABLE_GATES = ("grid", "linear", "switch")  # what build-moe makes (uniform: the ensemble; baked: for rendering)
GATE_GRIDS = ("dense", "tensorf", "hash")


# A gate's settings as a gate file records them before they took the recipe's names (`GateConfig.saved`).
_FORMER_NAMES = {"kind": "gate_type", "res": "gate_res", "channels": "gate_channels", "hidden": "gate_hidden",
                 "layers": "gate_layers", "grid": "gate_grid", "init": "gate_init"}


@dataclass
class GateConfig:
    """What a gate is. The fields named `gate_*` are the recipe's `moe.gate_*` keys, as build-moe resolved them (the
    recipe declares them, with their ranges and choices: `recipe.MoERecipe`); a gate may also be of a kind no recipe
    chooses (uniform: the ensemble's; baked: logits sampled on a lattice)."""

    gate_type: str = "grid"
    gate_res: int = 32  # the gate grid has gate_res^3 voxels over the box
    gate_channels: int = 8
    gate_hidden: int = 64
    gate_layers: int = 2
    pe: int = 6  # positional-encoding frequencies of the switch gate
    gate_grid: str = "dense"  # the feature grid of grid / linear gates: dense | tensorf | hash
    levels: int = 6  # hash grid levels
    log2_table: int = 15  # hash grid: at most 2^log2_table rows per level
    # the dense feature grid's start: random | expert (copied from an expert, `init_grid_from`)
    gate_init: str = "random"

    @staticmethod
    def saved(config: dict) -> "GateConfig":
        """The config a gate file records (under the former names `kind`, `res`, ... in files written before)."""
        return GateConfig(**{_FORMER_NAMES.get(key, key): value for key, value in config.items()})


def softmax(logits: Tensor) -> Tensor:
    """Softmax over the last (expert) dimension, in float32 even under autocast (reduced-precision
    logits are upcast first)."""
    if logits.dtype in (torch.float16, torch.bfloat16):
        logits = logits.float()
    # Over dim 0 of the (M, N) transpose: the same softmax, but CPU kernels vectorise along a reduced
    # dimension of a few experts badly (13k x 3: 1.7 against 0.6 ms forward and backward, one thread).
    return torch.softmax(logits.T, dim=0).T


def positional_encoding(x: Tensor, n_freq: int) -> Tensor:
    freqs = 2.0 ** torch.arange(n_freq, device=x.device, dtype=x.dtype) * math.pi
    y = (x[:, None, :] * freqs[:, None]).reshape(x.shape[0], -1)
    return torch.cat([x, torch.sin(y), torch.cos(y)], dim=-1)


def _mlp(d_in: int, hidden: int, layers: int, d_out: int) -> MLP:
    mlp = MLP([d_in] + [hidden] * layers + [d_out])
    last = mlp[-1]
    # Small random logits, not zeros: with exactly uniform probabilities top-k breaks every tie the
    # same way (experts 0..k-1), and the largest experts would never receive a sample to learn from.
    nn.init.normal_(last.weight, std=0.5 / math.sqrt(last.in_features))
    nn.init.zeros_(last.bias)
    return mlp


class Gate(nn.Module):
    """xyz (N, 3) -> logits (N, M); `probs` applies the softmax.

    Built on the CPU whatever `bbox`'s device, like any `nn.Module`: move it with `.to(device)`.
    """

    def __init__(self, cfg: GateConfig, n_experts: int, bbox: Tensor, shape: tuple[int, int, int] | None = None):
        super().__init__()
        if cfg.gate_type not in GATE_TYPES:
            raise ValueError(f"unknown gate type {cfg.gate_type!r}")
        if cfg.gate_grid not in GATE_GRIDS:
            raise ValueError(f"unknown gate grid {cfg.gate_grid!r}")
        self.cfg, self.m = cfg, n_experts
        self.register_buffer("bbox", bbox.detach().float().cpu().clone())
        self.shape = tuple(shape) if shape is not None else G.lattice_shape(self.bbox, cfg.gate_res ** 3)
        self.table = None
        self.vm = None
        self.hash = None
        self.mlp = None
        if cfg.gate_type in ("grid", "linear"):
            # unit-scale random features: the initial routing varies over space (see _center_logits)
            if cfg.gate_grid == "dense":
                self.table = nn.Parameter(torch.randn(math.prod(self.shape), cfg.gate_channels))
                d_feat = cfg.gate_channels
            elif cfg.gate_grid == "tensorf":
                self.vm = VMGrid(self.shape, cfg.gate_channels, init_std=1.0)
                d_feat = self.vm.out_dim
            else:
                self.hash = HashEncoding(self.bbox, cfg.levels, cfg.log2_table, 2, max(2, cfg.gate_res // 8),
                                         cfg.gate_res, init_std=1.0)
                d_feat = self.hash.out_dim
            self.mlp = _mlp(d_feat, cfg.gate_hidden, cfg.gate_layers if cfg.gate_type == "grid" else 0, n_experts)
        elif cfg.gate_type == "switch":
            self.mlp = _mlp(3 + 6 * cfg.pe, 128, 4, n_experts)
        elif cfg.gate_type == "baked":
            self.register_buffer("logit_table", torch.zeros(math.prod(self.shape), n_experts))
        if self.mlp is not None:
            self._center_logits()

    @torch.no_grad()
    def _center_logits(self, n: int = 4096) -> None:
        """Start with logits of mean 0 over the box: balanced, spatially varied initial routing
        (an uncentred ReLU MLP would route almost every point to the same experts)."""
        g = torch.Generator().manual_seed(0)
        xyz = self.bbox[0] + torch.rand(n, 3, generator=g).to(self.bbox) * (self.bbox[1] - self.bbox[0])
        self.mlp[-1].bias -= self.logits(xyz).mean(0)

    def logits(self, xyz: Tensor) -> Tensor:
        if self.cfg.gate_type == "uniform":
            return xyz.new_zeros(xyz.shape[0], self.m)
        if self.cfg.gate_type == "switch":
            rel = (xyz - self.bbox[0]) / (self.bbox[1] - self.bbox[0]) * 2 - 1
            return self.mlp(positional_encoding(rel, self.cfg.pe))
        if self.vm is not None:
            return self.mlp(self.vm(xyz, self.bbox))
        if self.hash is not None:
            return self.mlp(self.hash(xyz))
        idx, w = G.corners(xyz, self.bbox, self.shape)
        if self.cfg.gate_type == "baked":
            return G.lookup(self.logit_table, idx, w)
        return self.mlp(G.lookup(self.table, idx, w))

    @torch.no_grad()
    def init_grid_from(self, table: Tensor, shape: tuple[int, int, int], bbox: Tensor) -> None:
        """Start the dense feature grid from another dense grid: `table` (prod(shape), C) over `bbox`, C = the
        gate's channels. The same lattice (shape and box): an exact copy of `table`; another lattice: `table`
        resampled trilinearly at the gate's lattice vertices (`grid.resample`). The logits are centred again."""
        if self.table is None:
            raise ValueError("only a grid or linear gate with a dense feature grid starts from another grid")
        if table.shape != (math.prod(shape), self.table.shape[1]):
            raise ValueError(f"a table of {tuple(table.shape)} does not fit a {shape} lattice of "
                             f"{self.table.shape[1]} channels")
        src, box = table.detach().to(self.table), bbox.detach().to(self.bbox)
        same = tuple(shape) == self.shape and torch.equal(box, self.bbox)
        self.table.copy_(src if same else G.resample(src, tuple(shape), box, self.shape, self.bbox))
        self._center_logits()

    def grid_parameters(self) -> list[Tensor]:
        """The feature grid's parameters (trained at the gate's grid learning rate)."""
        if self.table is not None:
            return [self.table]
        if self.vm is not None:
            return list(self.vm.parameters())
        if self.hash is not None:
            return [self.hash.table]
        return []

    def probs(self, xyz: Tensor) -> Tensor:
        return softmax(self.logits(xyz))

    @torch.no_grad()
    def baked(self, res: int) -> "Gate":
        """A frozen copy whose logits are this gate's, sampled at the vertices of a res^3 lattice and
        interpolated trilinearly: one M-channel lookup per sample instead of the grid + MLP."""
        if self.cfg.gate_type in ("uniform", "baked"):
            return self
        out = Gate(GateConfig(gate_type="baked", gate_res=res, gate_channels=self.m, gate_hidden=0, gate_layers=0),
                   self.m, self.bbox)
        out = out.to(self.bbox.device)  # sampled where this gate lives
        pts = G.lattice_points(out.bbox, out.shape)
        out.logit_table.copy_(torch.cat([self.logits(pts[i : i + (1 << 16)]) for i in range(0, pts.shape[0], 1 << 16)]))
        return out.eval()

    def config_dict(self) -> dict:
        return {"config": asdict(self.cfg), "shape": list(self.shape), "experts": self.m}
