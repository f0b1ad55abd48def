"""Small in-process builders that more than one test file uses (the CLI helpers live in conftest.py)."""

from __future__ import annotations

import torch

from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.fields.ngp import NGPConfig, NGPExpert
from boostnerf_cli.fields.tensorf import TensoRFConfig, TensoRFExpert
from boostnerf_cli.metrics import ALEXNET_ENV, LPIPS_ENV, LPIPSModel
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.train import RayData

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
    gate = Gate(GateConfig(gate_type=kind, gate_res=4, gate_channels=4, gate_hidden=8, gate_layers=2), m, TOY_BOX)
    with torch.no_grad():
        for p in gate.parameters():
            p.normal_(0, 0.5)
    vd = DensityVolume(TOY_BOX, 6)
    vd.init_from(experts[0].density)
    return Mixture(experts, gate, vd, None, MixtureConfig(topk=k, renormalize=renormalize, step=0.05,
                                                          expert_names=[f"e{i}" for i in range(m)]))


def torchvision_alexnet_layout(model: LPIPSModel) -> dict[str, torch.Tensor]:
    """Backbone weights named as torchvision's alexnet state dict, with a (shrunk) classifier.

    The real file also holds classifier.{1,4,6}.* ((4096, 9216) ...), which the loader ignores;
    small stand-ins keep the test fast.
    """
    sd = {k: v.clone() for k, v in model.state_dict().items() if k.startswith("features.")}
    sd["classifier.1.weight"] = torch.zeros(4, 9)
    sd["classifier.1.bias"] = torch.zeros(4)
    return sd


def lpips_head_layout(model: LPIPSModel) -> dict[str, torch.Tensor]:
    """Head weights named as in lpips/weights/v0.1/alex.pth (`lin{k}.model.1.weight`)."""
    return {f"lin{k}.model.1.weight": h.weight.detach().clone() for k, h in enumerate(model.heads)}


def write_lpips_weights(folder, seed: int = 0) -> dict[str, str]:
    """A random LPIPS model's weights written in the two reference layouts under `folder` (the AlexNet backbone as
    torchvision saves it, the heads as the lpips package ships them) -> the environment that points boostnerf at
    them. The distances are not LPIPS's, but every line of the LPIPS branch runs."""
    model = LPIPSModel.random(seed=seed)
    backbone, heads = folder / "alexnet-owt-7be5be79.pth", folder / "alex.pth"
    torch.save(torchvision_alexnet_layout(model), backbone)
    torch.save(lpips_head_layout(model), heads)
    return {ALEXNET_ENV: str(backbone), LPIPS_ENV: str(heads)}


def family_expert(family: str, res: int = 8):
    """A small untrained expert of `family` (dvgo, tensorf, ngp) in `TOY_BOX`, seed 0."""
    torch.manual_seed(0)
    if family == "dvgo":
        return DVGOExpert(DVGOConfig(res=res, hidden=8, layers=1), TOY_BOX)
    if family == "tensorf":
        return TensoRFExpert(TensoRFConfig(res=res, hidden=8, layers=1, density_rank=2, app_rank=2, app_dim=4), TOY_BOX)
    return NGPExpert(NGPConfig(res=2, log2_table=8, base_res=2, max_res=8, grid_res=8, hidden=8, color_hidden=8,
                               color_layers=1, fit_steps=0), TOY_BOX)


def toward_box_rays(n: int = 128) -> RayData:
    """`n` training rays from around (0, 0, 3) toward the middle of `TOY_BOX`, with random colours (seed 1)."""
    g = torch.Generator().manual_seed(1)
    origins = torch.tensor([0.0, 0.0, 3.0]) + 0.3 * torch.randn(n, 3, generator=g)
    target = 0.5 * (torch.rand(n, 3, generator=g) - 0.5)
    dirs = torch.nn.functional.normalize(target - origins, dim=-1)
    return RayData(origins, dirs, torch.rand(n, 3, generator=g))


def routed_mixture(kind: str, device: torch.device | str) -> Mixture:
    """A mixture of three `family_expert` DVGO experts (res 6, 8, 10) as `kind` (top1, top2, ens), with a full
    occupancy grid and a dense density volume, on `device`."""
    experts = [family_expert("dvgo", r) for r in (6, 8, 10)]
    gate = Gate(GateConfig(gate_type="grid", gate_res=4, gate_channels=4, gate_hidden=8, gate_layers=1), 3, TOY_BOX)
    vd = DensityVolume(TOY_BOX, 6)
    with torch.no_grad():
        vd.table.fill_(2.0)
    k = {"top1": 1, "top2": 2, "ens": 3}[kind]
    mix = Mixture(experts, gate, vd, OccupancyGrid(torch.ones(6, 6, 6, dtype=torch.bool), TOY_BOX),
                  MixtureConfig(topk=k, step=0.1, expert_names=["a", "b", "c"]))
    if kind == "ens":
        mix.make_ensemble()
    mix = mix.to(device)
    mix.occupancy = mix.occupancy.to(device)
    return mix


def budgets_hold_every_sample(monkeypatch) -> None:
    """On a simulated GPU: every static packing budget grows, before it packs, to hold every sample its filter keeps,
    so a GPU run takes every step a CPU run takes and must give its numbers; it packs through the GPU's static code
    path, into slots sized as the GPU sizes them (`Budget.fit`: a margin over the count)."""
    from boostnerf_cli.render import packing

    pack = packing.Budget.pack

    def pack_all(self, mask):
        self.size = max(self.size or 0, self.fit(int(mask.sum())))
        return pack(self, mask)

    monkeypatch.setattr(packing.Budget, "pack", pack_all)
