"""`boostnerf finetune`: train gate and experts jointly (Algorithm 1), or the comparison models.

--topk k     -> moe/top{k}: sparse mixture, loss = photometric + lambda * L_rw-aux
--ensemble   -> moe/ens:    every expert, equal weights, jointly finetuned (the paper's Ens)
--baseline   -> moe/baseline: the largest expert trained alone for the same finetuning iterations
All three start from the same pretrained experts and use the same photometric loss and schedule.
Under torchrun every model trains data parallel (`train(..., data_parallel=True)`, the auxiliary loss
by `tasks.batch_routing`); rank 0 alone writes the outputs (docs/distributed.md).
"""

from __future__ import annotations

import dataclasses
import logging

from boostnerf_cli import distributed as dist
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import BaselineSpec, FinetuneSpec, Survey, decide
from boostnerf_cli.models import load_expert, load_mixture, mixture_routing_meta, save_expert, save_mixture
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig, Routing, check_config, routing_of
from boostnerf_cli.moe.router import check_topk
from boostnerf_cli.recipe import MoERecipe
from boostnerf_cli.scenes import Scene
from boostnerf_cli.stages.common import train_and_report
from boostnerf_cli.tasks import FieldTask, MixtureTask, train_rays
from boostnerf_cli.train import Schedule, TrainCheckpoint
from boostnerf_cli.workspace import Workspace, read_json, remove, write_json

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)


def model_name(topk: int | None, ensemble: bool, baseline: bool) -> str:
    chosen = sum([topk is not None, ensemble, baseline])
    if chosen != 1:
        raise BoostNerfError("finetune needs exactly one of --topk K, --ensemble or --baseline")
    return "ens" if ensemble else "baseline" if baseline else f"top{topk}"


def _source_digest(survey: Survey, name: str, init_meta: dict) -> str | None:
    """Digest of what model `name` is finetuned from: moe/init, or the largest expert for the baseline."""
    if name == "baseline":
        return survey.digest(init_meta["mixture"]["expert_names"][-1])
    return init_meta.get("digest")


def routing(name: str, topk: int | None, rec: MoERecipe, cfg: MixtureConfig,
            gate_kind: str) -> tuple[MixtureConfig, str]:
    """How finetuning configures moe/init's mixture (its config `cfg`, its gate's kind) for model `name`: the recipe's
    routing (`moe.mixture.Routing`), then the ensemble's uniform gate and k = M, or top-k's k.
    -> (the mixture's config, the gate's kind)."""
    cfg = dataclasses.replace(cfg, **routing_of(rec))
    m = len(cfg.expert_names)
    if name == "ens":  # equal weights over every expert: renormalising and the penalty change nothing
        return dataclasses.replace(cfg, topk=m, renormalize=True, penalty=Routing().penalty), "uniform"
    check_topk(topk, cfg.expert_names, "--topk")
    # at k = M every expert is used and the weights already sum to 1: renormalising changes nothing
    cfg = dataclasses.replace(cfg, topk=topk, renormalize=True if topk == m else rec.renormalize)
    check_config(cfg, m)
    return cfg, gate_kind


def spec(name: str, rec: MoERecipe, source: str | None, cfg: MixtureConfig | None = None,
         largest: str = "") -> FinetuneSpec | BaselineSpec:
    """What defines finetuned model `name`: its source's digest `source` (moe/init, or for the baseline the `largest`
    expert), and the recipe's settings, with `routing`'s config `cfg` for a mixture."""
    if name == "baseline":
        return BaselineSpec.of(rec, largest, source)
    return FinetuneSpec.of(name, rec, source, routing_of(cfg))


def _planned_signature(survey: Survey, name: str, topk: int | None, rec: MoERecipe, init_meta: dict) -> dict:
    """The signature this run would give `name`, from moe/init's metadata alone (nothing loaded)."""
    source = _source_digest(survey, name, init_meta)
    if name == "baseline":
        return spec(name, rec, source, largest=init_meta["mixture"]["expert_names"][-1]).signature()
    cfg, _ = routing(name, topk, rec, *mixture_routing_meta(survey.ws.model_path("init"), init_meta))
    return spec(name, rec, source, cfg).signature()


MOOT = ("moe.lam", "moe.penalty", "moe.renormalize")  # the recipe keys that some models cannot use


def mixture_init(survey: Survey) -> dict:
    """moe/init's metadata, refused when it is missing or built from experts that were retrained or removed since."""
    ws, meta = survey.ws, survey.meta("init")
    if meta is None:
        raise BoostNerfError(f"no mixture to finetune in {ws.root}: "
                             f"run `boostnerf build-moe --workspace {ws.root}` first")
    if (why := survey.stale("init")) is not None:
        what, remedy = why
        raise BoostNerfError(f"{what}, so moe/init is stale: rerun {remedy}")
    return meta


def unused_settings(survey: Survey, name: str, topk: int | None, rec: MoERecipe,
                    given: set[str]) -> tuple[list[str], str]:
    """Which of the recipe keys `given` (on the command line) cannot change model `name`, and why: the baseline has
    no gate; the ensemble's is uniform, with no auxiliary loss to weigh; at k = M every expert is used and the
    weights already sum to 1. Read from moe/init's metadata. -> (keys, why), ([], "") when each can."""
    asked = [key for key in MOOT if key in given]
    if name == "baseline":
        return asked, "the largest expert alone, no gate"
    cfg, kind = routing(name, topk, rec, *mixture_routing_meta(survey.ws.model_path("init"), mixture_init(survey)))
    unused = [key for key in asked if name == "ens" and key != "moe.renormalize"]
    if (kind == "uniform" or cfg.topk >= len(cfg.expert_names)) and "moe.renormalize" in asked:
        unused.append("moe.renormalize")
    why = "every expert is used with equal weights" if name == "ens" else "at k = M every expert is used"
    return unused, why if unused else ""


def run(survey: Survey, name: str, topk: int | None, rec: MoERecipe, device: str, force: bool) -> dict:
    """Finetune model `name` (skipped when finished with the same settings): survey, decide, load, train, report."""
    ws, init = survey.ws, mixture_init(survey)
    if (found := survey.finished(name)) is not None and not force:  # refused when made from another moe/init or
        decide(found, _planned_signature(survey, name, topk, rec, init)).check()  # expert, or other settings
        log(f"{name}: already finetuned, skipping (use --force to redo it)")
        return read_json(ws.moe_dir / f"{name}.json", "finetune report")
    scene = survey.scene()
    mix, _ = load_mixture(ws.model_path("init"), device)
    mix.train()
    if name == "baseline":
        return _baseline(ws, scene, mix, rec, device, force)
    source = _source_digest(survey, name, init)
    if name == "ens":
        mix.make_ensemble()
    cfg, kind = routing(name, topk, rec, mix.cfg, mix.gate.cfg.gate_type)
    mix.configure(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)})
    settings = scene.render_settings(mix.cfg.step, mix.bbox, rec.train.color_threshold)
    task = MixtureTask(mix, settings, rec.train, rec)
    sig = spec(name, rec, source, mix.cfg).signature()
    result, trained = train_and_report(task, train_rays(scene, mix.bbox, device, rec.train), _schedule(rec), rec.seed,
                                       name, TrainCheckpoint(ws.checkpoint_path(name), sig, restart_other=force), mix,
                                       data_parallel=True)
    final = result.history[-1] if result.history else {}
    report = {
        "name": name,
        "kind": "mixture",
        **routing_of(mix.cfg),
        "lambda": rec.lam,
        "seed": rec.seed,
        "gate": mix.gate.cfg.gate_type,
        "experts": mix.cfg.expert_names,
        **trained,
        "load": [final.get(f"load{i}", 0.0) for i in range(mix.m)],
    }

    def write() -> None:
        save_mixture(ws.model_path(name), mix, {"name": name, "from": "init", "signature": sig})
        write_json(ws.moe_dir / f"{name}.json", report)
        remove(ws.checkpoint_path(name))
        ws.update_manifest(moe={name: {"from": "init", "iterations": rec.iters}})

    dist.on_main(write)
    log(f"{name}: {result.iterations} steps in {result.seconds:.0f}s, train PSNR {report['train_psnr']:.2f}, "
        f"load per expert {[round(v, 3) for v in report['load']]}")
    return report


def _schedule(rec: MoERecipe) -> Schedule:
    """The joint training's schedule, the same for every finetuned model."""
    return Schedule.of(rec.iters, rec.train)


def _baseline(ws: Workspace, scene: Scene, mix: Mixture, rec: MoERecipe, device: str, force: bool = False) -> dict:
    """The largest expert of moe/init's mixture `mix` alone, trained for the same finetuning iterations and schedule."""
    largest = mix.cfg.expert_names[-1]
    model, occ, meta = load_expert(ws.expert_path(largest), device)
    model.train()
    settings = scene.render_settings(meta["step"], model.bbox, rec.train.color_threshold)
    task = FieldTask(model, settings, rec.train, skip=occ, base_mask=occ)
    sig = spec("baseline", rec, meta["digest"], largest=largest).signature()
    result, trained = train_and_report(task, train_rays(scene, model.bbox, device, rec.train), _schedule(rec),
                                       rec.seed, "baseline",
                                       TrainCheckpoint(ws.checkpoint_path("baseline"), sig, restart_other=force), model,
                                       data_parallel=True)
    report = {"name": "baseline", "kind": "expert", "from": largest, "seed": rec.seed, **trained}

    def write() -> None:
        save_expert(ws.model_path("baseline"), model, task.skip,
                    {**meta, "name": "baseline", "from": largest, "signature": sig})
        write_json(ws.moe_dir / "baseline.json", report)
        remove(ws.checkpoint_path("baseline"))
        ws.update_manifest(moe={"baseline": {"from": largest, "iterations": rec.iters}})

    dist.on_main(write)
    log(f"baseline ({largest}): {result.iterations} steps in {result.seconds:.0f}s, "
        f"train PSNR {report['train_psnr']:.2f}")
    return report
