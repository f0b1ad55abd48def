"""The expert families by name. A new family is one module in `fields/` (a config dataclass and a subclass of
`fields/base.py: ExpertModule` meeting the Expert contract) plus its class in the `FAMILIES` line below: the recipe
section `pretrain.<family>`, `--model <family>`, saving, loading and mixtures follow from it."""

from __future__ import annotations

import torch
from torch import nn

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.dvgo import DVGOExpert
from boostnerf_cli.fields.ngp import NGPExpert
from boostnerf_cli.fields.tensorf import TensoRFExpert

FAMILIES: dict[str, type] = {cls.family: cls for cls in (DVGOExpert, TensoRFExpert, NGPExpert)}
CONFIGS: dict[str, type] = {name: cls.config_type for name, cls in FAMILIES.items()}


def build_expert(family: str, config: dict, bbox: torch.Tensor) -> nn.Module:
    """A new, untrained expert of `family` with the options `config` over the box `bbox` (2, 3)."""
    if family not in FAMILIES:
        raise BoostNerfError(f"unknown model family {family!r}: choose one of {', '.join(sorted(FAMILIES))}")
    cfg_type = CONFIGS[family]
    known = set(cfg_type.__dataclass_fields__)
    unknown = set(config) - known
    if unknown:
        raise BoostNerfError(f"unknown {family} setting(s) {sorted(unknown)}: known are {sorted(known)}")
    return FAMILIES[family](cfg_type(**config), bbox)


def count_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
