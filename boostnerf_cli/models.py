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
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.renderer import RenderSettings, render_view
from boostnerf_cli.scenes import Scene, Split
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
        return MixtureConfig(**meta["mixture"]), meta["gate"]["config"]["kind"]
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
    gate = Gate(GateConfig(**gm["config"]), gm["experts"], tensors["gate.bbox"], tuple(gm["shape"]))
    vd = DensityVolume.from_config(meta["vd"], tensors["vd.bbox"])
    occ = None
    if "occupancy" in tensors:
        occ = OccupancyGrid(tensors.pop("occupancy").bool(), tensors.pop("occupancy_bbox"))
    mix = Mixture(experts, gate, vd, occ, MixtureConfig(**meta["mixture"]))
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
    save_tensors(dst, tensors, {**meta, "name": name, "pruned_from": pruned_from, "pruned_from_digest": meta["digest"],
                                "packed": packed, "stored_params": params - dropped})
    return tables, dropped


# --- any model of a workspace, ready to render ----------------------------------------------------
SKIP_NAMES = ("empty", "terminated")


@dataclass(frozen=True)
class Skips:
    """Which render-time skips are on; each can be turned off to measure what it saves and costs.

    empty:      samples in empty space are not evaluated (a model's occupancy grid; for a mixture also
                the density volume V_D below its threshold T)
    terminated: colour is computed only for samples whose rendering weight exceeds 1e-4 (drops samples
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

    def settings(self, scene: Scene, color_threshold: float = 1e-4) -> RenderSettings:
        return scene.render_settings(self.step, self.bbox, color_threshold)

    def render_setup(self, scene: Scene, skips: Skips) -> tuple[RenderSettings, Callable[[Tensor], Tensor] | None]:
        """The render settings and the empty-space filter for rendering this model with `skips`."""
        return self.settings(scene, 1e-4 if skips.terminated else 0.0), self.skip if skips.empty else None


def model_file(ws: Workspace, name: str) -> Path:
    """Where model `name` of the workspace lives: experts/NAME.safetensors, else moe/NAME.safetensors."""
    return ws.expert_path(name) if ws.expert_path(name).exists() else ws.model_path(name)


def load_model(ws: Workspace, name: str, device: str, exact_gate: bool = False) -> LoadedModel:
    """An expert (`dvgo-64`), a mixture (`top1`, `top2`, `ens`) or the finetuned `baseline` of the workspace.

    A mixture is returned ready to render: its gate baked (`Mixture.for_rendering`) unless `exact_gate`.
    """
    path = model_file(ws, name)
    if not path.exists() or name == "geometry":
        known = ", ".join(all_model_names(ws)) or "none yet"
        raise BoostNerfError(f"no model named {name!r} in {ws.root} (models: {known})")
    if read_meta(path).get("family") == "mixture":
        mix, meta = load_mixture(path, device)
        params = meta.get("stored_params", count_params(mix))  # the trained model's, before baking (pruned: stored)
        return LoadedModel(name, "mixture", mix, mix.skip, meta["step"], mix.bbox, params,
                           dropped_rows(path, meta)).for_rendering(exact_gate)
    model, occ, meta = load_expert(path, device)
    return LoadedModel(name, "expert", model, occ.to(device) if occ is not None else None, meta["step"],
                       model.bbox, meta.get("stored_params", count_params(model)), dropped_rows(path, meta))


def _finetune_flag(name: str) -> str:
    return {"baseline": "--baseline", "ens": "--ensemble"}.get(name, f"--topk {name[3:]}" if name[3:].isdigit() else name)


def stale_reason(ws: Workspace, name: str) -> tuple[str, str] | None:
    """Why model `name` is stale, as (what changed, the command that makes it again), or None when it is current:
    it was made from a model (moe/init from its experts, a finetuned mixture from moe/init, the baseline from the
    largest expert, a pruned model from its source) that changed since. The first stale link from the experts up
    is named, since remaking it comes first. A pruned model without its report (a prune stopped before its check)
    is stale too. An expert (or a missing file) is never stale here."""
    path = model_file(ws, name)
    if not path.exists():
        return None
    meta = read_meta(path)
    root = ws.root
    if "pruned_from" in meta and not (ws.moe_dir / f"{name}.json").exists():  # written last, after prune's check
        return (f"its prune did not finish (no moe/{name}.json, the check of its renders)",
                f"`boostnerf prune -w {root} --model {meta['pruned_from']}`")
    if name == "init":
        for expert, digest in (meta.get("inputs") or {}).items():
            src = ws.expert_path(expert)
            now = read_meta(src).get("digest") if src.exists() else None
            if now != digest:
                return (f"expert {expert} was {'removed' if now is None else 'retrained'} after build-moe",
                        f"`boostnerf build-moe -w {root}`, then finetune the mixtures again with --force")
        return None
    source, digest = meta.get("pruned_from"), meta.get("pruned_from_digest")
    if source is None:
        source, digest = meta.get("from"), meta.get("from_digest")
    if source is None or digest is None:
        return None
    if (earlier := stale_reason(ws, source)) is not None:  # the source's own staleness is remade first
        return earlier
    src = model_file(ws, source)
    now = read_meta(src).get("digest") if src.exists() else None
    if now == digest:
        return None
    change = "removed" if now is None else "changed"
    if "pruned_from" in meta:
        return (f"{source} was {change} after {name} was pruned from it",
                f"`boostnerf prune -w {root} --model {source} --force`")
    what = f"moe/{source} was rebuilt" if source == "init" else f"expert {source} was {'removed' if now is None else 'retrained'}"
    return f"{what} after {name} was finetuned from it", f"`boostnerf finetune -w {root} {_finetune_flag(name)} --force`"


def current_models(ws: Workspace, names: list[str] | None = None) -> list[str]:
    """`names` (default: every model of the workspace), refused in one line when one is stale (`stale_reason`):
    a table or picture of a model made from an expert since retrained would compare it with what it no longer is."""
    have = all_model_names(ws)
    names = names or have
    reasons = {n: stale_reason(ws, n) for n in dict.fromkeys([*names, *have])}
    stale = {n: reasons[n] for n in names if reasons[n] is not None}
    if stale:
        what = next(iter(stale.values()))[0]
        by_remedy: dict[str, list[str]] = {}  # each way of making stale models again, and the models it makes
        for n, (_, remedy) in stale.items():
            by_remedy.setdefault(remedy, []).append(n)
        others = [n for n in have if reasons[n] is None]
        raise BoostNerfError(
            f"{', '.join(stale)} {'is' if len(stale) == 1 else 'are'} stale: {what}; make "
            + "; ".join(f"{', '.join(names)} again with {remedy}" if i == 0 else f"{', '.join(names)} with {remedy}"
                        for i, (remedy, names) in enumerate(by_remedy.items()))
            + (f" (or name current models: {' '.join('--model ' + n for n in others)})" if others else ""))
    return names


def all_model_names(ws: Workspace) -> list[str]:
    """Experts smallest first, then mixtures in the paper's order."""
    order = {"baseline": 0, "top1": 1, "top2": 2, "ens": 9}
    mixtures = sorted((n for n in ws.model_names() if n != "init"), key=lambda n: (order.get(n, 5), n))
    return ws.expert_names() + mixtures


def n_views(split: Split, views: int | None) -> int:
    """How many views `--views N` means for `split`: the first N, or all."""
    return len(split) if views is None else min(views, len(split))


def render_split(model: LoadedModel, scene: Scene, split: Split, device: str, skips: Skips = ALL_SKIPS,
                 views: int | None = None) -> Iterator[dict]:
    """Render the first `views` views of a split (all by default), one at a time -> outputs with timings.
    A generator: a caller that writes or scores each view as it comes holds one view in memory, not the split
    (200 Blender test views at 800 px held 2.6 GB per model)."""
    settings, skip = model.render_setup(scene, skips)
    for i in range(n_views(split, views)):
        t0 = time.perf_counter()
        r = render_view(model.field, split, i, settings, skip, device)
        r["seconds"] = time.perf_counter() - t0
        yield r

