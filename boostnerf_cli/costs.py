"""What a model costs: the paper's ||w||_0 and GFLOPs per rendered image.

||w||_0 (supplementary, "||w||_0 Computation"): freeze the model, render every view of the split,
compute the photometric loss, and count the parameters whose gradient is non-zero. For a sparse
mixture this counts only what the routing actually uses (`prune` keeps exactly these grid rows).
GFLOPs per image: matrix products counted by torch's FlopCounterMode plus the analytic counts of
`boostnerf_cli.flops` (interpolation, routing, compositing), averaged over the rendered views.
"""

from __future__ import annotations

from typing import Callable, TypeVar

import torch

from boostnerf_cli.flops import count_flops
from boostnerf_cli.models import ALL_SKIPS, LoadedModel, Skips, n_views
from boostnerf_cli.render.packing import DYNAMIC
from boostnerf_cli.render.rays import image_rays
from boostnerf_cli.render.renderer import render_rays, render_view
from boostnerf_cli.scenes import Scene, Split


def photometric_grads(field, skip, settings, split: Split, device: str, views: int | None = None,
                      extra: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor | None]:
    """Backpropagate the photometric loss of the first `views` views of `split` through a frozen field.

    -> {parameter name: its gradient (None when nothing reached it)}, also for the `extra` tensors
    (e.g. a buffer made to require a gradient); the gradients are taken off the tensors afterwards.
    """
    tensors = {**dict(field.named_parameters()), **(extra or {})}
    for t in tensors.values():
        t.grad = None
        t.requires_grad_(True)
    n = n_views(split, views)
    total_pixels = n * split.height * split.width
    for i in range(n):
        o, d = image_rays(split.poses[i], split.intrinsics[i], split.height, split.width, settings.ndc)
        gt = split.images[i].reshape(-1, 3).to(device)
        o, d = o.to(device), d.to(device)
        for j in range(0, o.shape[0], settings.chunk):
            b = render_rays(field, o[j : j + settings.chunk], d[j : j + settings.chunk], settings, skip)
            loss = ((b.color - gt[j : j + settings.chunk]) ** 2).sum() / total_pixels
            if loss.requires_grad:
                loss.backward()
    grads = {}
    for name, t in tensors.items():
        grads[name] = t.grad
        t.grad = None
    return grads


def active_parameters(model: LoadedModel, scene: Scene, split: Split, device: str, views: int | None = None) -> dict:
    """-> {"w0": int, "per_module": {name: w0}} from the gradient of the photometric loss."""
    grads = photometric_grads(model.field, model.skip, model.settings(scene), split, device, views)
    per_module: dict[str, int] = {}
    for name, g in grads.items():
        if g is not None and name in model.dropped:  # a row a pruned file does not store is a constant now
            g = g[~model.dropped[name].to(g.device)]
        nz = int((g != 0).sum()) if g is not None else 0
        top = _module(name)
        per_module[top] = per_module.get(top, 0) + nz
    return {"w0": sum(per_module.values()), "per_module": per_module}


def _module(name: str) -> str:
    """The part of a model a parameter belongs to: `experts.I` or the first name (`gate`, ...)."""
    return ".".join(name.split(".")[:2]) if name.startswith("experts.") else name.split(".")[0]


def _params(module: torch.nn.Module, prefix: str, dropped: dict[str, torch.Tensor]) -> int:
    """Parameters of `module` (named `prefix` in the model), less the rows a pruned file does not store."""
    params = dict(module.named_parameters())
    total = sum(p.numel() for p in params.values())
    for name, rows in dropped.items():
        if _module(name) == prefix:
            total -= int(rows.sum()) * params[name[len(prefix) + 1:]].shape[1]
    return total


T = TypeVar("T")


def gflops_of(work: Callable[[], T]) -> tuple[T, float]:
    """Run `work` counting its floating-point operations (matrix products and the analytic counts) -> (what it
    returned, GFLOPs)."""
    with count_flops() as fc:
        out = work()
    return out, fc.total / 1e9


@torch.no_grad()
def gflops_per_image(model: LoadedModel, scene: Scene, split: Split, device: str, views: int | None = None,
                     skips: Skips = ALL_SKIPS) -> float:
    settings, skip = model.render_setup(scene, skips)
    n = n_views(split, views)
    total = 0.0
    for i in range(n):  # exact packing: the samples the model evaluates, not a budget's pads
        total += gflops_of(lambda i=i: render_view(model.field, split, i, settings, skip, device, packer=DYNAMIC))[1]
    return total / max(1, n)


def model_costs(model: LoadedModel, scene: Scene, split: Split, device: str, views: int | None = None,
                exact_gate: bool = False, skips: Skips = ALL_SKIPS) -> dict:
    """||w||_0 and GFLOPs per image of `model`, loaded with its exact (trainable) gate.

    ||w||_0 is counted on the model as trained; then `model` is made ready to render in place (a
    mixture's gate baked unless `exact_gate`) and the GFLOPs are those of what render and eval run
    with `skips`.
    """
    active = active_parameters(model, scene, split, device, views)
    row = {"name": model.name, "kind": model.kind, "params": model.params, "w0": active["w0"]}
    if model.kind == "mixture":
        mix = model.field
        row["experts"] = [
            {"name": n, "params": _params(mix.experts[i], f"experts.{i}", model.dropped),
             "w0": active["per_module"].get(f"experts.{i}", 0)}
            for i, n in enumerate(mix.cfg.expert_names)
        ]
        row["gate"] = {"params": _params(mix.gate, "gate", model.dropped), "w0": active["per_module"].get("gate", 0)}
    ready = model.for_rendering(exact_gate)
    row["gflops_per_image"] = round(gflops_per_image(ready, scene, split, device, views, skips), 4)
    return row

