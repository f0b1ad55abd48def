"""Recipes: YAML -> typed, validated settings (safe_load, unknown keys rejected).

A recipe supplies defaults for every stage; command-line flags override them. Sections:
`data` (how the scene is loaded), `pretrain` (experts), `moe` (mixture build and finetuning).
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import CONFIGS, FAMILIES
from boostnerf_cli.limits import (
    BBOX_COORD,
    GRID_RES,
    LEARNING_RATE,
    LOSS_WEIGHT,
    MAX_GRID_RES,
    MLP_LAYERS,
    MLP_WIDTH,
    NON_NEGATIVE,
    OPEN_UNIT,
    STEP_RATIO,
    THRESHOLD,
    OneOf,
    Range,
    at_least,
    limit,
    rule_of,
)
from boostnerf_cli.moe.gate import GATE_GRIDS, TRAINABLE_GATES
from boostnerf_cli.moe.mixture import DENSITY_THRESHOLD, Routing
from boostnerf_cli.render.renderer import COLOR_THRESHOLD
from boostnerf_cli.scenes import FORMATS

# Seeds feed numpy's generator (the procedural scene: no negative seeds) and torch's (64 bits, seed + res).
SEED = Range(0, 2**63 - 1)


@dataclass
class DataRecipe:
    image_size: int | None = limit(None, at_least(8))  # longer side in pixels after area downscaling; None = native
    # datasets without a test split: every N-th train view is held out
    holdout_every: int = limit(8, Range(2, also=(0,)))
    # the dataset layout (docs/datasets.md); auto: told by the files the folder holds
    format: str = limit("auto", OneOf(("auto", *FORMATS)))
    # the scene box [xmin, ymin, zmin, xmax, ymax, zmax] in world units, instead of the one the loader gives (bbox.txt,
    # or the region most cameras see): for content that reaches past it (docs/datasets.md, "The scene box")
    bbox: list[float] | None = limit(None, BBOX_COORD)
    # what the scene's space is (docs/datasets.md, "Scene kinds"): bounded (one box), unbounded (a 360-degree capture
    # with its background: space contracted into one ball), forward (LLFF, in NDC); auto: told by the layout and cameras
    scene: str = limit("auto", OneOf(("auto", "bounded", "unbounded", "forward")))


@dataclass
class GeometryRecipe:
    """The shared coarse stage that finds the occupied box and the occupancy mask."""

    res: int = limit(32, GRID_RES)  # the coarse grid has about res^3 voxels over the scene box
    iters: int = limit(600, at_least(1))  # training steps of the coarse grid
    batch_rays: int = limit(1024, at_least(1))  # rays per step
    lr: float = limit(0.1, LEARNING_RATE)  # learning rate of the coarse density grid
    alpha_init: float = limit(1e-4, OPEN_UNIT)  # opacity over one voxel of the coarse grid before training
    alpha_threshold: float = limit(1e-3, THRESHOLD)  # per coarse step: cells below it are empty
    # pushes ray opacity to 0 or 1: clears floaters against the background
    weight_entropy: float = limit(0.1, LOSS_WEIGHT)
    cover_foreground: bool = True  # grow the mask until every foreground training ray crosses it (render/coverage.py)
    hull_box: bool = True  # with cover_foreground: only occupied cells in the views' visual hull count as surface
    refine: bool = True  # with cover_foreground: a second coarse grid trains inside the box the first found (if < half)


@dataclass
class TrainRecipe:
    batch_rays: int = limit(4096, at_least(1))  # rays per step
    lr_grid: float = limit(0.1, LEARNING_RATE)  # learning rate of the grids (hash tables, VM factors)
    lr_mlp: float = limit(1e-3, LEARNING_RATE)  # learning rate of the MLPs
    lr_decay: float = limit(0.1, Range(0, 1, lo_open=True))  # learning rates fall to this fraction at the last step
    # sampling step in voxels of the final grid (pretrain only: finetuning samples at the experts' step, moe.step_from)
    step_ratio: float = limit(0.5, STEP_RATIO)
    color_threshold: float = limit(COLOR_THRESHOLD, THRESHOLD)  # samples with a smaller weight skip the colour MLP
    # weight of the per-sample colour loss (each sample's colour
    # against the pixel, by its rendering weight; DVGO's rgbper)
    weight_rgbper: float = limit(0.01, LOSS_WEIGHT)
    # weight of the ray-opacity entropy loss, which pushes each ray to fully opaque or empty
    weight_entropy: float = limit(1e-3, LOSS_WEIGHT)
    # weight of mip-NeRF 360's distortion loss (render/volrend.py: distortion), which gathers each ray's weight into
    # one short stretch (fewer floaters; DVGOv2 and nerfacto use it on unbounded scenes); 0: off
    weight_distortion: float = limit(0.0, LOSS_WEIGHT)
    # progressive growth (pretrain only; DVGO and TensoRF grids, not Instant-NGP hash grids, which keep their
    # size): the grid starts at 1/2^n of its voxels and doubles them at each of these n fractions of iters
    growth: list[float] = limit(rule=OPEN_UNIT, factory=lambda: [0.1, 0.2, 0.3])
    # steps between refreshes of the occupancy mask from the density (0 = never;
    # while finetuning only the baseline has one, the mixtures skip by V_D)
    occupancy_every: int = limit(500, NON_NEGATIVE)
    occupancy_threshold: float = limit(1e-4, THRESHOLD)  # alpha per step below which a cell is skipped
    # composite each training ray on a random colour, not the scene's background (for captures whose every pixel is
    # opaque, LLFF: empty space can then fake no colour; docs/datasets.md)
    random_background: bool = False
    log_every: int = limit(100, at_least(1))  # steps between log lines (and entries of the report's history)
    # steps between training checkpoints (an interrupted run resumes from the last)
    checkpoint_every: int = limit(500, at_least(1))
    # torch.compile the step's loss and its gradient into fused kernels: auto = on a GPU (where the step then neither
    # waits for the device nor launches kernel by kernel), off on a CPU (a compile takes minutes there)
    compile: str = limit("auto", OneOf(("auto", "on", "off")))


def family_sections(cls: type) -> type:
    """Give the pretrain recipe one `dict` section per registered expert family (`fields/registry.py`), so that a
    new family needs no line here. Applied before `@dataclass`, so the sections are ordinary fields, last."""
    for name in FAMILIES:
        cls.__annotations__[name] = "dict"
        setattr(cls, name, field(default_factory=dict))
    return cls


@dataclass
@family_sections
class PretrainRecipe:
    # the experts' family (its architecture: the section of that name)
    model: str = limit("dvgo", OneOf(tuple(FAMILIES)))
    # one expert per value: its grid has res^3 voxels (ngp: res levels)
    res: list[int] = limit(rule=GRID_RES, factory=lambda: [64, 96, 128], min_items=1)
    iters: int = limit(3000, at_least(1))  # training steps of each expert
    seed: int = limit(0, SEED)  # expert at res trains with seed + res (also the procedural scene's seed)
    skip: bool = True  # False (--no-skip): experts train on the whole scene box, no occupancy mask
    geometry: GeometryRecipe = field(default_factory=GeometryRecipe)
    train: TrainRecipe = field(default_factory=TrainRecipe)
    # then one section per expert family (`family_sections`): dvgo, tensorf, ngp, each a mapping of its config's
    # fields other than res (for ngp, res is the number of levels L), a value or one per resolution

    def family_config(self) -> dict:
        """The architecture settings of the chosen family (its section, e.g. `pretrain.dvgo`)."""
        return dict(getattr(self, self.model, {}))


def unused_family_note(pre: PretrainRecipe) -> str | None:
    """A note when the recipe sets another family's architecture but none for the chosen one (a dvgo recipe run with
    `pretrain --model ngp`): those settings do not carry over, and the experts take their family's defaults."""
    others = [name for name in FAMILIES if name != pre.model and getattr(pre, name)]
    if not others or pre.family_config():
        return None
    sections = " and ".join(f"pretrain.{name}" for name in others)
    return (f"note: the experts are {pre.model} and the recipe has no pretrain.{pre.model} section, so they take "
            f"{pre.model}'s default architecture; its {sections} settings apply only to that family")


def _finetune_train() -> TrainRecipe:
    """Finetuning continues from trained experts: lower learning rates, no growth."""
    return TrainRecipe(lr_grid=0.03, lr_mlp=5e-4, growth=[], occupancy_every=0)


@dataclass
class MoERecipe(Routing):
    """The `moe` section: the mixture's routing (`moe/mixture.py: Routing`, whose keys it holds), its gate and
    density volume (build-moe), and the joint training (finetune)."""

    # grid: softmax(MLP(grid features)) (paper); linear: softmax of a linear map of them
    # (the paper's ablation); switch: an MLP on encoded positions, no grid (Switch-NeRF)
    gate_type: str = limit("grid", OneOf(TRAINABLE_GATES))
    # dense | tensorf | hash | auto (the experts' family: dvgo dense, tensorf VM, ngp hash)
    gate_grid: str = limit("auto", OneOf(("auto", *GATE_GRIDS)))
    gate_res: int = limit(32, Range(2, MAX_GRID_RES))  # the gate grid has gate_res^3 voxels (128 in the paper)
    gate_channels: int = limit(8, Range(1, 512))  # features per vertex of the gate's grid
    gate_hidden: int = limit(64, MLP_WIDTH)  # width of the gate's MLP
    gate_layers: int = limit(2, MLP_LAYERS)  # hidden layers of the gate's MLP (0: a linear map to the M logits)
    # the gate's dense feature grid: random, or expert: the smallest (dvgo) expert's feature grid, copied
    # (same lattice) or resampled trilinearly, gate_channels then = its channels (the official code's)
    gate_init: str = limit("random", OneOf(("random", "expert")))
    # with gate_init expert: the expert whose feature grid the gate copies, by name, in the mixture or not (the
    # official code copies a 128^3 model it leaves out of the mixture); empty: the mixture's smallest expert
    gate_from: str = ""
    # density volume V_D (vd_res^3 voxels); default: the smallest expert's res
    vd_res: int | None = limit(None, GRID_RES)
    # T: samples whose V_D opacity over one step is below it are filtered
    density_threshold: float = limit(DENSITY_THRESHOLD, THRESHOLD)
    # render step of the mixture: the largest expert's (the paper: same step as the baseline) or the smallest's
    step_from: str = limit("largest", OneOf(("smallest", "largest")))
    # lambda: weight of the resolution-weighted auxiliary loss (L_tot = L_nerf + lambda L_rw-aux; the paper uses 1e-3)
    lam: float = limit(1e-3, LOSS_WEIGHT)
    iters: int = limit(1000, at_least(1))  # joint training steps of each mixture, the ensemble and the baseline
    lr_gate: float = limit(1e-2, LEARNING_RATE)  # learning rate of the gate's grid
    lr_gate_mlp: float = limit(1e-3, LEARNING_RATE)  # learning rate of the gate's MLP
    seed: int = limit(0, SEED)  # the gate's initialisation (build-moe) and the finetuning batches
    train: TrainRecipe = field(default_factory=_finetune_train)


@dataclass
class Recipe:
    data: DataRecipe = field(default_factory=DataRecipe)
    pretrain: PretrainRecipe = field(default_factory=PretrainRecipe)
    moe: MoERecipe = field(default_factory=MoERecipe)
    name: str = "defaults"  # the recipe's name in reports (a recipe file without one: its file name)

    def override(self, changes: dict[str, Any]) -> "Recipe":
        """Set the keys `changes` names by their dotted path (`"pretrain.iters"`, `"pretrain.dvgo.hidden"`) to its
        values, then check the recipe again (`check_recipe`, errors naming the setting). -> self."""
        for path, value in changes.items():
            *sections, key = path.split(".")
            target = self
            for name in sections:
                target = getattr(target, name)
            if isinstance(target, dict):  # a family section: its keys are checked with the recipe
                target[key] = value
            elif not hasattr(target, key):
                raise BoostNerfError(f"no recipe key {path}")
            else:
                setattr(target, key, value)
        return check_recipe(self, "setting")


def parse_setting(text: str) -> tuple[str, Any]:
    """`KEY=VALUE` (`--set pretrain.geometry.iters=300`) -> (key, value): the value read as a recipe file's YAML reads
    it, the key and the value's type checked as a recipe file's are (its range: with the recipe, `check_recipe`)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key or "" in key.split("."):
        raise BoostNerfError(f"--set {text!r}: give KEY=VALUE, a recipe key and its value, e.g. "
                             "--set pretrain.geometry.iters=300 (docs/recipe-keys.md)")
    try:
        value = yaml.load(raw, Loader=_RecipeLoader)  # noqa: S506 (a safe loader)
    except (yaml.YAMLError, ValueError) as e:
        raise BoostNerfError(f"--set {key}: {raw!r} is not a YAML value ({str(e).splitlines()[0]})") from None
    nested: Any = value
    for name in reversed(key.split(".")):
        nested = {name: nested}
    built: Any = _build(Recipe, nested, "")  # unknown keys and wrong types refused as in a recipe file
    _check_unused(built)  # and a key finetuning does not use (moe.train.step_ratio, growth)
    for name in key.split("."):
        built = built[name] if isinstance(built, dict) else getattr(built, name)
    return key, built


def _key_text(key: Any) -> str:
    """A YAML key as an error message shows it: as written, or its repr when that would break the line ("\\n")."""
    return key if isinstance(key, str) and key.isprintable() else repr(key)


def _build(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, dict):
        raise BoostNerfError(f"recipe section {where or 'top level'} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted((k for k in data if k not in fields), key=str)
    if unknown:
        raise BoostNerfError(f"unknown recipe key {where + '.' if where else ''}{_key_text(unknown[0])}: known keys "
                             f"here are {', '.join(sorted(fields))}")
    kwargs = {}
    for key, value in data.items():
        path = f"{where + '.' if where else ''}{key}"
        if dataclasses.is_dataclass(hints[key]) and isinstance(value, dict):
            # A partial section overrides its own defaults (e.g. moe.train keeps finetuning's lower learning
            # rates when only batch_rays is given), not those of the section's class.
            default = fields[key].default_factory() if fields[key].default_factory is not dataclasses.MISSING else None
            built = _build(hints[key], value, path)
            kwargs[key] = (built if default is None
                           else dataclasses.replace(default, **{k: getattr(built, k) for k in value}))
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
        try:
            return float(value)
        except OverflowError:
            raise BoostNerfError(f"recipe key {where} = {value}: too large for a float") from None
    if hint in (int, float, str, bool) and not (isinstance(value, hint)
                                                and not (hint is int and isinstance(value, bool))):
        fix = ""
        if hint is int and isinstance(value, float) and value.is_integer() and abs(value) < 1e18:
            fix = f" (write {int(value)})"  # `1e3` is a float in YAML 1.2
        elif hint is str and isinstance(value, (int, float)) and not isinstance(value, bool):
            fix = " (quote it to keep it text)"  # `name: 1e5`
        raise BoostNerfError(f"recipe key {where} must be {hint.__name__}, got {value!r}{fix}")
    return value


def _bad(source: str, where: str, value: Any, rule: Any) -> BoostNerfError:
    finite = "a finite number " if isinstance(value, float) and not math.isfinite(value) else ""
    return BoostNerfError(f"{source} {where} = {value!r}: must be {finite}{rule}")


def check_section(section: Any, where: str, source: str = "recipe key") -> None:
    """Refuse any value of a recipe section (a dataclass, recursively) outside its field's declared rule
    (`limits.limit`); the family sections (`dvgo`, `tensorf`, `ngp`) against their config's fields.
    `source` starts the message: "recipe key" when read from a file, "setting" once flags override it."""
    for f in dataclasses.fields(section):
        value, path = getattr(section, f.name), f"{where + '.' if where else ''}{f.name}"
        if dataclasses.is_dataclass(value):
            check_section(value, path, source)
        elif f.name in CONFIGS and isinstance(value, dict):
            _check_family(f.name, value, path, source)
        elif isinstance(value, list):
            if len(value) < f.metadata.get("min_items", 0):
                raise BoostNerfError(f"{source} {path} = {value!r}: needs at least {f.metadata['min_items']} value(s)")
            for item in value:
                _check_value(f, item, path, source)
        else:
            _check_value(f, value, path, source)


def _check_value(f: dataclasses.Field, value: Any, path: str, source: str) -> None:
    rule = rule_of(f)
    if rule is not None and value is not None and not rule.allows(value):
        raise _bad(source, path, value, rule)


def _check_family(family: str, section: dict, where: str, source: str) -> None:
    """A family section: known keys (the config's fields but `res`), each value (single, or per resolution) in range."""
    cfg = CONFIGS[family]
    hints = typing.get_type_hints(cfg)
    fields = {f.name: f for f in dataclasses.fields(cfg) if f.name != "res"}
    for key, value in section.items():
        if key not in fields:
            extra = " (the resolutions are pretrain.res)" if key == "res" else ""
            raise BoostNerfError(f"unknown {source} {where}.{_key_text(key)}{extra}: known keys here are "
                                 f"{', '.join(sorted(fields))}")
        per_res = value.items() if isinstance(value, dict) else [(None, value)]
        listed: set[int] = set()
        for res, v in per_res:
            path = f"{where}.{key}" if res is None else f"{where}.{key}[{res}]"
            if res is not None:
                if not _is_int_key(res):
                    raise BoostNerfError(f"{source} {where}.{key}: the keys of a per-expert mapping must be "
                                         f"resolutions (integers), got {res!r}")
                if int(res) in listed:  # 8 and "8" (a manifest's JSON has only the latter)
                    raise BoostNerfError(f"{source} {where}.{key} lists resolution {int(res)} twice: keep one")
                listed.add(int(res))
            _check_value(fields[key], _coerce(hints[key], v, path), path, source)


def _is_int_key(key: Any) -> bool:
    if isinstance(key, bool) or (isinstance(key, float) and not key.is_integer()):  # 8.5 is no resolution
        return False
    try:
        int(key)
    except (TypeError, ValueError):
        return False
    return True


def nearest_listed(mapping: dict[int, Any], res: int) -> int:
    """The resolution whose value a per-expert mapping gives the expert at `res`: `res` itself when listed, else the
    nearest listed one (the larger on a tie)."""
    return res if res in mapping else min(mapping, key=lambda r: (abs(r - res), -r))


def _family_value(section: dict, key: str, res: int, default: Any) -> Any:
    """The value of family option `key` for the expert at `res`, as pretrain takes it (`nearest_listed`): a check
    that looks up `res` alone would pass a mapping whose nearest value then fails mid-run."""
    value = section.get(key, default)
    if isinstance(value, dict):
        value = {int(k): v for k, v in value.items()}
        value = value[nearest_listed(value, res)] if value else default
    return value


def check_recipe(recipe: Recipe, source: str = "recipe key") -> Recipe:
    """Every value of `recipe` in its declared range (see `check_section`), plus the rules between keys:
    the resolutions of pretrain.res are distinct (they name the experts), an ngp expert's coarsest hash level is no
    finer than its finest (base_res <= max_res), and data.bbox is a box."""
    check_section(recipe, "", source)
    box = recipe.data.bbox
    if box is not None and (len(box) != 6 or not all(box[i + 3] > box[i] for i in range(3))):
        raise BoostNerfError(f"{source} data.bbox = {box!r}: must be six numbers, xmin, ymin, zmin, xmax, ymax, "
                             "zmax, each max above its min")
    pre = recipe.pretrain
    twice = sorted({r for r in pre.res if pre.res.count(r) > 1})
    if twice:
        raise BoostNerfError(f"{source} pretrain.res = {pre.res!r} lists {twice[0]} more than once: each expert is "
                             "named by its resolution, so give each its own")
    if pre.model == "ngp":
        defaults = CONFIGS["ngp"]()
        for res in pre.res:
            lo = _family_value(pre.ngp, "base_res", res, defaults.base_res)
            hi = _family_value(pre.ngp, "max_res", res, defaults.max_res)
            if lo > hi:
                raise BoostNerfError(f"{source} pretrain.ngp.max_res = {hi!r}: must be >= base_res ({lo!r}) "
                                     f"(expert ngp-{res})")
    return recipe


def _check_unused(recipe: Recipe) -> None:
    """Refuse a recipe file that sets a key finetuning ignores (a workspace's manifest that records one still loads:
    the key never changed what was trained)."""
    unused = _finetune_train()
    for key in ("step_ratio", "growth"):
        value = getattr(recipe.moe.train, key)
        if value != getattr(unused, key):
            raise BoostNerfError(f"recipe key moe.train.{key} = {value!r}: finetuning does not use it (the mixtures "
                                 "and the baseline sample at their experts' step, moe.step_from, and no grid grows "
                                 f"while finetuning): remove it (pretrain.train.{key} sets it for the experts)")


class _RecipeLoader(yaml.SafeLoader):
    """YAML's safe loader, with two of its surprises taken out of recipes: a key given twice in one section (the
    last silently wins, and a second `pretrain:` block throws the whole first one away) is refused, and a number
    written `1e-2` or `1.0e3` is a float (YAML 1.1 reads it as text, which a float key refuses: "must be float")."""

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:  # the mapping's own keys: a merge (`<<: *anchor`) may be overridden here
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                line = seen.get(key)
            except TypeError:  # a list or mapping as a key: the safe loader's own error says so
                break
            if line is not None:
                raise ValueError(f"key {key!r} is given twice (lines {line + 1} and {key_node.start_mark.line + 1}): "
                                 "keep one")
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


_RecipeLoader.add_implicit_resolver(  # YAML 1.2's floats: 1e-2, 1E5, -1.5e3 (1.1 wants a dot and a signed exponent)
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def load_recipe(path: Path | None) -> Recipe:
    """Parse and validate a YAML recipe (None -> built-in defaults)."""
    if path is None:
        return Recipe()
    path = Path(path)
    if not path.exists():
        raise BoostNerfError(f"recipe {path} does not exist (recipes ship in the recipes/ folder)")
    if path.is_dir():
        raise BoostNerfError(f"recipe {path} is a folder: pass a YAML file (e.g. recipes/demo-dvgo-cpu.yaml)")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise BoostNerfError(f"recipe {path} is not a text file (not UTF-8): pass a YAML recipe") from None
    except OSError as e:
        raise BoostNerfError(f"cannot read recipe {path} ({e.strerror or type(e).__name__})") from None
    try:
        data = yaml.load(text, Loader=_RecipeLoader) or {}  # noqa: S506 (a safe loader)
    except (yaml.YAMLError, ValueError) as e:  # ValueError: an integer of more than 4300 digits, a key given twice
        raise BoostNerfError(f"recipe {path} is not valid YAML: {str(e).splitlines()[0]}") from None
    recipe = check_recipe(_build(Recipe, data, ""))
    _check_unused(recipe)
    if recipe.name == "defaults":
        recipe.name = path.stem
    return recipe


def recipe_dict(recipe: Recipe) -> dict:
    return dataclasses.asdict(recipe)


def recipe_from_dict(data: dict) -> Recipe:
    """A recipe recorded in a workspace manifest (validated like a YAML file)."""
    return check_recipe(_build(Recipe, data, ""), "workspace manifest's recipe key")


def recorded_recipe(data: dict | None, where: Path) -> Recipe | None:
    """The recipe recorded in file `where` (a workspace's manifest, a bench folder's config), for a command given no
    --recipe; None when it records none. One line naming the file when it no longer loads (hand-edited, or written by
    another boostnerf)."""
    if not data:
        return None
    try:
        return recipe_from_dict(data)
    except BoostNerfError as e:
        raise BoostNerfError(f"the recipe recorded in {where} does not load ({e}): give --recipe FILE to use another "
                             "recipe") from None
