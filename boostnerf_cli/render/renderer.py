"""Render rays through any Field: fixed-step sampling, skipping, compositing, chunked images.

Two passes per batch of rays:
1. density pass: samples at a fixed step inside the scene box, minus those the skip filter (an
   occupancy grid or the mixture's density volume) marks empty, go through `field.density`; a skip
   with a `visible` filter (a mixture's, moe.vd_filter: visible) filters along the rays instead, and also
   drops samples it hides;
2. colour pass: only samples whose rendering weight exceeds `color_threshold` go through
   `field.color`. This drops samples behind terminated rays (their transmittance, hence weight,
   is ~0) and samples in near-empty space, which together hold almost none of the pixel's colour.
Setting both skips off (`skip=None`, `color_threshold=0`) evaluates every sample in the box.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import torch
from torch import Tensor

from boostnerf_cli import flops
from boostnerf_cli.fields.base import Field
from boostnerf_cli.render.rays import NDC, image_rays, intersect_box
from boostnerf_cli.render.volrend import composite, render_weights


@dataclass(frozen=True)
class RenderSettings:
    """How rays are sampled and which samples are skipped."""

    step: float  # world units between samples
    near: float
    far: float
    bbox: Tensor  # (2, 3)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    color_threshold: float = 1e-4  # weight below which a sample's colour is not computed
    max_samples: int = 1024  # per ray; the step grows if a ray would need more (never with Scene.render_settings)
    chunk: int = 8192  # rays per chunk when rendering whole images
    ndc: NDC | None = None  # forward-facing scenes: camera rays are warped to NDC (step, near, far, bbox in NDC)


@dataclass
class RayBundle:
    color: Tensor  # (R, 3)
    depth: Tensor  # (R,)
    acc: Tensor  # (R,)
    n_samples: int  # samples evaluated by the density pass
    n_color: int  # samples evaluated by the colour pass
    extras: dict


def sample_rays(
    origins: Tensor, dirs: Tensor, settings: RenderSettings, jitter: bool
) -> tuple[Tensor, Tensor, Tensor, float]:
    """Fixed-step samples inside the box.

    -> t (R, S) sample distances, valid (R, S) bool, xyz (R, S, 3), step used.
    Samples sit at t_enter + (j + u) * step with u = 0.5 (or one uniform draw per ray when jitter).
    """
    bbox = settings.bbox.to(origins.device)
    t0, t1, hit = intersect_box(origins, dirs, bbox, settings.near, settings.far)
    span = torch.where(hit, t1 - t0, torch.zeros_like(t0))
    longest = float(span.max()) if span.numel() else 0.0
    step = max(settings.step, longest / settings.max_samples)
    n = max(1, int(torch.ceil(torch.tensor(longest / step)).item()))
    j = torch.arange(n, device=origins.device, dtype=origins.dtype)
    u = torch.rand_like(t0)[:, None] if jitter else torch.full_like(t0, 0.5)[:, None]
    t = t0[:, None] + (j[None, :] + u) * step
    valid = hit[:, None] & (t < t1[:, None])
    xyz = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    return t, valid, xyz, step


def render_rays(
    field: Field,
    origins: Tensor,
    dirs: Tensor,
    settings: RenderSettings,
    skip: Callable[[Tensor], Tensor] | None = None,
    jitter: bool = False,
    color_threshold: float | None = None,
) -> RayBundle:
    """Render a batch of rays (R, 3), (R, 3) through `field`; differentiable w.r.t. the field."""
    t, valid, xyz, step = sample_rays(origins, dirs, settings, jitter)
    r, s = t.shape
    if hasattr(field, "batch_view"):  # shares the density pass's work with the colour pass
        field = field.batch_view()
    thr = settings.color_threshold if color_threshold is None else color_threshold
    visible = getattr(skip, "visible", None)  # a filter along the rays (a mixture's MixtureSkip), else per point
    if skip is None or not valid.any():
        keep = valid
    elif visible is not None:
        keep = visible(xyz, valid, step, thr)
    else:
        keep = valid.clone()
        keep[valid] = skip(xyz[valid])
    flat = keep.reshape(-1).nonzero().squeeze(-1)
    pts = xyz.reshape(-1, 3)[flat]
    sigma = torch.zeros(r * s, device=origins.device, dtype=origins.dtype)
    if flat.numel():
        sigma = sigma.index_put((flat,), field.density(pts).to(sigma.dtype))  # float32 under autocast too
    sigma = sigma.reshape(r, s)
    weights, _, _ = render_weights(sigma, torch.full_like(sigma, step))

    wk = weights.reshape(-1)[flat]
    sel = wk.detach() > thr if thr > 0 else torch.ones_like(wk, dtype=torch.bool)
    cflat = flat[sel]
    rgb = torch.zeros(r * s, 3, device=origins.device, dtype=origins.dtype)
    if cflat.numel():
        ray_of = cflat // s
        if hasattr(field, "color_rows"):  # reuses the density pass's work (routing, encoding)
            colors = field.color_rows(sel.nonzero().squeeze(-1), dirs[ray_of])
        else:
            colors = field.color(pts[sel], dirs[ray_of])
        rgb = rgb.index_put((cflat,), colors.to(rgb.dtype))
    rgb = rgb.reshape(r, s, 3)
    color, depth, acc = composite(weights, rgb, t, settings.background)
    flops.add("composite", flops.COMPOSITE_FLOPS * r * s)
    # rows: the density pass's samples (indices into the flattened (R, S) samples, in the order `field.density`
    # saw them); step: the sampling step used
    return RayBundle(color, depth, acc, int(flat.numel()), int(cflat.numel()),
                     {"weights": weights, "t": t, "rgb": rgb, "rows": flat, "step": step})


@torch.no_grad()
def render_image(
    field: Field,
    pose: Tensor,
    intrinsics: Tensor,
    height: int,
    width: int,
    settings: RenderSettings,
    skip: Callable[[Tensor], Tensor] | None = None,
    color_threshold: float | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, Tensor | int]:
    """Render one image in chunks of `settings.chunk` rays (bounded memory).

    -> {"rgb": (H, W, 3), "depth": (H, W), "acc": (H, W), "n_samples": int, "n_color": int}
    """
    origins, dirs = image_rays(pose, intrinsics, height, width, settings.ndc)
    origins, dirs = origins.to(device), dirs.to(device)
    parts = []
    n_samples = n_color = 0
    for i in range(0, origins.shape[0], settings.chunk):
        b = render_rays(field, origins[i : i + settings.chunk], dirs[i : i + settings.chunk], settings, skip,
                        color_threshold=color_threshold)
        parts.append((b.color, b.depth, b.acc))
        n_samples += b.n_samples
        n_color += b.n_color
    color, depth, acc = (torch.cat(p).cpu() for p in zip(*parts))
    return {
        "rgb": color.reshape(height, width, 3).clamp(0, 1),
        "depth": depth.reshape(height, width),
        "acc": acc.reshape(height, width),
        "n_samples": n_samples,
        "n_color": n_color,
    }


class Views(Protocol):
    """Posed cameras of one size, e.g. a dataset split: poses (N, 4, 4), intrinsics (N, 3, 3)."""

    poses: Tensor
    intrinsics: Tensor
    height: int
    width: int


def render_view(field: Field, views: Views, i: int, settings: RenderSettings,
                skip: Callable[[Tensor], Tensor] | None = None, device: torch.device | str = "cpu") -> dict:
    """`render_image` of camera `i` of `views` (a dataset split)."""
    return render_image(field, views.poses[i], views.intrinsics[i], views.height, views.width, settings, skip,
                        device=device)
