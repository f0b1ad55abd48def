"""Model files: every expert, mixture and baseline is written and read here, and nowhere else.

A model file is one safetensors file (`workspace.save_tensors`): the module's state dict, plus its
occupancy grid when it has one (`occupancy` uint8, `occupancy_bbox`), and JSON metadata (the family's
`config_dict()`, or for a mixture its config, gate, density volume and experts' configs, and what the
writing stage adds: name, render step, digests). `load_model` turns any model of a workspace into a
`LoadedModel`: a field ready to render with what rendering it needs.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import torch
from torch import Tensor, nn

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import FAMILIES, count_params
from boostnerf_cli.lineage import PrunedSpec
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.packing import packer_for
from boostnerf_cli.render.renderer import COLOR_THRESHOLD, RenderSettings, render_view
from boostnerf_cli.scenes import Scene, Split
from boostnerf_cli.startup import CLOCK, timed
from boostnerf_cli.workspace import (
    MALFORMED,
    Workspace,
    dropped_rows,
    load_tensors,
    malformed,
    pack_rows,
    read_meta,
    save_tensors,
)


# --- experts --------------------------------------------------------------------------------------
def save_expert(path: Path, model: nn.Module, occupancy: OccupancyGrid | None, extra_meta: dict | None = None) -> None:
    tensors = {k: v for k, v in model.state_dict().items()}
    if occupancy is not None:
        tensors["occupancy"] = occupancy.occupied.to(torch.uint8)
        tensors["occupancy_bbox"] = occupancy.bbox.clone()
    save_tensors(path, tensors, {**model.config_dict(), **(extra_meta or {})})


def new_expert(meta: dict, bbox: Tensor, source: str) -> nn.Module:
    """An untrained expert of the family and configuration `meta` records (a model file's, a checkpoint's), over
    `bbox`; one line naming `source` for a family this boostnerf does not know."""
    family = meta.get("family")
    if not isinstance(family, str) or family not in FAMILIES:
        raise BoostNerfError(f"{source} holds an unknown model family {family!r}; was it written by a newer boostnerf?")
    return FAMILIES[family].from_config(meta, bbox)


@timed("models")
def load_expert(path: Path, device: str | torch.device = "cpu") -> tuple[nn.Module, OccupancyGrid | None, dict]:
    """-> (expert in eval mode, its occupancy grid or None, metadata)."""
    tensors, meta = load_tensors(path, device)
    family = meta.get("family")
    try:
        occ = None
        if "occupancy" in tensors:
            occ = OccupancyGrid(tensors.pop("occupancy").bool(), tensors.pop("occupancy_bbox"))
        model = new_expert(meta, tensors["bbox"], str(path))
        model.load_state_dict(tensors)
    except MALFORMED as e:
        raise BoostNerfError(f"{path} does not hold a valid {family} expert ({malformed(e)}; written by another "
                             "boostnerf version?): delete it and rerun the stage that wrote it") from None
    return model.to(device).eval(), occ, meta


# --- mixtures -------------------------------------------------------------------------------------
def save_mixture(path: Path, mix: Mixture, extra: dict | None = None) -> None:
    tensors = {k: v for k, v in mix.state_dict().items()}
    if mix.occupancy is not None:
        tensors["occupancy"] = mix.occupancy.occupied.to(torch.uint8)
        tensors["occupancy_bbox"] = mix.occupancy.bbox.clone()
    meta = {
        "family": "mixture",
        "mixture": asdict(mix.cfg),
        "gate": mix.gate.config_dict(),
        "vd": mix.vd.config_dict(),
        "experts": [ex.config_dict() for ex in mix.experts],
        "step": mix.cfg.step,
        **(extra or {}),
    }
    save_tensors(path, tensors, meta)


@timed("models")
def load_mixture(path: Path, device: str | torch.device = "cpu") -> tuple[Mixture, dict]:
    """-> (mixture in eval mode, metadata)."""
    tensors, meta = load_tensors(path, device)
    if meta.get("family") != "mixture":
        raise BoostNerfError(f"{path} is not a mixture of experts file")
    try:
        return build_mixture(path, tensors, meta, device)
    except MALFORMED as e:
        raise invalid_mixture(path, e) from None


def invalid_mixture(path: Path, e: BaseException) -> BoostNerfError:
    """The one-line error for a mixture file whose contents do not make a mixture (`e`: what was wrong)."""
    return BoostNerfError(f"{path} does not hold a valid mixture ({malformed(e)}; written by another boostnerf "
                          "version?): rerun build-moe and finetune")


def mixture_routing_meta(path: Path, meta: dict) -> tuple[MixtureConfig, str]:
    """(the mixture's config, its gate's kind) from a mixture file's metadata `meta` alone, nothing loaded."""
    try:
        return MixtureConfig.saved(meta["mixture"]), GateConfig.saved(meta["gate"]["config"]).gate_type
    except MALFORMED as e:
        raise invalid_mixture(path, e) from None


def build_mixture(path: Path, tensors: dict, meta: dict, device) -> tuple[Mixture, dict]:
    """The mixture that `save_mixture` wrote as `tensors` and `meta` (read from `path`, named in errors)."""
    experts = []
    for i, em in enumerate(meta["experts"]):
        if em["family"] not in FAMILIES:
            raise BoostNerfError(f"{path}: expert {i} has unknown family {em['family']!r}")
        experts.append(FAMILIES[em["family"]].from_config(em, tensors[f"experts.{i}.bbox"]))
    gm = meta["gate"]
    gate = Gate(GateConfig.saved(gm["config"]), gm["experts"], tensors["gate.bbox"], tuple(gm["shape"]))
    vd = DensityVolume.from_config(meta["vd"], tensors["vd.bbox"])
    occ = None
    if "occupancy" in tensors:
        occ = OccupancyGrid(tensors.pop("occupancy").bool(), tensors.pop("occupancy_bbox"))
    mix = Mixture(experts, gate, vd, occ, MixtureConfig.saved(meta["mixture"]))
    mix.load_state_dict(tensors)
    return mix.to(device).eval(), meta


# --- pruned models ---------------------------------------------------------------------------------
def save_pruned(src: Path, dst: Path, keep: dict[str, Tensor], fill: Callable[[str, Tensor, Tensor], list[float]],
                name: str, pruned_from: str, params: int) -> tuple[list[dict], int]:
    """Write model file `src` to `dst` with only the `keep` rows (V,) bool of each named grid table stored
    (`workspace.pack_rows`); a dropped row reads back as `fill(table name, table, keep)`.
    `params`: the model's parameter count. -> (one summary per table, parameters dropped)."""
    tensors, meta = load_tensors(src)
    if meta.get("packed"):
        raise BoostNerfError(f"{src} is already a pruned model")
    packed, tables, dropped = {}, [], 0
    for tname, rows in keep.items():
        table, rows = tensors.pop(tname), rows.cpu()
        values = fill(tname, table, rows)
        parts = pack_rows(table, rows)
        tensors[f"{tname}@values"], tensors[f"{tname}@mask"] = parts["values"], parts["mask"]
        packed[tname] = {"rows": table.shape[0], "fill": values}
        kept = int(rows.sum())
        dropped += (table.shape[0] - kept) * table.shape[1]
        tables.append({"name": tname, "rows": table.shape[0], "kept_rows": kept, "channels": table.shape[1],
                       "fill": values})
    meta = {k: v for k, v in meta.items() if k != "format_version"}
    save_tensors(dst, tensors, {**meta, "name": name, "from": pruned_from,
                                "signature": PrunedSpec({pruned_from: meta["digest"]}).signature(),
                                "packed": packed, "stored_params": params - dropped})
    return tables, dropped


# --- any model of a workspace, ready to render ----------------------------------------------------
SKIP_NAMES = ("empty", "terminated")


@dataclass(frozen=True)
class Skips:
    """Which render-time skips are on; each can be turned off to measure what it saves and costs.

    empty:      samples in empty space are not evaluated (a model's occupancy grid; for a mixture also
                the density volume V_D below its threshold T)
    terminated: colour is computed only for samples whose rendering weight exceeds COLOR_THRESHOLD (drops samples
                behind rays that have terminated and in near-empty space)
    All off (`--no-skip`) is dense fixed-step sampling over the model's box, every sample through density
    and colour.
    """

    empty: bool = True
    terminated: bool = True

    @staticmethod
    def from_flags(no_skip: bool = False, off: list[str] | None = None) -> "Skips":
        off = set(off or [])
        unknown = sorted(off - set(SKIP_NAMES))
        if unknown:
            raise BoostNerfError(f"--skip-off {unknown[0]}: unknown skip; the skips are {', '.join(SKIP_NAMES)}")
        if no_skip:
            off = set(SKIP_NAMES)
        return Skips(empty="empty" not in off, terminated="terminated" not in off)

    def describe(self) -> str:
        on = [n for n in SKIP_NAMES if getattr(self, n)]
        return "all on" if len(on) == len(SKIP_NAMES) else "all off" if not on else f"only {', '.join(on)} on"


ALL_SKIPS = Skips()


@dataclass(frozen=True)
class Viewing:
    """Which views a reading stage (eval, render) renders and how: the split, its first `views` (None: all), the
    skips, and for a mixture its exact gate instead of the baked one (`LoadedModel.for_rendering`)."""

    split: str = "test"
    views: int | None = None
    skips: Skips = ALL_SKIPS
    exact_gate: bool = False


@dataclass
class LoadedModel:
    """A field ready to render, with what rendering it needs."""

    name: str
    kind: str  # "expert" or "mixture"
    field: nn.Module
    skip: Callable[[Tensor], Tensor] | None
    step: float
    bbox: Tensor
    params: int
    # a pruned model: {parameter name: (V,) bool, the rows its file does not store}; they read back as a constant,
    # so they are no longer parameters (not in `params`, nor in ||w||_0)
    dropped: dict[str, Tensor] = field(default_factory=dict)

    def for_rendering(self, exact_gate: bool = False) -> "LoadedModel":
        """Ready to render: a mixture's gate baked (`Mixture.for_rendering`) unless `exact_gate`."""
        if self.kind == "mixture":
            self.field.for_rendering(exact_gate)
        return self

    def settings(self, scene: Scene, color_threshold: float = COLOR_THRESHOLD) -> RenderSettings:
        return scene.render_settings(self.step, self.bbox, color_threshold)

    def render_setup(self, scene: Scene, skips: Skips) -> tuple[RenderSettings, Callable[[Tensor], Tensor] | None]:
        """The render settings and the empty-space filter for rendering this model with `skips`."""
        return self.settings(scene, COLOR_THRESHOLD if skips.terminated else 0.0), self.skip if skips.empty else None


def load_model(ws: Workspace, name: str, device: str, exact_gate: bool = False) -> LoadedModel:
    """An expert (`dvgo-64`), a mixture (`top1`, `top2`, `ens`) or the finetuned `baseline` of the workspace.

    A mixture is returned ready to render: its gate baked (`Mixture.for_rendering`) unless `exact_gate`.
    """
    path = ws.model_file(name)
    if not path.exists() or name == "geometry":
        known = ", ".join(ws.all_model_names()) or "none yet"
        raise BoostNerfError(f"no model named {name!r} in {ws.root} (models: {known})")
    if read_meta(path).get("family") == "mixture":
        mix, meta = load_mixture(path, device)
        params = meta.get("stored_params", count_params(mix))  # the trained model's, before baking (pruned: stored)
        return LoadedModel(name, "mixture", mix, mix.skip, meta["step"], mix.bbox, params,
                           dropped_rows(path, meta)).for_rendering(exact_gate)
    model, occ, meta = load_expert(path, device)
    return LoadedModel(name, "expert", model, occ.to(device) if occ is not None else None, meta["step"],
                       model.bbox, meta.get("stored_params", count_params(model)), dropped_rows(path, meta))


def n_views(split: Split, views: int | None) -> int:
    """How many views `--views N` means for `split`: the first N, or all."""
    return len(split) if views is None else min(views, len(split))


def render_split(model: LoadedModel, scene: Scene, split: Split, device: str, skips: Skips = ALL_SKIPS,
                 views: int | None = None, warm: bool = False) -> Iterator[dict]:
    """Render the first `views` views of a split (all by default), one at a time -> outputs with timings
    (`seconds`; with `warm`, after a first, untimed render of view 0, whose time is each output's `warmup_seconds`).
    A generator: a caller that writes or scores each view as it comes holds one view in memory, not the split
    (200 Blender test views at 800 px held 2.6 GB per model)."""
    settings, skip = model.render_setup(scene, skips)
    packer = packer_for(device)  # one for the split: each image reuses the budgets the ones before it sized
    CLOCK.ready(model.name)
    warmup = None
    if warm and n_views(split, views):  # the first image pays once: budgets sized, kernels compiled, caches filled
        t0 = time.perf_counter()
        render_view(model.field, split, 0, settings, skip, device, packer)
        warmup = _synced(device) - t0
    for i in range(n_views(split, views)):
        t0 = time.perf_counter()
        r = render_view(model.field, split, i, settings, skip, device, packer)
        r["seconds"] = _synced(device) - t0
        r["warmup_seconds"] = warmup
        yield r


def _synced(device: str) -> float:
    """The time once the device has finished what was queued (a GPU's images are timed to their last kernel)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter()

