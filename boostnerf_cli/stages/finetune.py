"""`boostnerf finetune`: train gate and experts jointly (Algorithm 1), or the comparison models.

--topk k     -> moe/top{k}: sparse mixture, loss = photometric + lambda * L_rw-aux
--ensemble   -> moe/ens:    every expert, equal weights, jointly finetuned (the paper's Ens)
--baseline   -> moe/baseline: the largest expert trained alone for the same finetuning iterations
All three start from the same pretrained experts and use the same photometric loss and schedule.
Under torchrun every model trains data parallel (`train(..., data_parallel=True)`, the auxiliary loss
by `tasks.batch_routing`); rank 0 alone writes the outputs (docs/distributed.md).
"""

from __future__ import annotations

from typing import Callable

from boostnerf_cli import distributed as dist
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import count_params
from boostnerf_cli.models import load_expert, load_mixture, save_expert, save_mixture, stale_reason
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig
from boostnerf_cli.moe.router import check_topk
from boostnerf_cli.recipe import MoERecipe, check_section, shaping_changes
from boostnerf_cli.scenes import Scene
from boostnerf_cli.stages.common import workspace_scene
from boostnerf_cli.tasks import FieldTask, MixtureTask, train_rays
from boostnerf_cli.train import Schedule, train
from boostnerf_cli.workspace import Workspace, read_json, read_meta, write_json


def model_name(topk: int | None, ensemble: bool, baseline: bool) -> str:
    chosen = sum([topk is not None, ensemble, baseline])
    if chosen != 1:
        raise BoostNerfError("finetune needs exactly one of --topk K, --ensemble or --baseline")
    return "ens" if ensemble else "baseline" if baseline else f"top{topk}"


def check_inputs(ws: Workspace) -> None:
    """Refuse a moe/init built from experts that have been retrained or removed since build-moe."""
    if (stale := stale_reason(ws, "init")) is not None:
        what, remedy = stale
        raise BoostNerfError(f"{what}, so moe/init is stale: rerun {remedy}")


def _source_digest(ws: Workspace, name: str, init_meta: dict) -> str | None:
    """Digest of what model `name` is finetuned from: moe/init, or the largest expert for the baseline."""
    if name == "baseline":
        largest = init_meta["mixture"]["expert_names"][-1]
        return read_meta(ws.expert_path(largest)).get("digest")
    return init_meta.get("digest")


def run(ws: Workspace, name: str, topk: int | None, rec: MoERecipe, device: str, force: bool,
        log: Callable[[str], None]) -> dict:
    check_section(rec, "moe", "setting")  # the recipe was checked when read; flags may have changed it since
    init = ws.model_path("init")
    if not init.exists():
        raise BoostNerfError(f"no mixture to finetune in {ws.root}: run `boostnerf build-moe --workspace {ws.root}` first")
    init_meta = read_meta(init)
    check_inputs(ws)
    if ws.model_path(name).exists() and (ws.moe_dir / f"{name}.json").exists() and not force:
        if stale_reason(ws, name) is not None:  # moe/init is current (above), so: finetuned from an older one
            raise BoostNerfError(
                f"{name} was finetuned from an older {'expert' if name == 'baseline' else 'moe/init'} "
                f"(build-moe or pretrain ran again since): add --force to finetune it again"
            )
        log(f"{name}: already finetuned, skipping (use --force to redo it)")
        return read_json(ws.moe_dir / f"{name}.json", "finetune report")
    if force:
        dist.on_main(lambda: ws.checkpoint_path(name).unlink(missing_ok=True))
    scene = workspace_scene(ws)
    mix, meta = load_mixture(init, device)
    mix.train()
    sched = Schedule(rec.iters, rec.train.batch_rays, rec.train.lr_decay, rec.train.log_every, rec.train.checkpoint_every)
    source = _source_digest(ws, name, init_meta)
    if name == "baseline":
        return _baseline(ws, scene, mix, rec, sched, device, log, source)
    mix.configure(mix=rec.mix, aux_norm=rec.aux_norm, aux_samples=rec.aux_samples, vd_source=rec.vd_source,
                  vd_filter=rec.vd_filter)
    if name == "ens":
        mix.make_ensemble()
    else:
        check_topk(topk, mix.cfg.expert_names, "--topk")
        mix.configure(topk=topk, renormalize=rec.renormalize, penalty=rec.penalty, bake_res=rec.bake_res)
    settings = scene.render_settings(mix.cfg.step, mix.bbox, rec.train.color_threshold)
    task = MixtureTask(mix, settings, rec.train, rec)
    signature = {"stage": "finetune", "model": name, "from": source, "iters": rec.iters, "seed": rec.seed,
                 "topk": mix.cfg.topk, "renormalize": mix.cfg.renormalize, "penalty": mix.cfg.penalty}
    defaults = MixtureConfig()
    for key in ("mix", "aux_norm", "aux_samples", "vd_source", "vd_filter"):  # named only when not the default: older checkpoints still resume
        if getattr(mix.cfg, key) != getattr(defaults, key):
            signature[key] = getattr(mix.cfg, key)
    if rec.train.random_background:
        signature["random_background"] = True
    if task.wide_steps:
        signature["wide_steps"] = task.wide_steps
    if task.gate_noise:
        signature["gate_noise"] = task.gate_noise
    signature.update(_shaping(rec, ("lam",)))
    result = train(task, train_rays(scene, mix.bbox, device, rec.train), sched, rec.seed, name, checkpoint=ws.checkpoint_path(name),
                   signature=signature, data_parallel=True)
    mix.eval()
    final = result.history[-1] if result.history else {}
    report = {
        "name": name,
        "kind": "mixture",
        "topk": mix.cfg.topk,
        "renormalize": mix.cfg.renormalize,
        "lambda": rec.lam,
        "penalty": mix.cfg.penalty,
        "mix": mix.cfg.mix,
        "aux_norm": mix.cfg.aux_norm,
        "aux_samples": mix.cfg.aux_samples,
        "vd_source": mix.cfg.vd_source,
        "vd_filter": mix.cfg.vd_filter,
        "wide_steps": task.wide_steps,
        "gate_noise": task.gate_noise,
        "gate": mix.gate.cfg.kind,
        "experts": mix.cfg.expert_names,
        "iterations": result.iterations,
        "seconds": round(result.seconds, 2),
        "skipped_steps": result.skipped_steps,
        "params": count_params(mix),
        "load": [final.get(f"load{i}", 0.0) for i in range(mix.m)],
        "train_psnr": final.get("psnr"),
        "history": result.history,
    }

    def write() -> None:
        save_mixture(ws.model_path(name), mix, {"name": name, "from": "init", "from_digest": source})
        write_json(ws.moe_dir / f"{name}.json", report)
        ws.checkpoint_path(name).unlink(missing_ok=True)
        ws.update_manifest(moe={name: {"from": "init", "iterations": rec.iters}})

    dist.on_main(write)
    log(f"{name}: {result.iterations} steps in {result.seconds:.0f}s, train PSNR {report['train_psnr']:.2f}, "
        f"load per expert {[round(v, 3) for v in report['load']]}")
    return report


def _shaping(rec: MoERecipe, keys: tuple[str, ...]) -> dict:
    """The signature's entries for the joint training settings that differ from the defaults (`shaping_changes`):
    `train` (batch, thresholds, loss weights; not the learning rates), and the MoE section's `keys` (lambda)."""
    default = MoERecipe()
    out = {k: getattr(rec, k) for k in keys if getattr(rec, k) != getattr(default, k)}
    if changed := shaping_changes(rec.train, default.train, leave_out=("random_background",)):
        out["train"] = changed
    return out


def _baseline(ws: Workspace, scene: Scene, mix: Mixture, rec: MoERecipe, sched: Schedule, device: str,
              log: Callable[[str], None], source: str | None) -> dict:
    """The largest expert alone, trained for the same finetuning iterations and schedule."""
    largest = mix.cfg.expert_names[-1]
    model, occ, meta = load_expert(ws.expert_path(largest), device)
    model.train()
    settings = scene.render_settings(meta["step"], model.bbox, rec.train.color_threshold)
    task = FieldTask(model, settings, rec.train, skip=occ, base_mask=occ)
    signature = {"stage": "finetune", "model": "baseline", "from": source, "iters": rec.iters, "seed": rec.seed}
    if rec.train.random_background:  # named only when set: older checkpoints still resume
        signature["random_background"] = True
    signature.update(_shaping(rec, ()))
    result = train(task, train_rays(scene, model.bbox, device, rec.train), sched, rec.seed, "baseline",
                   checkpoint=ws.checkpoint_path("baseline"), signature=signature, data_parallel=True)
    model.eval()
    final = result.history[-1] if result.history else {}
    report = {
        "name": "baseline",
        "kind": "expert",
        "from": largest,
        "iterations": result.iterations,
        "seconds": round(result.seconds, 2),
        "skipped_steps": result.skipped_steps,
        "params": count_params(model),
        "train_psnr": final.get("psnr"),
        "history": result.history,
    }

    def write() -> None:
        save_expert(ws.model_path("baseline"), model, task.skip,
                    {**meta, "name": "baseline", "from": largest, "from_digest": source})
        write_json(ws.moe_dir / "baseline.json", report)
        ws.checkpoint_path("baseline").unlink(missing_ok=True)
        ws.update_manifest(moe={"baseline": {"from": largest, "iterations": rec.iters}})

    dist.on_main(write)
    log(f"baseline ({largest}): {result.iterations} steps in {result.seconds:.0f}s, train PSNR {report['train_psnr']:.2f}")
    return report
