"""Can any spatial partition of single models beat the best of them on views it has not seen?

A Top-1 mixture renders each sample with one expert, chosen by where the sample is. It can only beat its largest
expert if some other expert renders some part of the scene better, on views none of them trained on, and if the
parts where that holds are the same from view to view. This script measures that directly, without a gate and
without joint training: it takes models trained alone (each workspace's `baseline`, or any model name), renders
held-out views with every one of them at the same sample positions, splats each model's per-pixel squared error
back along the ray (by the models' mean rendering weight) into a map_res^3 lattice over the box, and routes every
sample to the model with the lowest error in its cell. Each lattice is chosen on one set of views and scored on
another:

    chosen on the training views    what a gate trained on the photometric loss could at best learn
    chosen on the even held-out views, scored on the odd ones (and the reverse)
                                     a partition that generalises across unseen views
    chosen on the scored views      an upper bound (it has seen the answer)

Controls: each model alone at the common sample positions (the finest model's step), and a random partition
with the held-out choice's proportions (what the seams between models cost). Prints one JSON document.

    python research/partition_oracle.py --model NAME=WORKSPACE [--model NAME=WORKSPACE ...] [--map-res 16,32]
        [--train-views 24] [--out FILE] [--device cuda]

NAME=WORKSPACE names a model (`baseline`, `dvgo-80`, ...) of a workspace; give them smallest first. A baseline is
labelled by the expert it was trained on (dvgo-80). Every workspace must be of one scene, with one box.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.metrics.image import psnr, ssim
from boostnerf_cli.models import LoadedModel, load_model
from boostnerf_cli.render.rays import image_rays
from boostnerf_cli.render.renderer import RenderSettings, render_rays, sample_rays
from boostnerf_cli.stages.common import resolve_device
from boostnerf_cli.workspace import Workspace, read_meta


def cells(xyz: Tensor, bbox: Tensor, res: int) -> Tensor:
    """(N, 3) points -> (N,) flat index of their cell in a res^3 lattice over `bbox`."""
    u = ((xyz - bbox[0]) / (bbox[1] - bbox[0]) * res).long().clamp(0, res - 1)
    return (u[:, 0] * res + u[:, 1]) * res + u[:, 2]


class Routed:
    """A Field that renders each sample with one model, chosen by its cell of `route` (res^3,) ints."""

    def __init__(self, models: list[LoadedModel], route: Tensor, bbox: Tensor):
        device = models[0].bbox.device
        self.models, self.route, self.bbox = models, route.to(device), bbox.to(device)
        self.res = round(route.numel() ** (1 / 3))

    def which(self, xyz: Tensor) -> Tensor:
        return self.route[cells(xyz, self.bbox, self.res)]

    def _run(self, xyz: Tensor, call, dim: int) -> Tensor:
        out = xyz.new_zeros(xyz.shape[0], dim)
        idx = self.which(xyz)
        for e, model in enumerate(self.models):
            rows = (idx == e).nonzero().squeeze(-1)
            if rows.numel():
                out[rows] = call(model.field, rows).reshape(rows.numel(), dim).to(out.dtype)
        return out

    def density(self, xyz: Tensor) -> Tensor:
        return self._run(xyz, lambda f, r: f.density(xyz[r]), 1)[:, 0]

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        return self._run(xyz, lambda f, r: f.color(xyz[r], dirs[r]), 3)

    def skip(self, xyz: Tensor) -> Tensor:
        """Each sample passes its own model's empty-space filter."""
        keep = torch.ones(xyz.shape[0], dtype=torch.bool, device=xyz.device)
        idx = self.which(xyz)
        for e, model in enumerate(self.models):
            rows = (idx == e).nonzero().squeeze(-1)
            if rows.numel() and model.skip is not None:
                keep[rows] = model.skip(xyz[rows])
        return keep


@torch.no_grad()
def render(field, skip, split, i: int, settings: RenderSettings) -> tuple[Tensor, Tensor]:
    """View i -> colour (H*W, 3), weights (H*W, S), on the CPU (rendered where the field is)."""
    o, d = image_rays(split.poses[i], split.intrinsics[i], split.height, split.width, settings.ndc)
    device = field.bbox.device
    b = render_rays(field, o.to(device), d.to(device), settings, skip)
    return b.color.clamp(0, 1).cpu(), b.extras["weights"].cpu()


@torch.no_grad()
def splat(models: list[LoadedModel], split, views: list[int], settings: RenderSettings, bbox: Tensor,
          resolutions: list[int]) -> dict[int, tuple[Tensor, Tensor]]:
    """-> {res: ((M, res^3) per-cell error of each model on `views`, (res^3,) rendering weight)}: each model's per-pixel
    squared error spread along the ray by the models' mean rendering weight, divided by that weight's total in the
    cell (inf where no view saw the cell). Each view is rendered once for every lattice."""
    err = {res: torch.zeros(len(models), res**3, dtype=torch.float64) for res in resolutions}
    mass = {res: torch.zeros(res**3, dtype=torch.float64) for res in resolutions}
    for i in views:
        gt = split.images[i].reshape(-1, 3)
        outs = [render(m.field, m.skip, split, i, settings) for m in models]
        o, d = image_rays(split.poses[i], split.intrinsics[i], split.height, split.width, settings.ndc)
        _, valid, xyz, _ = sample_rays(o, d, settings, jitter=False, fit=True)  # the slots render_rays used
        w = torch.stack([wt for _, wt in outs]).mean(0)  # (R, S)
        where = valid & (w > 1e-4)
        ws = w[where].double()
        pix = [((rgb - gt) ** 2).mean(-1).double()[:, None].expand_as(w)[where] for rgb, _ in outs]  # per sample
        for res in resolutions:
            c = cells(xyz[where], bbox, res)
            mass[res].index_add_(0, c, ws)
            for e, p in enumerate(pix):
                err[res][e].index_add_(0, c, ws * p)
    return {res: (torch.where(mass[res] > 0, err[res] / mass[res].clamp_min(1e-30),
                              torch.full_like(err[res], float("inf"))), mass[res]) for res in resolutions}


def pooled(odd: dict, even: dict, n_odd: int, n_even: int, key: str) -> float:
    """The mean PSNR (or SSIM) over all held-out views from the means over the odd and the even ones."""
    return (odd[key] * n_odd + even[key] * n_even) / (n_odd + n_even)


@torch.no_grad()
def score(field, skip, split, views: list[int], settings: RenderSettings) -> dict:
    rows = []
    for i in views:
        rgb, _ = render(field, skip, split, i, settings)
        pred = rgb.reshape(split.height, split.width, 3)
        rows.append((psnr(pred, split.images[i]), ssim(pred, split.images[i])))
    return {"psnr": round(sum(r[0] for r in rows) / len(rows), 4),
            "ssim": round(sum(r[1] for r in rows) / len(rows), 5)}


def choose(err: Tensor, default: int) -> Tensor:
    """Each cell's lowest-error model; cells no view saw go to `default`."""
    seen = torch.isfinite(err).all(0)
    return torch.where(seen, err.argmin(0), torch.full_like(seen, default, dtype=torch.long))


def shares(route: Tensor, weight: Tensor, m: int) -> list[float]:
    """How much of the rendering weight (`weight`, per cell) each model's cells hold."""
    total = float(weight.sum()) or 1.0
    return [round(float(weight[route == e].sum()) / total, 4) for e in range(m)]


def model_spec(text: str) -> tuple[str, str]:
    """--model NAME=WORKSPACE -> (NAME, WORKSPACE)."""
    name, sep, root = text.partition("=")
    if not (sep and name and root):
        raise argparse.ArgumentTypeError(f"{text!r}: give NAME=WORKSPACE, e.g. baseline=OUT/oracle-80")
    return name, root


def lattices(text: str) -> list[int]:
    """--map-res 16,32 -> [16, 32]."""
    try:
        values = [int(r) for r in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(1 <= v <= 256 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: give lattice sizes from 1 to 256, comma-separated, e.g. 16,32")
    return values


def positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give a whole number of at least 1")
    return value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", action="append", required=True, type=model_spec,
                    help="NAME=WORKSPACE, smallest model first (at least two)")
    ap.add_argument("--map-res", default=[16, 32], type=lattices, help="lattice resolutions, comma-separated")
    ap.add_argument("--train-views", type=positive, default=24, help="training views the training-view choice reads")
    ap.add_argument("--seed", type=int, default=0, help="the random partition's draw")
    ap.add_argument("--out", type=Path, help="also write the JSON here")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the models render")
    args = ap.parse_args()
    if len(args.model) < 2:
        ap.error("give at least two --model NAME=WORKSPACE to partition between")
    device = resolve_device(args.device)  # cuda without a GPU: one line
    models, names = [], []
    scene = None
    for name, root in args.model:
        ws = Workspace(Path(root))
        scene = scene or Survey(ws).scene()
        models.append(load_model(ws, name, device))
        # a workspace's baseline is its largest expert trained on: named by that expert (dvgo-80)
        label = read_meta(ws.model_file(name)).get("from", name) if name == "baseline" else name
        names.append(label if label not in names else f"{label}@{Path(root).name}")
    bbox = models[0].bbox.cpu()
    for m in models[1:]:
        if not torch.allclose(m.bbox.cpu(), bbox, atol=1e-4):
            sys.exit(f"error: {m.name} has another box ({m.bbox.tolist()} against {bbox.tolist()}): "
                     "give models of one box")
    step = min(m.step for m in models)
    settings = scene.render_settings(step, bbox)
    test, train = scene.split("test"), scene.split("train")
    if len(test) < 2:
        sys.exit(f"error: the scene holds out {len(test)} view(s); the cells are chosen on one half of the held-out "
                 "views and scored on the other, so it needs at least 2 (pretrain with --holdout-every 8, or a test "
                 "split)")
    even, odd = list(range(0, len(test), 2)), list(range(1, len(test), 2))
    train_views = list(range(0, len(train), max(1, len(train) // args.train_views)))[: args.train_views]
    t0 = time.time()
    out = {"inputs": names, "step": step, "test_views": len(test), "train_views": train_views,
           "alone": {}, "maps": {}}
    n_odd, n_even = len(odd), len(even)

    def halves(route_for_odd: Tensor, route_for_even: Tensor | None = None) -> dict:
        """A route's scores on the odd and the even views (another route for the even ones), and over all."""
        s_odd = score(*_field(models, route_for_odd, bbox), test, odd, settings)
        s_even = score(*_field(models, route_for_odd if route_for_even is None else route_for_even, bbox), test,
                       even, settings)
        return {"odd": s_odd, "even": s_even, "psnr": round(pooled(s_odd, s_even, n_odd, n_even, "psnr"), 4)}

    for e, m in enumerate(models):
        s_odd, s_even = (score(m.field, m.skip, test, views, settings) for views in (odd, even))
        out["alone"][names[e]] = {"even": s_even, "odd": s_odd, "all": {
            "psnr": round(pooled(s_odd, s_even, n_odd, n_even, "psnr"), 4),
            "ssim": round(pooled(s_odd, s_even, n_odd, n_even, "ssim"), 5)}}
    largest = len(models) - 1
    gen = torch.Generator().manual_seed(args.seed)
    resolutions = args.map_res
    on_even, on_odd, on_train = (splat(models, split, views, settings, bbox, resolutions)
                                 for split, views in ((test, even), (test, odd), (train, train_views)))
    for res in resolutions:
        (err_even, mass_even), (err_odd, mass_odd), (err_train, _) = on_even[res], on_odd[res], on_train[res]
        mass = mass_even + mass_odd  # the held-out views' rendering weight in each cell
        row = {}
        for label, route_for_odd, route_for_even in (
            ("training views", choose(err_train, largest), None),
            ("the other held-out half", choose(err_even, largest), choose(err_odd, largest)),
            ("the scored views (upper bound)", choose(err_odd, largest), choose(err_even, largest)),
        ):
            row[label] = {**halves(route_for_odd, route_for_even), "cells": shares(route_for_odd, mass, len(models))}
        # seams: a random partition in the proportions of the held-out choice
        p = torch.tensor([max(v, 1e-6) for v in row["the other held-out half"]["cells"]])
        rand = torch.multinomial(p / p.sum(), res**3, replacement=True, generator=gen)
        row["random, the held-out proportions"] = {**halves(rand), "cells": shares(rand, mass, len(models))}
        out["maps"][str(res)] = row
        print(f"map {res}^3 done ({time.time() - t0:.0f} s)", file=sys.stderr)
    out["seconds"] = round(time.time() - t0)
    out.update(table(out))
    text = json.dumps(out, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


def table(out: dict) -> dict:
    """The result as a generic table of scripts/tables.py ({"columns", "rows"}): each model alone, then each lattice's
    choices, every PSNR and SSIM over all held-out views, against the largest model alone."""
    names = out["inputs"]
    n_odd, n_even = out["test_views"] // 2, out["test_views"] - out["test_views"] // 2

    def both(r: dict, key: str) -> float:
        return pooled(r["odd"], r["even"], n_odd, n_even, key)

    top = both(out["alone"][names[-1]], "psnr")

    def row(model: str, res: str, label: str, r: dict, shares: str) -> list[str]:
        return [model, res, label, f"{both(r, 'psnr'):.3f}", f"{both(r, 'psnr') - top:+.2f}", f"{both(r, 'ssim'):.4f}",
                shares]

    rows = [row(f"{name} alone", "-", "-", r, "-") for name, r in out["alone"].items()]
    for res, choices in out["maps"].items():
        rows += [row("partition", f"{res}^3", label, r, " / ".join(f"{c:.2f}" for c in r["cells"]))
                 for label, r in choices.items()]
    return {"columns": ["model", "cells", "models chosen on", "PSNR", f"vs {names[-1]} alone", "SSIM",
                        "rendering weight per model"], "rows": rows}


def _field(models, route, bbox):
    f = Routed(models, route, bbox)
    return f, f.skip


if __name__ == "__main__":
    try:
        main()
    except BoostNerfError as e:  # a missing workspace or model, a scene without a test split: one line
        sys.exit(f"error: {e}")
