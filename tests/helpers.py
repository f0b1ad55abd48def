"""Small in-process builders that more than one test file uses (the CLI helpers live in conftest.py)."""

from __future__ import annotations

import torch

from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig

TOY_BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def toy_experts(m: int, seed: int = 0) -> list[DVGOExpert]:
    """`m` small DVGO experts in `TOY_BOX` (res 6, 8, 10, ...) with random weights from `seed`."""
    torch.manual_seed(seed)
    out = []
    for i in range(m):
        e = DVGOExpert(DVGOConfig(res=6 + 2 * i, hidden=8, layers=1), TOY_BOX)
        with torch.no_grad():
            e.density_table.normal_(0, 2)
            e.feature_table.normal_()
            for p in e.rgbnet.parameters():
                p.normal_(0, 0.3)
        out.append(e)
    return out


def toy_mixture(m: int = 3, k: int = 2, kind: str = "grid", renormalize: bool = True, seed: int = 0) -> Mixture:
    """A top-`k` mixture of `toy_experts(m, seed)` with a random `kind` gate; its density volume is fitted
    to the first expert. Deterministic for a given seed."""
    experts = toy_experts(m, seed)
    gate = Gate(GateConfig(kind=kind, res=4, channels=4, hidden=8, layers=2), m, TOY_BOX)
    with torch.no_grad():
        for p in gate.parameters():
            p.normal_(0, 0.5)
    vd = DensityVolume(TOY_BOX, 6)
    vd.init_from(experts[0].density)
    return Mixture(experts, gate, vd, None, MixtureConfig(topk=k, renormalize=renormalize, step=0.05,
                                                          expert_names=[f"e{i}" for i in range(m)]))
