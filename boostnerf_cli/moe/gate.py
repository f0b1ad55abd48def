"""Gates: a probability field G(x) over the M experts.

grid    (paper): G(x) = softmax(MLP(interp(V_G, x))), V_G a low-resolution dense feature grid,
        MLP with `layers` hidden ReLU layers of `hidden` units (2 x 64 in the paper)
linear  : softmax(W interp(V_G, x) + b)              (the paper's "linear" ablation)
switch  : softmax(MLP_4x128(PE(x)))                  (Switch-NeRF-style, no grid)
uniform : G(x)_i = 1/M                               (the ensemble; no parameters)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from boostnerf_cli.fields import grid as G

GATE_TYPES = ("grid", "linear", "switch", "uniform")


@dataclass
class GateConfig:
    kind: str = "grid"
    res: int = 32  # the gate grid has res^3 voxels over the box
    channels: int = 8
    hidden: int = 64
    layers: int = 2
    pe: int = 6  # positional-encoding frequencies of the switch gate


def positional_encoding(x: Tensor, n_freq: int) -> Tensor:
    freqs = 2.0 ** torch.arange(n_freq, device=x.device, dtype=x.dtype) * math.pi
    y = (x[:, None, :] * freqs[:, None]).reshape(x.shape[0], -1)
    return torch.cat([x, torch.sin(y), torch.cos(y)], dim=-1)


def _mlp(d_in: int, hidden: int, layers: int, d_out: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = d_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    last = nn.Linear(d, d_out)
    # Small random logits, not zeros: with exactly uniform probabilities top-k breaks every tie the
    # same way (experts 0..k-1), and the largest experts would never receive a sample to learn from.
    nn.init.normal_(last.weight, std=0.5 / math.sqrt(d))
    nn.init.zeros_(last.bias)
    mods.append(last)
    return nn.Sequential(*mods)


class Gate(nn.Module):
    """xyz (N, 3) -> logits (N, M); `probs` applies the softmax."""

    def __init__(self, cfg: GateConfig, n_experts: int, bbox: Tensor, shape: tuple[int, int, int] | None = None):
        super().__init__()
        if cfg.kind not in GATE_TYPES:
            raise ValueError(f"unknown gate type {cfg.kind!r}")
        self.cfg, self.m = cfg, n_experts
        self.register_buffer("bbox", bbox.detach().clone().float())
        self.shape = tuple(shape) if shape is not None else G.lattice_shape(self.bbox, cfg.res ** 3)
        self.table = None
        self.mlp = None
        if cfg.kind in ("grid", "linear"):
            self.table = nn.Parameter(torch.randn(math.prod(self.shape), cfg.channels))
            self.mlp = _mlp(cfg.channels, cfg.hidden, cfg.layers if cfg.kind == "grid" else 0, n_experts)
        elif cfg.kind == "switch":
            self.mlp = _mlp(3 + 6 * cfg.pe, 128, 4, n_experts)
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
        if self.cfg.kind == "uniform":
            return xyz.new_zeros(xyz.shape[0], self.m)
        if self.cfg.kind == "switch":
            rel = (xyz - self.bbox[0]) / (self.bbox[1] - self.bbox[0]) * 2 - 1
            return self.mlp(positional_encoding(rel, self.cfg.pe))
        idx, w = G.corners(xyz, self.bbox, self.shape)
        return self.mlp(G.lookup(self.table, idx, w))

    def probs(self, xyz: Tensor) -> Tensor:
        """Softmax in float32 even under autocast (reduced-precision logits are upcast first)."""
        logits = self.logits(xyz)
        if logits.dtype in (torch.float16, torch.bfloat16):
            logits = logits.float()
        return torch.softmax(logits, dim=-1)

    def config_dict(self) -> dict:
        return {"config": asdict(self.cfg), "shape": list(self.shape), "experts": self.m}
