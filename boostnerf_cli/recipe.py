"""Recipes: YAML -> typed, validated settings (safe_load, unknown keys rejected).

A recipe supplies defaults for every stage; command-line flags override them. Sections:
`data` (how the scene is loaded), `pretrain` (experts), `moe` (mixture build and finetuning).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from boostnerf_cli.errors import BoostNerfError


@dataclass
class DataRecipe:
    image_size: int | None = None  # longer side in pixels after area downscaling; None = native
    holdout_every: int = 8  # for datasets without a test split: every N-th train view is held out
    format: str = "auto"  # auto | blender | nsvf | tanks | llff | nerfstudio (docs/datasets.md)


@dataclass
class GeometryRecipe:
    """The shared coarse stage that finds the occupied box and the occupancy mask."""

    res: int = 32
    iters: int = 600
    batch_rays: int = 1024
    lr: float = 0.1
    alpha_init: float = 1e-4
    alpha_threshold: float = 1e-3  # per coarse step: cells below it are empty
    weight_entropy: float = 0.1  # pushes ray opacity to 0 or 1: clears floaters against the background


@dataclass
class TrainRecipe:
    batch_rays: int = 4096
    lr_grid: float = 0.1
    lr_mlp: float = 1e-3
    lr_decay: float = 0.1
    step_ratio: float = 0.5  # sampling step in voxels of the final grid
    color_threshold: float = 1e-4  # samples with a smaller weight skip the colour MLP
    weight_rgbper: float = 0.01
    weight_entropy: float = 1e-3
    growth: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3])  # fractions of iters; voxels x2 each
    occupancy_every: int = 500  # steps between occupancy refreshes (0 = never)
    occupancy_threshold: float = 1e-4  # alpha per step below which a cell is skipped
    log_every: int = 100
    checkpoint_every: int = 500


@dataclass
class PretrainRecipe:
    model: str = "dvgo"
    res: list[int] = field(default_factory=lambda: [64, 96, 128])
    iters: int = 3000
    seed: int = 0
    geometry: GeometryRecipe = field(default_factory=GeometryRecipe)
    train: TrainRecipe = field(default_factory=TrainRecipe)
    dvgo: dict = field(default_factory=dict)  # DVGOConfig fields other than res
    tensorf: dict = field(default_factory=dict)  # TensoRFConfig fields other than res
    ngp: dict = field(default_factory=dict)  # NGPConfig fields other than res (res = levels L)

    def family_config(self) -> dict:
        """The architecture settings of the chosen family (`dvgo`, `tensorf` or `ngp` section)."""
        return dict({"dvgo": self.dvgo, "tensorf": self.tensorf, "ngp": self.ngp}.get(self.model, {}))


def _finetune_train() -> TrainRecipe:
    """Finetuning continues from trained experts: lower learning rates, no growth."""
    return TrainRecipe(lr_grid=0.03, lr_mlp=5e-4, growth=[], occupancy_every=0)


@dataclass
class MoERecipe:
    gate_type: str = "grid"  # grid | linear | switch
    gate_grid: str = "auto"  # dense | tensorf | hash | auto (the experts' family: dvgo dense, tensorf VM, ngp hash)
    gate_res: int = 32  # the gate grid has gate_res^3 voxels (128 in the paper)
    gate_channels: int = 8
    gate_hidden: int = 64
    gate_layers: int = 2
    vd_res: int | None = None  # density volume V_D (vd_res^3 voxels); default: the smallest expert's res
    density_threshold: float = 1e-3  # T: samples whose V_D opacity over one step is below it are filtered
    step_from: str = "largest"  # render step of the mixture: the largest expert's (the paper: same step as the baseline) or the smallest's
    topk: int = 2
    lam: float = 1e-3
    penalty: str = "geometric"  # geometric | linear | quadratic | none
    renormalize: bool = True  # top-k weights sum to 1 (k = 1: straight-through 1); False: raw probabilities (docs/results.md)
    bake_res: int = 128  # rendering samples the trained gate's logits on a bake_res^3 lattice (0: run the gate MLP)
    iters: int = 1000
    lr_gate: float = 1e-2
    lr_gate_mlp: float = 1e-3
    seed: int = 0
    train: TrainRecipe = field(default_factory=_finetune_train)


@dataclass
class Recipe:
    data: DataRecipe = field(default_factory=DataRecipe)
    pretrain: PretrainRecipe = field(default_factory=PretrainRecipe)
    moe: MoERecipe = field(default_factory=MoERecipe)
    name: str = "defaults"


def _build(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, dict):
        raise BoostNerfError(f"recipe section {where or 'top level'} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise BoostNerfError(
            f"unknown recipe key {where + '.' if where else ''}{unknown[0]}: known keys here are {', '.join(sorted(fields))}"
        )
    kwargs = {}
    for key, value in data.items():
        path = f"{where + '.' if where else ''}{key}"
        if dataclasses.is_dataclass(hints[key]) and isinstance(value, dict):
            # A partial section overrides its own defaults (e.g. moe.train keeps finetuning's lower learning
            # rates when only batch_rays is given), not those of the section's class.
            default = fields[key].default_factory() if fields[key].default_factory is not dataclasses.MISSING else None
            built = _build(hints[key], value, path)
            kwargs[key] = built if default is None else dataclasses.replace(default, **{k: getattr(built, k) for k in value})
        else:
            kwargs[key] = _coerce(hints[key], value, path)
    return cls(**kwargs)


def _coerce(hint: Any, value: Any, where: str) -> Any:
    if dataclasses.is_dataclass(hint):
        return _build(hint, value, where)
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        hint = next(a for a in args if a is not type(None))
        origin = typing.get_origin(hint)
    if origin is list:
        (item,) = typing.get_args(hint)
        if not isinstance(value, list):
            raise BoostNerfError(f"recipe key {where} must be a list")
        return [_coerce(item, v, where) for v in value]
    if hint is dict:
        if not isinstance(value, dict):
            raise BoostNerfError(f"recipe key {where} must be a mapping")
        return value
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint in (int, float, str, bool) and not (isinstance(value, hint) and not (hint is int and isinstance(value, bool))):
        raise BoostNerfError(f"recipe key {where} must be {hint.__name__}, got {value!r}")
    return value


def load_recipe(path: Path | None) -> Recipe:
    """Parse and validate a YAML recipe (None -> built-in defaults)."""
    if path is None:
        return Recipe()
    path = Path(path)
    if not path.exists():
        raise BoostNerfError(f"recipe {path} does not exist (recipes ship in the recipes/ folder)")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise BoostNerfError(f"recipe {path} is not valid YAML: {str(e).splitlines()[0]}") from None
    recipe = _build(Recipe, data, "")
    if recipe.name == "defaults":
        recipe.name = path.stem
    return recipe


def recipe_dict(recipe: Recipe) -> dict:
    return dataclasses.asdict(recipe)


def recipe_from_dict(data: dict) -> Recipe:
    """A recipe recorded in a workspace manifest (validated like a YAML file)."""
    return _build(Recipe, data, "")
