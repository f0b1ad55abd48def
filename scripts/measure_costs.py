"""Measure, side by side in one process, the cost targets of docs/benchmarks.md on a trained workspace.

    python scripts/measure_costs.py --workspace WS [--mixture top1] [--views 3] [--steps 12] [--threads 2]

Writes WS/reports/costs.json and prints a summary. Four measurements, each alternating its
variants (A B A B ...) so that a noisy machine slows both alike; the figures are medians.

1. skips: the largest expert (and the finetuned `baseline` and `--mixture`, when present) render the
   first `--views` held-out views with every skip on, and the largest expert also with every skip
   off (`--no-skip`: dense fixed-step samples over the model's box, every sample through density and
   colour). Reported: seconds per image and PSNR of each; the speed-up of skips on the largest expert.
2. step: one pretraining-style training step of the largest expert (sampling, skip filters, density
   and colour passes, compositing, loss, backward, NaN guard, fused Adam), against the bare forward and
   backward of its density and colour on exactly the samples that step evaluated. Reported: the ratio
   bare / step (the share of the step spent in the model's own grid interpolation and MLP).
3. mixture overhead: one finetuning step of `--mixture` (loss, backward, optimiser), against the
   mixture's own machinery run forward and backward on the samples of that step: the gate (grid
   lookup, MLP, softmax), top-k, the auxiliary loss, and the dispatch and gather (sort by expert,
   row gathers, weighted index_add) with the experts replaced by a 3 -> out linear map so that only the
   routing bookkeeping is timed. Reported: overhead / step.
4. shared work (experts with a per-batch view, e.g. NGP): a pretraining step of the largest expert
   through its view (each sample encoded once for both passes) against the same step through the
   bare Field protocol (the colour pass encodes its samples again), alternated on the same batches.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from boostnerf_cli.fields.base import BareField
from boostnerf_cli.lineage import Survey
from boostnerf_cli.metrics import mse_to_psnr
from boostnerf_cli.models import Skips, load_expert, load_mixture, load_model
from boostnerf_cli.moe.mixture import RoutedMixture
from boostnerf_cli.moe.router import Routes, aux_loss, dispatch, top_k
from boostnerf_cli.recipe import Recipe, recipe_from_dict
from boostnerf_cli.render.renderer import render_view
from boostnerf_cli.tasks import FieldTask, MixtureTask, train_rays
from boostnerf_cli.train import batch_gradients, grads_finite, make_optimizer
from boostnerf_cli.workspace import Workspace, write_json


def timed(fn, *args):
    """-> (seconds, fn(*args))"""
    t0 = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t0, out


def measure_skips(ws: Workspace, scene, names: list[str], views: int, device: str) -> dict:
    split = scene.split("test")
    n = min(views, len(split))
    variants = [(name, True) for name in names] + [(names[0], False)]
    models = {name: load_model(ws, name, device) for name in names}
    secs = {v: [] for v in variants}
    psnr = {v: [] for v in variants}
    for i in range(n):
        # rotate the order view by view: no variant always runs right after the slow skips-off render
        for name, skip in variants[i % len(variants):] + variants[:i % len(variants)]:
            model = models[name]
            settings, skip_fn = model.render_setup(scene, Skips() if skip else Skips.from_flags(no_skip=True))
            t, out = timed(render_view, model.field, split, i, settings, skip_fn, device)
            secs[(name, skip)].append(t)
            psnr[(name, skip)].append(mse_to_psnr(float(torch.mean((out["rgb"] - split.images[i]) ** 2))))
    rows = [{"model": name, "skips": "on" if skip else "off",
             "seconds_per_image": statistics.median(secs[(name, skip)]), "psnr": sum(psnr[(name, skip)]) / n}
            for name, skip in variants]
    on, off = rows[0], rows[-1]
    return {"views": n, "rows": rows, "speedup": off["seconds_per_image"] / on["seconds_per_image"],
            "psnr_drop": off["psnr"] - on["psnr"]}


class Recorder:
    """Wraps a field and keeps the inputs of its last density and colour calls.

    A field with a per-batch view (`batch_view`, e.g. an NGP expert) is recorded through it, so the
    step measured is the one training runs: the colour pass then records the rows it reuses.
    """

    def __init__(self, field):
        self.field, self.pts, self.cpts, self.cdirs, self.rows = field, None, None, None, None
        if hasattr(field, "batch_view"):
            self.batch_view = lambda packer=None: _RecordingView(self, field.batch_view(packer))

    def density(self, xyz):
        self.pts, self.rows = xyz.detach(), None
        return self.field.density(xyz)

    def color(self, xyz, dirs):
        self.cpts, self.cdirs = xyz.detach(), dirs.detach()
        return self.field.color(xyz, dirs)

    def regularization(self):
        return self.field.regularization()


class _RecordingView:
    def __init__(self, rec: Recorder, view):
        self.rec, self.view = rec, view

    def density(self, xyz, live=None):
        self.rec.pts = xyz.detach()
        return self.view.density(xyz, live)

    def color_rows(self, rows, dirs, live=None):
        self.rec.rows, self.rec.cpts, self.rec.cdirs = rows, self.rec.pts[rows], dirs.detach()
        return self.view.color_rows(rows, dirs, live)


def _train_step(task, opt, rays, batch: int, gen: torch.Generator) -> None:
    """The body of train.train's loop (without its logging and checkpoints), through its own pieces."""
    idx = torch.randint(0, len(rays), (batch,), generator=gen).to(rays.origins.device)
    opt.zero_grad(set_to_none=True)
    learnable, loss_bad, _ = batch_gradients(task, rays, idx, 0)
    if learnable and not bool(loss_bad) and bool(grads_finite([p for g in opt.param_groups for p in g["params"]])):
        opt.step()


def _bare_step(model, pts, cpts, cdirs, rows=None) -> None:
    """The model's own work in a step: density and colour forward and backward on the step's samples
    (through its per-batch view when the step used one: `rows` are then the colour pass's rows)."""
    if rows is None:
        (model.density(pts).sum() + model.color(cpts, cdirs).sum()).backward()
    else:
        view = model.batch_view()
        (view.density(pts).sum() + view.color_rows(rows, cdirs).sum()).backward()


def _gate_part(mix, pts):
    """Gate (grid, MLP, softmax), top-k and the auxiliary loss, forward and backward -> routing."""
    probs = mix.gate.probs(pts)
    vals, idx = top_k(probs, mix.cfg.topk, mix.cfg.renormalize)
    (vals.sum() + aux_loss(probs, idx, mix.penalty)).backward()
    return idx, vals.detach().requires_grad_()


def _dispatch_part(m, pts, rows, idx, vals, lin1, lin3) -> None:
    """Dispatch and gather of both passes with stand-in experts (a 3 -> out linear map), forward and backward."""
    d = dispatch(Routes(vals, idx, m), lambda e, r: lin1(pts[r]), 1, pts)
    xr = pts[rows]  # as RoutedMixture.color_rows does
    c = dispatch(Routes(vals[rows], idx[rows], m), lambda e, r: lin3(xr[r]), 3, pts)
    (d.sum() + c.sum()).backward()


def _expert_tasks(ws: Workspace, scene, rec: Recipe, expert: str, device: str, wrappers: dict) -> tuple:
    """`expert` in training mode and, per name in `wrappers`, a pretraining task on `wrap(expert)`
    (its occupancy grid, render settings and schedule as pretrain sets them) -> (expert, tasks)."""
    model, occ, meta = load_expert(ws.expert_path(expert), device)
    model.train()
    tcfg = rec.pretrain.train
    settings = scene.render_settings(meta["step"], model.bbox, tcfg.color_threshold)
    tasks = {}
    for name, wrap in wrappers.items():
        tasks[name] = FieldTask(wrap(model), settings, tcfg, skip=occ, base_mask=occ)
        tasks[name].param_groups = lambda: model.param_groups(tcfg.lr_grid, tcfg.lr_mlp)
    return model, tasks


def measure_step(ws: Workspace, scene, rec: Recipe, expert: str, steps: int, device: str) -> dict:
    tcfg = rec.pretrain.train
    model, tasks = _expert_tasks(ws, scene, rec, expert, device, {"step": Recorder})
    task = tasks["step"]
    rec_model = task.model
    opt = make_optimizer(task)
    rays = train_rays(scene, model.bbox, device, tcfg)
    gen = torch.Generator().manual_seed(0)
    step_s, bare_s, samples = [], [], []
    for i in range(steps + 2):
        t_step, _ = timed(_train_step, task, opt, rays, tcfg.batch_rays, gen)
        pts, cpts, cdirs = rec_model.pts, rec_model.cpts, rec_model.cdirs
        opt.zero_grad(set_to_none=True)
        t_bare, _ = timed(_bare_step, model, pts, cpts, cdirs, rec_model.rows)
        opt.zero_grad(set_to_none=True)
        if i >= 2:  # warm-up
            step_s.append(t_step)
            bare_s.append(t_bare)
            samples.append((pts.shape[0], cpts.shape[0]))
    step, bare_t = statistics.median(step_s), statistics.median(bare_s)
    return {"expert": expert, "batch_rays": tcfg.batch_rays, "steps": steps,
            "density_samples": statistics.median(s[0] for s in samples),
            "color_samples": statistics.median(s[1] for s in samples),
            "step_seconds": step, "bare_seconds": bare_t, "throughput_ratio": bare_t / step}


def measure_view(ws: Workspace, scene, rec: Recipe, expert: str, steps: int, device: str) -> dict | None:
    """A pretraining step of `expert` through its per-batch view against the same step through the
    bare Field protocol, alternated; None when the expert has no per-batch view."""
    tcfg = rec.pretrain.train
    model, tasks = _expert_tasks(ws, scene, rec, expert, device, {"view": lambda m: m, "plain": BareField})
    if not hasattr(model, "batch_view"):
        return None
    opt = make_optimizer(tasks["view"])
    rays = train_rays(scene, model.bbox, device, tcfg)
    gens = {name: torch.Generator().manual_seed(0) for name in tasks}  # the same batches for both
    secs: dict[str, list[float]] = {name: [] for name in tasks}
    for i in range(steps + 2):
        for name, task in tasks.items():
            t, _ = timed(_train_step, task, opt, rays, tcfg.batch_rays, gens[name])
            if i >= 2:
                secs[name].append(t)
    view, plain = statistics.median(secs["view"]), statistics.median(secs["plain"])
    return {"expert": expert, "steps": steps, "view_step_seconds": view, "plain_step_seconds": plain,
            "speedup": plain / view}


def measure_mixture(ws: Workspace, scene, rec: Recipe, name: str, steps: int, device: str) -> dict:
    mix, _ = load_mixture(ws.model_path(name), device)
    mix.train()
    m = mix.m
    settings = scene.render_settings(mix.cfg.step, mix.bbox, rec.moe.train.color_threshold)
    task = MixtureTask(mix, settings, rec.moe.train, rec.moe)
    opt = make_optimizer(task)
    rays = train_rays(scene, mix.bbox, device, rec.moe.train)
    gen = torch.Generator().manual_seed(0)
    captured = {}
    orig_density, orig_color_rows = RoutedMixture.density, RoutedMixture.color_rows

    def density(self, xyz, live=None):  # keeps the samples of the density pass
        captured["pts"] = xyz.detach()
        return orig_density(self, xyz, live)

    def color_rows(self, rows, dirs, live=None):
        captured["rows"], captured["dirs"] = rows.detach(), dirs.detach()
        return orig_color_rows(self, rows, dirs, live)

    RoutedMixture.density, RoutedMixture.color_rows = density, color_rows
    lin1 = torch.nn.Linear(3, 1).to(device)
    lin3 = torch.nn.Linear(3, 3).to(device)
    step_s, over_s, parts = [], [], []
    try:
        for i in range(steps + 2):
            t_step, _ = timed(_train_step, task, opt, rays, rec.moe.train.batch_rays, gen)
            pts, rows = captured["pts"], captured["rows"]
            opt.zero_grad(set_to_none=True)
            t_gate, (idx, vals) = timed(_gate_part, mix, pts)
            t_disp, _ = timed(_dispatch_part, m, pts, rows, idx, vals, lin1, lin3)
            opt.zero_grad(set_to_none=True)
            if i >= 2:
                step_s.append(t_step)
                over_s.append(t_gate + t_disp)
                parts.append((t_gate, t_disp, pts.shape[0], rows.shape[0]))
    finally:
        RoutedMixture.density, RoutedMixture.color_rows = orig_density, orig_color_rows
    step, over = statistics.median(step_s), statistics.median(over_s)
    return {"mixture": name, "topk": mix.cfg.topk, "steps": steps, "step_seconds": step,
            "gate_topk_aux_seconds": statistics.median(p[0] for p in parts),
            "dispatch_gather_seconds": statistics.median(p[1] for p in parts),
            "density_samples": statistics.median(p[2] for p in parts),
            "color_samples": statistics.median(p[3] for p in parts),
            "overhead_seconds": over, "overhead_fraction": over / step}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--mixture", default="top1")
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--only", default="skips,step,view,mixture", help="comma-separated: skips, step, view, mixture")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    ws = Workspace(args.workspace)
    manifest = ws.require_manifest()
    rec = recipe_from_dict(manifest["recipe"]) if manifest.get("recipe") else Recipe()
    scene = Survey(ws).scene()
    largest = ws.expert_names()[-1]
    only = set(args.only.split(","))
    result = {"workspace": str(ws.root), "threads": args.threads, "torch": torch.__version__}
    if "skips" in only:
        names = [largest] + [n for n in ("baseline", args.mixture) if ws.model_path(n).exists()]
        result["skips"] = measure_skips(ws, scene, names, args.views, args.device)
        for r in result["skips"]["rows"]:
            print(f"render {r['model']:>10} skips {r['skips']:>3}: {r['seconds_per_image']:.3f} s/image, "
                  f"PSNR {r['psnr']:.3f}")
        print(f"skips speed-up {result['skips']['speedup']:.2f}x, PSNR drop {result['skips']['psnr_drop']:+.4f} dB")
    if "step" in only:
        s = result["step"] = measure_step(ws, scene, rec, largest, args.steps, args.device)
        print(f"step of {largest}: {s['step_seconds']:.3f} s, bare density+colour fwd+bwd {s['bare_seconds']:.3f} s "
              f"-> {100 * s['throughput_ratio']:.1f}% ({s['density_samples']} density, "
              f"{s['color_samples']} colour samples)")
    if "view" in only:
        v = result["view"] = measure_view(ws, scene, rec, largest, args.steps, args.device)
        if v is not None:
            print(f"step of {largest} through its per-batch view {v['view_step_seconds']:.3f} s, through the bare "
                  f"Field protocol {v['plain_step_seconds']:.3f} s -> {v['speedup']:.2f}x")
    if "mixture" in only and ws.model_path(args.mixture).exists():
        x = result["mixture"] = measure_mixture(ws, scene, rec, args.mixture, args.steps, args.device)
        print(f"{args.mixture} step {x['step_seconds']:.3f} s: gate+top-k+aux {x['gate_topk_aux_seconds']:.3f} s, "
              f"dispatch+gather {x['dispatch_gather_seconds']:.3f} s -> overhead {100 * x['overhead_fraction']:.1f}%")
    write_json(ws.reports_dir / "costs.json", result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
