"""`boostnerf build-moe`: assemble pretrained experts, the density volume V_D and an untrained gate.

Writes `moe/init.safetensors` (+ `moe/init.json`), the starting point of every `finetune`.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, fields

import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.base import Expert
from boostnerf_cli.fields.registry import FAMILIES, count_params
from boostnerf_cli.lineage import SKIP, Found, MixtureInitSpec, Survey, decide, describe_change
from boostnerf_cli.models import load_expert, save_mixture
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig, routing_of
from boostnerf_cli.recipe import MoERecipe
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.workspace import read_json, write_json

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)


@dataclass(frozen=True)
class Member:
    """A pretrained expert, loaded for the mixture (or as the gate's source): its name, model, parameter count and
    render step."""

    name: str
    model: Expert
    params: int
    step: float


def build(survey: Survey, names: list[str] | None, rec: MoERecipe, device: str) -> dict:
    """Build moe/init from the experts `names` (default: every finished one) with the recipe's moe section: survey,
    load, assemble, decide, write. A moe/init built from the same experts with the same settings is kept as it is
    (`decide`: SKIP); one of other settings, or made from experts retrained since, is built again (said: the models
    finetuned from it are then stale)."""
    ws = survey.ws
    experts, outside, inputs = _experts(survey, names, rec, device)
    topk = rec.topk
    if topk > len(experts):  # the untrained mixture's k is used by nothing but bench's untrained rows: fit it, say so
        topk = len(experts)
        log(f"note: moe.topk = {rec.topk} but the mixture has {len(experts)} expert{'s' if len(experts) > 1 else ''}: "
            f"moe/init routes to {topk} (finetune --topk K sets each finetuned model's k)")
    vd, occ, step = _density_volume(rec, experts, device)
    gate_grid = resolve_gate_grid(rec.gate_grid, [e.model.family for e in experts])
    source = gate_source(rec, gate_grid, experts, outside)
    channels = rec.gate_channels if source is None else source.model.feature_table.shape[1]
    torch.manual_seed(rec.seed)  # the gate's random initialisation: the same for the same recipe
    settings = {f.name: getattr(rec, f.name) for f in fields(GateConfig) if hasattr(rec, f.name)}  # moe.gate_*
    gate = Gate(GateConfig(**{**settings, "gate_grid": gate_grid, "gate_channels": channels}), len(experts), vd.bbox)
    if source is not None:
        gate.init_grid_from(source.model.feature_table, source.model.shape, source.model.bbox)
    gate = gate.to(device)
    cfg = MixtureConfig(**{**routing_of(rec), "topk": topk}, density_threshold=rec.density_threshold, vd_res=vd.res,
                        step=step, expert_names=[e.name for e in experts])
    mix = Mixture([e.model for e in experts], gate, vd, occ, cfg)
    spec = MixtureInitSpec(inputs, {"mixture": asdict(cfg), "gate": gate.config_dict(), "seed": rec.seed})
    found, wanted = survey.finished("init"), spec.signature()
    if found is not None and found.signature is not None and decide(found, wanted).action == SKIP:
        log("moe/init: already built from these experts with these settings, kept as it is")
        return read_json(ws.moe_dir / "init.json", "build-moe report")
    if found is not None:
        _say_rebuilt(survey, found, wanted)
    save_mixture(ws.model_path("init"), mix, {"name": "init", "signature": spec.signature()})
    report = {
        "name": "init",
        "experts": cfg.expert_names,
        "expert_params": [e.params for e in experts],
        "gate": gate.config_dict(),
        "gate_params": count_params(gate),
        "gate_init": "random" if source is None else source.name,
        "density_volume": {"res": cfg.vd_res, "threshold": rec.density_threshold, "from": cfg.expert_names[0],
                           "occupied_fraction": occ.fraction(), "source": rec.vd_source, "filter": rec.vd_filter},
        "step": step,
    }
    write_json(ws.moe_dir / "init.json", report)
    ws.update_manifest(moe={"init": {"experts": cfg.expert_names, "gate": rec.gate_type, "gate_grid": gate_grid,
                                     "inputs": inputs, "digest": survey.digest("init")}})
    _say_built(rec, cfg, gate, gate_grid, source, occ)
    return report


def _experts(survey: Survey, names: list[str] | None, rec: MoERecipe,
             device: str) -> tuple[list[Member], Member | None, dict[str, str]]:
    """The mixture's experts, loaded, smallest first (by parameters, then name); the gate's source when
    moe.gate_from names one left out of the mixture; {name: digest} of both (retraining either makes moe/init stale).
    Refused: no expert, an unknown or repeated name, experts of different scenes."""
    ws, manifest = survey.ws, survey.manifest()
    available = ws.expert_names()
    if not available:
        raise BoostNerfError(f"{ws.root} has no pretrained experts: "
                             f"run `boostnerf pretrain --workspace {ws.root}` first")
    unfinished = [n for n in ws.expert_files() if n not in available]
    if unfinished and not names:
        log(f"build-moe: leaving out {', '.join(unfinished)}: weights without a training report (pretrain did not "
            "finish them; rerun pretrain to)")
    training = sorted(p.stem for p in ws.checkpoints_dir.glob("*.pt") if p.stem.rpartition("-")[0] in FAMILIES
                      and p.stem.rpartition("-")[2].isdigit() and p.stem not in available + unfinished)
    if training and not names:  # pretrain interrupted in them: a training state, no weights yet
        log(f"build-moe: leaving out {', '.join(training)}: still in training "
            f"({', '.join(f'checkpoints/{n}.pt' for n in training)}; rerun pretrain to finish it)")
    names = names or available
    missing = [n for n in names if n not in available]
    if missing:
        raise BoostNerfError(f"no pretrained expert {missing[0]!r} in {ws.root} (experts: {', '.join(available)})")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise BoostNerfError(f"--experts names {twice[0]} more than once: a mixture holds each expert once")
    extra = [rec.gate_from] if rec.gate_from and rec.gate_from not in names else []  # the gate's source, left out
    if extra and extra[0] not in available:
        raise BoostNerfError(f"moe.gate_from = {rec.gate_from!r}: no pretrained expert of that name in {ws.root} "
                             f"(experts: {', '.join(available)})")
    loaded, scenes, inputs = {}, set(), {}
    for n in names + extra:
        inputs[n] = survey.digest(n)
        model, occ, meta = load_expert(ws.expert_path(n), device)
        loaded[n] = Member(n, model, count_params(model), meta["step"])
        scenes.add(meta.get("scene"))
    if len(scenes) > 1 or (manifest.get("scene_id") and scenes != {manifest["scene_id"]}):
        raise BoostNerfError(
            "the experts were trained on different scenes or image sizes: retrain them in one workspace with "
            "`boostnerf pretrain --force`, or pass --experts with experts of one scene"
        )
    for n in names + extra:  # an expert trained on a geometry since retrained: made again first
        decide(Found(n, None, survey.stale(n)), None).check()
    experts = sorted((loaded[n] for n in names), key=lambda e: (e.params, e.name))
    return experts, loaded[extra[0]] if extra else None, inputs


def _density_volume(rec: MoERecipe, experts: list[Member],
                    device: str) -> tuple[DensityVolume, OccupancyGrid, float]:
    """V_D fitted to the smallest expert's density, its occupancy at the mixture's render step (refused when it
    keeps no cell), and that step. -> (V_D, occupancy, step)."""
    smallest = experts[0].model
    bbox = smallest.bbox
    step = experts[0].step if rec.step_from == "smallest" else experts[-1].step
    vd = DensityVolume(bbox, rec.vd_res or smallest.spatial_res).to(device)
    vd.init_from(smallest.density)
    occ = OccupancyGrid.from_density(vd.density, bbox, vd.shape, step, rec.density_threshold)
    if occ.fraction() == 0:
        coarse = rec.vd_res and 2 * rec.vd_res <= smallest.spatial_res
        raise BoostNerfError(
            f"V_D from {experts[0].name} keeps no cell: its opacity over one render step is at most "
            f"moe.density_threshold = {rec.density_threshold:g} everywhere, so every sample would be filtered and "
            "the mixture could not train; lower it (--threshold)"
            + (f" or raise moe.vd_res (= {rec.vd_res}: a volume this coarse reads the expert's density at few points; "
               f"unset, it is the smallest expert's {smallest.spatial_res})" if coarse else "")
            + " or train the experts longer (pretrain --iters N --force), unless the scene shows nothing but "
            "empty space")
    return vd, occ, step


def _say_rebuilt(survey: Survey, found: Found, wanted: dict) -> None:
    """Say why moe/init is built again, and which finetuned models that leaves stale."""
    why = found.stale[0] if found.stale else describe_change(found.signature, wanted) if found.signature else None
    made = [n for n in survey.models if "init" in ((survey.signature(n) or {}).get("inputs") or {})]
    log(f"moe/init: building it again ({why or 'it records no settings'})"
        + (f"; {', '.join(made)}, finetuned from the old one, will be stale: finetune "
           f"{'it' if len(made) == 1 else 'them'} again with --force" if made else ""))


def _say_built(rec: MoERecipe, cfg: MixtureConfig, gate: Gate, gate_grid: str, source: Member | None,
               occ: OccupancyGrid) -> None:
    has_grid = rec.gate_type in ("grid", "linear")  # a switch gate encodes positions: it has no grid to size
    grid_text = f" ({gate_grid} features) {'x'.join(map(str, gate.shape))}" if has_grid else ""
    if source is not None:
        same = tuple(source.model.shape) == tuple(gate.shape)
        grid_text += f" started from {source.name}'s feature grid ({'copied' if same else 'resampled trilinearly'})"
    log(f"built a mixture of {len(cfg.expert_names)} experts ({', '.join(cfg.expert_names)}), gate {rec.gate_type}"
        f"{grid_text}, V_D from {cfg.expert_names[0]} keeps {100 * occ.fraction():.1f}% of cells"
        + (f" (its filter then reads {cfg.expert_names[-1]}'s density as it trains)" if rec.vd_source == "largest"
           else ""))


def gate_source(rec: MoERecipe, gate_grid: str, experts: list[Member],
                outside: Member | None = None) -> Member | None:
    """The expert whose feature grid starts the gate's (moe.gate_init: expert), or None (random).

    The smallest expert, or the one `moe.gate_from` names (`outside`: one left out of the mixture). The official
    code (EIDOSLAB/boost-your-nerf, instant-ngp/moe_main.py) copies the gate's k0 feature grid from the
    lowest-resolution, 128^3, model and then leaves that model out of the mixture; its density grid is copied too
    but never read by the gate's forward, so only the feature grid is copied here. `experts`: smallest first.
    Needs a grid or linear gate with a dense grid and a dvgo source expert."""
    if rec.gate_init == "random":
        if rec.gate_from:
            raise BoostNerfError(f"moe.gate_from = {rec.gate_from!r} needs moe.gate_init = expert (the gate is random "
                                 f"now): set moe.gate_init to expert, or moe.gate_from to ''")
        return None
    source = outside or next((e for e in experts if e.name == rec.gate_from), experts[0])
    if source.model.family != "dvgo":
        raise BoostNerfError(f"moe.gate_init = expert needs a dvgo expert (the gate copies a dense feature grid); "
                             f"{source.name} is {source.model.family}: set moe.gate_init to random")
    if rec.gate_type not in ("grid", "linear") or gate_grid != "dense":
        raise BoostNerfError(f"moe.gate_init = expert needs a grid or linear gate with a dense feature grid "
                             f"(moe.gate_type = {rec.gate_type}, gate grid {gate_grid}): set moe.gate_init to random "
                             "or moe.gate_grid to dense")
    return source


def resolve_gate_grid(choice: str, families: list[str]) -> str:
    """`auto`: the gate grid of the experts' family as in the paper; dense when families are mixed."""
    if choice != "auto":
        return choice
    kinds = {FAMILIES[f].gate_grid for f in families}
    return kinds.pop() if len(kinds) == 1 else "dense"
