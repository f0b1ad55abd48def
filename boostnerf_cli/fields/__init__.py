"""Fields: the Field protocol and the expert families, with one way to save and load them."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.base import Expert, Field
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.fields.ngp import NGPConfig, NGPExpert
from boostnerf_cli.fields.tensorf import TensoRFConfig, TensoRFExpert
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.workspace import MALFORMED, load_tensors, malformed, save_tensors

FAMILIES: dict[str, type] = {"dvgo": DVGOExpert, "tensorf": TensoRFExpert, "ngp": NGPExpert}
CONFIGS: dict[str, type] = {"dvgo": DVGOConfig, "tensorf": TensoRFConfig, "ngp": NGPConfig}

__all__ = ["CONFIGS", "FAMILIES", "Expert", "Field", "build_expert", "count_params", "load_expert", "save_expert"]


def build_expert(family: str, config: dict, bbox: torch.Tensor) -> nn.Module:
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


def save_expert(path: Path, model: nn.Module, occupancy: OccupancyGrid | None, extra_meta: dict | None = None) -> None:
    tensors = {k: v for k, v in model.state_dict().items()}
    if occupancy is not None:
        tensors["occupancy"] = occupancy.occupied.to(torch.uint8)
        tensors["occupancy_bbox"] = occupancy.bbox.clone()
    save_tensors(path, tensors, {**model.config_dict(), **(extra_meta or {})})


def load_expert(path: Path, device: str | torch.device = "cpu") -> tuple[nn.Module, OccupancyGrid | None, dict]:
    """-> (expert in eval mode, its occupancy grid or None, metadata)."""
    tensors, meta = load_tensors(path, device)
    family = meta.get("family")
    if not isinstance(family, str) or family not in FAMILIES:
        raise BoostNerfError(f"{path} holds an unknown model family {family!r}; was it written by a newer boostnerf?")
    try:
        occ = None
        if "occupancy" in tensors:
            occ = OccupancyGrid(tensors.pop("occupancy").bool(), tensors.pop("occupancy_bbox"))
        model = FAMILIES[family].from_config(meta, tensors["bbox"])
        model.load_state_dict(tensors)
    except MALFORMED as e:
        raise BoostNerfError(f"{path} does not hold a valid {family} expert ({malformed(e)}; written by another "
                             "boostnerf version?): delete it and rerun the stage that wrote it") from None
    return model.to(device).eval(), occ, meta
