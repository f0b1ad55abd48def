"""`boostnerf finetune`: train gate and experts jointly (Algorithm 1), or the comparison models.

--topk k     -> moe/top{k}: sparse mixture, loss = photometric + lambda * L_rw-aux
--ensemble   -> moe/ens:    every expert, equal weights, jointly finetuned (the paper's Ens)
--baseline   -> moe/baseline: the largest expert trained alone for the same finetuning iterations
All three start from the same pretrained experts and use the same photometric loss and schedule.
Under torchrun every model trains data parallel (`train(..., data_parallel=True)`, the auxiliary loss
by `batch_routing`); rank 0 alone writes the outputs (docs/distributed.md).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from boostnerf_cli import distributed as dist
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields import count_params, load_expert, save_expert
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig, RoutingStats, load_mixture, save_mixture
from boostnerf_cli.moe.router import aux_denominator, expert_counts, penalty_weights
from boostnerf_cli.recipe import MoERecipe, TrainRecipe, check_section
from boostnerf_cli.render.renderer import RayBundle, RenderSettings, render_rays
from boostnerf_cli.render.volrend import render_weights
from boostnerf_cli.scenes import Scene
from boostnerf_cli.stages.common import workspace_scene
from boostnerf_cli.stages.pretrain import FieldTask, photometric_loss
from boostnerf_cli.train import RayData, Schedule, train
from boostnerf_cli.workspace import Workspace, read_json, read_meta, write_json


@dataclass
class MixtureTask:
    """One finetuning step of a mixture: render with routing stats, photometric + lambda * aux loss."""

    mix: Mixture
    settings: RenderSettings
    tcfg: TrainRecipe
    rec: MoERecipe

    def param_groups(self) -> list[dict]:
        return self.mix.param_groups(self.tcfg.lr_grid, self.tcfg.lr_mlp, self.rec.lr_gate, self.rec.lr_gate_mlp)

    def before_step(self, step: int) -> bool:
        return False

    def loss(self, origins: Tensor, dirs: Tensor, rgb: Tensor, step: int):
        stats = RoutingStats()
        bundle = render_rays(self.mix.with_stats(stats), origins, dirs, self.settings, self.mix.skip, jitter=True)
        loss, logs = photometric_loss(bundle, rgb, self.tcfg)
        for ex in self.mix.experts:  # family-specific terms (TensoRF's L1), as in pretraining
            reg = ex.regularization()
            if reg is not None:
                loss = loss + reg
        keep = None
        if self.mix.cfg.aux_samples == "visible":
            keep = visible_samples(self.mix, bundle, origins, dirs, self.settings.color_threshold)
        aux, aux_value, load = batch_routing(stats, self.mix.penalty, self.mix.m, self.mix.cfg.aux_norm, keep)
        if self.rec.lam > 0 and self.mix.gate.cfg.kind != "uniform":
            loss = loss + self.rec.lam * aux
            logs["aux"] = aux_value
        for i, f in enumerate(load):
            logs[f"load{i}"] = f
        logs["samples"] = bundle.n_samples / origins.shape[0]
        return loss, logs

    def state(self) -> dict:
        return {"model": self.mix.state_dict()}

    def load_state(self, state: dict) -> None:
        self.mix.load_state_dict(state["model"])


@torch.no_grad()
def visible_samples(mix: Mixture, bundle: RayBundle, origins: Tensor, dirs: Tensor, threshold: float) -> Tensor:
    """Which samples of the density pass are visible, as the official code counts them for its auxiliary loss
    (EIDOSLAB/boost-your-nerf, dvgo/moe.py, DVGOMoE.forward): the density volume's opacity over the step and its
    rendering weight along the ray (V_D alone composited over the density pass's samples) both above `threshold`
    (its fast_color_thres, 1e-4; here moe.train.color_threshold). -> (n_samples,) bool, in the routing order."""
    rows, t, step = bundle.extras["rows"], bundle.extras["t"], bundle.extras["step"]
    r, s = t.shape
    ray = rows // s
    xyz = origins[ray] + t.reshape(-1)[rows, None] * dirs[ray]  # the renderer's sample positions
    sigma = torch.zeros(r * s, device=t.device, dtype=t.dtype)
    sigma[rows] = mix.vd.density(xyz).to(t.dtype)
    weights, alpha, _ = render_weights(sigma.reshape(r, s), torch.full((r, s), step, device=t.device, dtype=t.dtype))
    return (alpha.reshape(-1)[rows] > threshold) & (weights.reshape(-1)[rows] > threshold)


def batch_routing(stats: RoutingStats, weights: Tensor, m: int, norm: str = "batch",
                  keep: Tensor | None = None) -> tuple[Tensor, float, list[float]]:
    """The auxiliary loss L = M / Z^2 sum_i c_i m_i w_i of the step's whole batch, and the load per expert.

    Z = |B| (norm "batch") or sum_i c_i (norm "counts", `router.aux_loss`); the batch is every routed sample, or
    those where `keep` holds (mask over the routed samples; the load is over every routed sample).
    -> (the term to add to this rank's loss, L's value, the fraction of routed samples each expert got).
    Data parallel, the batch is the union of the ranks' shards and L is not a mean of per-shard terms:
    the counts c_i and the number of samples |B| are summed over the ranks (they carry no gradient), and
    each rank's term keeps its own samples' probability mass m_i^(r), times the number of ranks N, so the
    ranks' averaged gradient, (1/N) sum_r N M/Z^2 sum_i c_i w_i grad m_i^(r), is exactly L's gradient.
    """
    if dist.world_size() == 1:
        aux = stats.aux(weights, norm, keep)
        return aux, float(aux.detach()), stats.load(m)
    probs = torch.cat(stats.probs) if stats.probs else weights.new_zeros(0, m)
    idx = torch.cat(stats.idx) if stats.idx else torch.zeros(0, 1, dtype=torch.long, device=weights.device)
    routed, n_routed = expert_counts(idx, m).to(weights), float(idx.shape[0])
    if keep is not None:
        probs, idx = probs[keep], idx[keep]
    mass = probs.sum(dim=0)
    local = torch.cat([expert_counts(idx, m).to(mass), mass, mass.new_tensor([float(probs.shape[0])]), routed.to(mass),
                       mass.new_tensor([n_routed])])
    total = dist.all_sum(local.double())
    counts, n = total[:m].to(mass), float(total[2 * m])
    routed_total, n_routed = total[2 * m + 1 : 3 * m + 1], float(total[-1])
    load = (routed_total / n_routed).tolist() if n_routed > 0 else [0.0] * m
    if n == 0:
        return mass.sum() * 0.0, 0.0, load
    z = aux_denominator(n, idx.shape[1], norm)
    value = m / z**2 * float((total[:m] * total[m : 2 * m] * weights.double()).sum())
    return dist.world_size() * m / z**2 * (counts * mass * weights.to(mass)).sum(), value, load


def model_name(topk: int | None, ensemble: bool, baseline: bool) -> str:
    chosen = sum([topk is not None, ensemble, baseline])
    if chosen != 1:
        raise BoostNerfError("finetune needs exactly one of --topk K, --ensemble or --baseline")
    return "ens" if ensemble else "baseline" if baseline else f"top{topk}"


def check_inputs(ws: Workspace, init_meta: dict) -> None:
    """Refuse a moe/init built from experts that have been retrained or removed since build-moe."""
    for expert, digest in (init_meta.get("inputs") or {}).items():
        path = ws.expert_path(expert)
        now = read_meta(path).get("digest") if path.exists() else None
        if now != digest:
            what = "removed" if now is None else "retrained"
            raise BoostNerfError(
                f"expert {expert} was {what} after build-moe, so moe/init is stale: rerun "
                f"`boostnerf build-moe --workspace {ws.root}`, then finetune with --force"
            )


def _source_digest(ws: Workspace, name: str, init_meta: dict) -> str | None:
    """Digest of what model `name` is finetuned from: moe/init, or the largest expert for the baseline."""
    if name == "baseline":
        largest = init_meta["mixture"]["expert_names"][-1]
        return read_meta(ws.expert_path(largest)).get("digest")
    return init_meta.get("digest")


def train_rays(scene: Scene, bbox: Tensor, device: str) -> RayData:
    """The scene's train-split rays that hit `bbox` (`RayData.from_split`), moved to `device`: what finetuning trains on."""
    return RayData.from_split(scene.splits["train"], bbox.cpu(), scene.near, scene.far, scene.ndc).to(device)


def run(ws: Workspace, name: str, topk: int | None, rec: MoERecipe, device: str, force: bool,
        log: Callable[[str], None]) -> dict:
    check_section(rec, "moe", "setting")  # the recipe was checked when read; flags may have changed it since
    init = ws.model_path("init")
    if not init.exists():
        raise BoostNerfError(f"no mixture to finetune in {ws.root}: run `boostnerf build-moe --workspace {ws.root}` first")
    init_meta = read_meta(init)
    check_inputs(ws, init_meta)
    if ws.model_path(name).exists() and (ws.moe_dir / f"{name}.json").exists() and not force:
        made_from = read_meta(ws.model_path(name)).get("from_digest")
        if made_from is not None and made_from != _source_digest(ws, name, init_meta):
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
    mix.cfg = dataclasses.replace(mix.cfg, mix=rec.mix, aux_norm=rec.aux_norm, aux_samples=rec.aux_samples)
    if name == "ens":
        mix.gate = Gate(GateConfig(kind="uniform"), mix.m, mix.bbox).to(device)
        mix.cfg = dataclasses.replace(mix.cfg, topk=mix.m)
    else:
        if not 1 <= topk <= mix.m:
            raise BoostNerfError(f"--topk must be between 1 and the number of experts ({mix.m}), got {topk}")
        mix.cfg = dataclasses.replace(mix.cfg, topk=topk, renormalize=rec.renormalize, penalty=rec.penalty,
                                      bake_res=rec.bake_res)
        mix.penalty = penalty_weights(mix.m, rec.penalty, device=mix.penalty.device)
    settings = RenderSettings(step=mix.cfg.step, near=scene.near, far=scene.far, bbox=mix.bbox,
                              background=scene.background, color_threshold=rec.train.color_threshold, ndc=scene.ndc)
    task = MixtureTask(mix, settings, rec.train, rec)
    signature = {"stage": "finetune", "model": name, "from": source, "iters": rec.iters, "seed": rec.seed,
                 "topk": mix.cfg.topk, "renormalize": mix.cfg.renormalize, "penalty": mix.cfg.penalty}
    defaults = MixtureConfig()
    for key in ("mix", "aux_norm", "aux_samples"):  # named only when not the default: older checkpoints still resume
        if getattr(mix.cfg, key) != getattr(defaults, key):
            signature[key] = getattr(mix.cfg, key)
    result = train(task, train_rays(scene, mix.bbox, device), sched, rec.seed, name, checkpoint=ws.checkpoint_path(name),
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


def _baseline(ws: Workspace, scene: Scene, mix: Mixture, rec: MoERecipe, sched: Schedule, device: str,
              log: Callable[[str], None], source: str | None) -> dict:
    """The largest expert alone, trained for the same finetuning iterations and schedule."""
    largest = mix.cfg.expert_names[-1]
    model, occ, meta = load_expert(ws.expert_path(largest), device)
    model.train()
    settings = RenderSettings(step=meta["step"], near=scene.near, far=scene.far, bbox=model.bbox,
                              background=scene.background, color_threshold=rec.train.color_threshold, ndc=scene.ndc)
    task = FieldTask(model, settings, rec.train, skip=occ, base_mask=occ)
    result = train(task, train_rays(scene, model.bbox, device), sched, rec.seed, "baseline",
                   checkpoint=ws.checkpoint_path("baseline"),
                   signature={"stage": "finetune", "model": "baseline", "from": source, "iters": rec.iters,
                              "seed": rec.seed}, data_parallel=True)
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
