"""Render rays through any Field: fixed-step sampling, skipping, compositing, chunked images.

Two passes per batch of rays:
1. density pass: samples at a fixed step inside the scene box, minus those the skip filter (an
   occupancy grid or the mixture's density volume) marks empty, go through `field.density`; a skip
   with a `visible` filter (a mixture's, moe.vd_filter: visible) filters along the rays instead, and also
   drops samples it hides;
2. colour pass: only samples whose rendering weight exceeds `color_threshold` go through
   `field.color`. This drops samples behind terminated rays (their transmittance, hence weight,
   is ~0) and samples in near-empty space, which together hold almost none of the pixel's colour.
Setting both skips off (`skip=None`, `settings.color_threshold=0`) evaluates every sample in the box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Protocol

import torch
from torch import Tensor

from boostnerf_cli import flops
from boostnerf_cli.device import constant
from boostnerf_cli.fields import grid as G
from boostnerf_cli.fields.base import Field
from boostnerf_cli.render.contraction import Contraction
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.packing import DYNAMIC, Packer, packer_for
from boostnerf_cli.render.rays import NDC, image_rays, intersect_box
from boostnerf_cli.render.timing import part
from boostnerf_cli.render.volrend import composite, render_weights

# A sample whose rendering weight is at most this skips its colour (the two-pass renderer's second pass; DVGO's
# fast_color_thres): the renderer's default, train.color_threshold's and every rendered view's with the skip on.
COLOR_THRESHOLD = 1e-4


@dataclass(frozen=True)
class RenderSettings:
    """How rays are sampled and which samples are skipped."""

    step: float  # world units between samples
    near: float
    far: float
    bbox: Tensor  # (2, 3)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    color_threshold: float = COLOR_THRESHOLD  # weight below which a sample's colour is not computed
    # per ray; the step grows if the box's diagonal needs more (never with Scene.render_settings)
    max_samples: int = 1024
    chunk: int = 8192  # rays per chunk when rendering whole images
    ndc: NDC | None = None  # forward-facing scenes: camera rays are warped to NDC (step, near, far, bbox in NDC)
    # unbounded scenes: samples are placed and contracted by it (render/contraction.py; bbox: its box, far: its bound)
    contraction: Contraction | None = None

    # (samples per ray, step): as many samples as the box's diagonal holds at `step`, at most `max_samples` (the step
    # grows to fit). No ray crosses the box over a longer chord, so every ray of every batch has the same number of
    # sample slots and no batch waits to learn its longest ray.
    sampling: tuple[int, float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """Works out `sampling` when the settings are made, outside any step (the box is read from its device once),
        so that a compiled step finds it ready: worked out lazily inside a step, it stops the compiler there (Python
        3.11's cached_property takes a lock), which then runs that function eagerly for good."""
        if self.contraction is not None:  # the linear stretch, then the shell's depth
            c = self.contraction
            step = max(self.step, (max(2 * c.radius, c.reach) + c.radius) / self.max_samples)
            object.__setattr__(self, "sampling", (sum(self.contraction.slots(step)), step))
            return
        diagonal = float((self.bbox[1] - self.bbox[0]).norm())
        step = max(self.step, diagonal / self.max_samples)
        object.__setattr__(self, "sampling", (max(1, min(self.max_samples, math.ceil(diagonal / step) + 1)), step))


@dataclass
class RayBundle:
    color: Tensor  # (R, 3)
    depth: Tensor  # (R,)
    acc: Tensor  # (R,)
    n_samples: int | Tensor  # samples evaluated by the density pass (a device count with a static packer)
    n_color: int | Tensor  # samples evaluated by the colour pass
    extras: dict


def sample_rays(
    origins: Tensor, dirs: Tensor, settings: RenderSettings, jitter: bool, fit: bool = False
) -> tuple[Tensor, Tensor, Tensor, float]:
    """Fixed-step samples inside the box.

    -> t (R, S) sample distances, valid (R, S) bool, xyz (R, S, 3), step used (`RenderSettings.sampling`).
    Samples sit at t_enter + (j + u) * step with u = 0.5 (or one uniform draw per ray when jitter). S is the slots
    the box's diagonal needs, or with `fit` the slots this batch's longest ray needs (fewer samples, for one wait
    for the device: the CPU's way); the samples of a ray are the same either way.
    With `settings.contraction` (an unbounded scene) the samples are the contraction's (`Contraction.sample`: linear
    inside its sphere, even in disparity outside, to its far bound), xyz contracted points, and S always all slots.
    """
    n, step = settings.sampling
    if settings.contraction is not None:
        t, valid, xyz = settings.contraction.sample(origins, dirs, settings.near, step, jitter)
        return t, valid, xyz, step
    bbox = settings.bbox.to(origins.device)
    t0, t1, hit = intersect_box(origins, dirs, bbox, settings.near, settings.far)
    if fit and t0.numel():
        longest = float(torch.where(hit, t1 - t0, torch.zeros_like(t0)).max())
        n = max(1, min(n, math.ceil(longest / step)))
    j = torch.arange(n, device=origins.device, dtype=origins.dtype)
    u = torch.rand_like(t0)[:, None] if jitter else torch.full_like(t0, 0.5)[:, None]
    t = t0[:, None] + (j[None, :] + u) * step
    valid = hit[:, None] & (t < t1[:, None])
    xyz = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    return t, valid, xyz, step


# `sample_list` tests a ray's slots in runs of this many, by the run's middle, against the cells a skip may keep, where
# those cells, grown by half a run, are at most this share of the box (one thread: lego's baseline at 100 px, 64% of
# its box, renders 6.6% faster; the quickstart's, 98%, 4% slower, fern's, 96%, 3% slower)
SPAN = 8
SPARSE = 0.75


def sample_list(origins: Tensor, dirs: Tensor, settings: RenderSettings,
                keep: OccupancyGrid | None = None) -> tuple[Tensor, Tensor, Tensor, float]:
    """The samples `sample_rays(..., jitter=False, fit=True)` marks valid in a bounded scene, made as lists instead of
    an (R, S) grid most of whose slots lie outside the box: ray (K,) each sample's ray, t (K,), xyz (K, 3), in ray
    order and along each ray; the same values, bit for bit (the same operations on the same numbers), and the step.

    A ray's valid slots are a prefix (t grows with the slot), so each ray's count is worked out from its chord and
    checked against `t < t_exit` at its last slot and the one after, where float rounding may differ by one.

    `keep`: the cells outside which the skip keeps no sample (an occupancy grid; `keep_cells`). Where they, grown by
    half a run's length (`OccupancyGrid.grown`), fill at most `SPARSE` of the box, a ray's slots are taken in runs of
    `SPAN`, and a run is made only where its middle lies in the grown cells: every sample of a run left out lies in
    an empty cell of `keep`, which the skip would drop. The samples made are those the skip may keep, the same values
    as without `keep`: lego's baseline at 100 px makes 386k of an image's 628k samples, Top-1 316k."""
    n, step = settings.sampling
    bbox = settings.bbox.to(origins.device)
    t0, t1, hit = intersect_box(origins, dirs, bbox, settings.near, settings.far)
    half = torch.full((), 0.5, dtype=origins.dtype, device=origins.device)
    span = torch.where(hit, t1 - t0, torch.zeros_like(t0))
    count = torch.ceil(span / step - 0.5).clamp_(0, n)
    for _ in range(2):  # the estimate within one of the count: step down while the last slot is past the exit ...
        last = t0 + ((count - 1) + half) * step
        count = torch.where((count > 0) & ~(hit & (last < t1)), count - 1, count)
    for _ in range(2):  # ... and up while the next slot is still inside
        after = t0 + (count + half) * step
        count = torch.where((count < n) & hit & (after < t1), count + 1, count)
    count = count.long()
    grown = None
    if keep is not None and len(t0) and keep.fraction() <= SPARSE:  # growing them only fills more of the box
        # a run's samples lie within (SPAN - 1) / 2 steps of its middle, along each axis at most that far
        grown = keep.grown((SPAN - 1) / 2 * step * float(dirs.norm(dim=-1).max()))
    if grown is None or grown.fraction() > SPARSE:
        ray = torch.repeat_interleave(torch.arange(len(t0), device=origins.device), count)
        start = torch.cumsum(count, 0) - count
        j = (torch.arange(len(ray), device=origins.device) - start.index_select(0, ray)).to(origins.dtype)
    else:
        ray, j = _runs_kept(origins, dirs, t0, count, step, grown)
    t = t0.index_select(0, ray) + (j + half) * step
    # the rays of one pinhole camera share one origin (an expanded tensor): added as it is, not gathered per sample
    origin = origins[:1] if origins.stride(0) == 0 else origins.contiguous().index_select(0, ray)
    direction = dirs.contiguous().index_select(0, ray)
    if not G.by_axis(direction) or not t.dtype == origin.dtype == direction.dtype or (torch.is_grad_enabled() and (
            origin.requires_grad or direction.requires_grad)):  # (products written into place have no gradient)
        return ray, t, origin + t[:, None] * direction, step
    xyz = torch.empty_like(direction)  # axis by axis: products broadcast along the short last axis are slow here
    for a in range(3):
        torch.mul(t, direction[:, a], out=xyz[:, a]).add_(origin[:, a])
    return ray, t, xyz, step


def _runs_kept(origins: Tensor, dirs: Tensor, t0: Tensor, count: Tensor, step: float,
               grown: OccupancyGrid) -> tuple[Tensor, Tensor]:
    """`sample_list`'s slots in runs of `SPAN` whose middle lies in the cells `grown` (a skip's, grown by half a run):
    -> each slot's ray and its index along the ray (as a float), in ray order and along each ray."""
    device = origins.device
    runs = (count + (SPAN - 1)) // SPAN
    run_ray = torch.repeat_interleave(torch.arange(len(t0), device=device), runs)
    first = (torch.arange(len(run_ray), device=device) - (torch.cumsum(runs, 0) - runs).index_select(0, run_ray)) * SPAN
    size = (count.index_select(0, run_ray) - first).clamp_max_(SPAN)
    middle = t0.index_select(0, run_ray) + (first.to(t0.dtype) + size.to(t0.dtype) * 0.5) * step
    origin = origins[:1] if origins.stride(0) == 0 else origins.index_select(0, run_ray)
    pts = origin + middle[:, None] * dirs.index_select(0, run_ray)
    kept = grown.within(pts).nonzero().squeeze(-1)
    run_ray, first, size = run_ray.index_select(0, kept), first.index_select(0, kept), size.index_select(0, kept)
    ray = torch.repeat_interleave(run_ray, size)
    start = torch.repeat_interleave(torch.cumsum(size, 0) - size - first, size)  # each slot's run's start, less first
    return ray, (torch.arange(len(ray), device=device) - start).to(origins.dtype)


def kept_samples(skip, xyz: Tensor, valid: Tensor, step: float, threshold: float, packer: Packer) -> Tensor:
    """(R, S) the samples inside the box that `skip` keeps: a filter of points (an occupancy grid: called on every
    sample), or one with `filter` (a mixture's V_D, which packs its own work and may filter along the rays)."""
    if skip is None:
        return valid
    if hasattr(skip, "filter"):
        return skip.filter(xyz, valid, step, threshold, packer)
    return packer.keep_where(skip, xyz.reshape(-1, 3), valid.reshape(-1)).reshape(valid.shape)


def passing(skip, pts: Tensor, box: Tensor) -> Tensor:
    """(K,) bool: which of the samples `pts`, inside the render box `box`, a filter of points keeps: by its lookup for
    points inside its own box (`OccupancyGrid.within`) where its box holds `box`, else by its general one."""
    if hasattr(skip, "within"):
        own = skip.bbox.to(box.device)
        if bool((own[0] <= box[0]).all() and (own[1] >= box[1]).all()):
            return skip.within(pts)
    return skip(pts)


def kept_rows(skip, xyz: Tensor, valid: Tensor, step: float, threshold: float, box: Tensor) -> Tensor:
    """`kept_samples` on the dynamic packing, as the sorted list of the kept samples' rows of the flattened (R, S)
    samples: a filter with `filter_rows` lists them itself (a mixture's V_D), a filter of points tests the samples
    inside the box `box` (`passing`)."""
    if skip is not None and hasattr(skip, "filter_rows"):
        return skip.filter_rows(xyz, valid, step, threshold)
    if skip is None or hasattr(skip, "filter"):
        return kept_samples(skip, xyz, valid, step, threshold, DYNAMIC).reshape(-1).nonzero().squeeze(-1)
    rows = valid.reshape(-1).nonzero().squeeze(-1)
    return rows.index_select(0, passing(skip, xyz.reshape(-1, 3).index_select(0, rows), box).nonzero().squeeze(-1))


def render_rays(
    field: Field,
    origins: Tensor,
    dirs: Tensor,
    settings: RenderSettings,
    skip: Callable[[Tensor], Tensor] | None = None,
    jitter: bool = False,
    packer: Packer = DYNAMIC,
) -> RayBundle:
    """Render a batch of rays (R, 3), (R, 3) through `field`; differentiable w.r.t. the field. `packer`: how the
    kept samples are listed (render/packing.py); with a static one nothing here waits for the device, and
    `packer.overflowed()` says afterwards whether the result misses samples."""
    with part("sampling"):
        t, valid, xyz, step = sample_rays(origins, dirs, settings, jitter, fit=not packer.static)
    r, s = t.shape
    # a per-batch view shares the density pass's work with the colour pass, and is told which slots are pads
    view = field.batch_view(packer) if hasattr(field, "batch_view") else None
    thr = settings.color_threshold
    with part("skipping"):
        keep = kept_samples(skip, xyz, valid, step, thr, packer)
        dens = packer.pack("density", keep.reshape(-1))
        pts = xyz.reshape(-1, 3)[dens.rows]
    sigma = torch.zeros(r, s, device=origins.device, dtype=origins.dtype)
    if len(dens):  # none kept (dynamic packing): the rays see only the background, cut off from the field
        with part("field density"):
            sigma = view.density(pts, dens.live) if view is not None else field.density(pts)
        with part("compositing"):
            sigma = dens.scatter(sigma.to(origins.dtype)).reshape(r, s)  # float32 under autocast too
    with part("compositing"):
        contracted = settings.contraction is not None
        deltas = Contraction.deltas(xyz) if contracted else torch.full_like(sigma, step)
        weights, _, _ = render_weights(sigma, deltas)
        wk = weights.reshape(-1)[dens.rows]
        sel = dens.keep(wk.detach() > thr if thr > 0 else torch.ones_like(wk, dtype=torch.bool))
        col = packer.pack("color", sel)  # slots of the density pass
        cflat = dens.sub(col)  # the same samples, as rows of the (R, S) samples
        ray_of = torch.div(cflat.rows, s, rounding_mode="floor")
    rgb = torch.zeros(r, s, 3, device=origins.device, dtype=origins.dtype)
    if len(col):
        with part("field color"):
            if view is not None:
                colors = view.color_rows(col.rows, dirs[ray_of], col.live)
            else:
                colors = field.color(pts[col.rows], dirs[ray_of])
        with part("compositing"):
            rgb = cflat.scatter(colors.to(origins.dtype)).reshape(r, s, 3)
    with part("compositing"):
        color, depth, acc = composite(weights, rgb, t, settings.background)
    flops.add("composite", flops.COMPOSITE_FLOPS * r * s)
    # rows: the density pass's samples (indices into the flattened (R, S) samples, in the order `field.density`
    # saw them; with a static packer, `live` says which slots hold one); step: the sampling step used
    # deltas (unbounded scenes): each sample's contracted interval (`Contraction.deltas`), else `step` for all
    extras = {"weights": weights, "t": t, "rgb": rgb, "rows": dens.rows, "live": dens.live, "step": step}
    if contracted:
        extras["deltas"] = deltas
    return RayBundle(color, depth, acc, dens.count(), cflat.count(), extras)


def kept_of_list(skip, pts: Tensor, threshold: float, box: Tensor) -> Tensor | None:
    """Of the samples `pts` (K, 3) inside the box `box`, the indices of those `skip` keeps (all: None); a filter that
    needs the samples along their rays (`filter` without `filter_list`) is not asked here."""
    if skip is None:
        return None
    if hasattr(skip, "filter_list"):
        return skip.filter_list(pts, threshold)
    return passing(skip, pts, box).nonzero().squeeze(-1)


def keep_cells(skip, threshold: float) -> OccupancyGrid | None:
    """The cells outside which `skip` keeps no sample of a list (`kept_of_list`; `sample_list` makes no other): an
    occupancy grid's occupied cells, a mixture's cells its table does not fail (`MixtureSkip.keep_cells`); None where
    the skip has no such grid."""
    if isinstance(skip, OccupancyGrid):
        return skip
    cells = getattr(skip, "keep_cells", None)
    return cells(threshold) if cells is not None else None


def _listable(skip, settings: RenderSettings) -> bool:
    """Whether `render_rays_packed` can sample as lists (`sample_list`) and skip on them (`kept_of_list`)."""
    if settings.contraction is not None:
        return False
    return skip is None or not hasattr(skip, "filter") or (hasattr(skip, "lists") and skip.lists(
        settings.color_threshold))


def render_rays_packed(
    field: Field,
    origins: Tensor,
    dirs: Tensor,
    settings: RenderSettings,
    skip: Callable[[Tensor], Tensor] | None = None,
) -> RayBundle:
    """`render_rays` for rendering on the CPU (no gradient, the dynamic packing), composited over the kept samples
    only: the same colour, depth and opacity (to float32 rounding), without per-sample extras.

    Padded compositing works on every slot of the (R, S) samples (S the longest ray's), most of them skipped; here
    each ray's transmittance is an exclusive sum over its kept samples alone (a running sum over the list in float64,
    less its value at the ray's first sample), and colour, depth and opacity are sums over them per ray. The skipped
    slots add exactly nothing in the padded sums either. In a bounded scene, with a filter of points, the samples
    themselves are made as lists of those inside the box (`sample_list`), never as the (R, S) grid, and only in runs
    that reach a cell the filter may keep (`keep_cells`)."""
    r = origins.shape[0]
    thr = settings.color_threshold
    view = field.batch_view(DYNAMIC) if hasattr(field, "batch_view") else None
    delta: Tensor | float
    if _listable(skip, settings):
        with part("sampling"):
            ray, tk, pts, step = sample_list(origins, dirs, settings, keep_cells(skip, thr))
        with part("skipping"):
            kept = kept_of_list(skip, pts, thr, settings.bbox.to(pts.device))
            if kept is not None:
                ray, tk, pts = ray.index_select(0, kept), tk.index_select(0, kept), pts.index_select(0, kept)
        delta = step
    else:
        with part("sampling"):
            t, valid, xyz, step = sample_rays(origins, dirs, settings, jitter=False, fit=True)
        with part("skipping"):
            rows = kept_rows(skip, xyz, valid, step, thr, settings.bbox.to(xyz.device))  # in ray order, along each ray
            pts = xyz.reshape(-1, 3).index_select(0, rows)
            ray = torch.div(rows, t.shape[1], rounding_mode="floor")
            tk = t.reshape(-1).index_select(0, rows)
            delta = Contraction.deltas(xyz).reshape(-1).index_select(0, rows) if settings.contraction is not None \
                else step
    color = origins.new_zeros(r, 3)
    depth, acc = origins.new_zeros(r), origins.new_zeros(r)
    n_color = 0
    if len(pts):
        with part("field density"):
            sigma = view.density(pts, None) if view is not None else field.density(pts)
        with part("compositing"):
            tau = sigma.to(origins.dtype) * delta
            run = torch.cumsum(tau.double(), 0)
            first = torch.ones_like(ray, dtype=torch.bool)
            first[1:] = ray[1:] != ray[:-1]
            start = (run - tau)[first]  # the running sum before each ray's first kept sample
            before = run - tau - start.index_select(0, torch.cumsum(first, 0) - 1)
            weights = torch.exp(-before).to(tau.dtype) * -torch.expm1(-tau)
            acc.index_add_(0, ray, weights)
            depth.index_add_(0, ray, weights * tk)
            col = (weights > thr).nonzero().squeeze(-1) if thr > 0 else torch.arange(len(pts), device=pts.device)
            n_color = len(col)
        flops.add("composite", flops.COMPOSITE_FLOPS * len(pts) + 6 * n_color)
        if n_color:
            with part("field color"):
                ray_col = ray.index_select(0, col)
                if view is not None:
                    colors = view.color_rows(col, dirs.index_select(0, ray_col), None)
                else:
                    colors = field.color(pts.index_select(0, col), dirs.index_select(0, ray_col))
            with part("compositing"):
                color.index_add_(0, ray_col, weights.index_select(0, col)[:, None] * colors.to(origins.dtype))
    with part("compositing"):
        bg = constant(tuple(settings.background), color.device, color.dtype)
        color = color + (1.0 - acc)[:, None] * bg
    return RayBundle(color, depth, acc, len(pts), n_color, {})


class Camera(NamedTuple):
    """One posed pinhole camera: pose (4, 4) camera-to-world, intrinsics (4,) fx, fy, cx, cy in pixels, and the
    image's size in pixels."""

    pose: Tensor
    intrinsics: Tensor
    height: int
    width: int


@torch.no_grad()
def render_image(
    field: Field,
    camera: Camera,
    settings: RenderSettings,
    skip: Callable[[Tensor], Tensor] | None = None,
    device: torch.device | str = "cpu",
    packer: Packer | None = None,
) -> dict[str, Tensor | int]:
    """Render the image `camera` sees in chunks of `settings.chunk` rays (bounded memory).

    `packer` (default: `packer_for(device)`; keep one per model to reuse its budgets from image to image): with
    static budgets no chunk waits for the device; the budgets are settled once the image is done, and an image
    whose samples overflowed one is rendered again with the grown budgets, so no sample is ever missing.
    -> {"rgb": (H, W, 3), "depth": (H, W), "acc": (H, W), "n_samples": int, "n_color": int}
    """
    pose, intrinsics, height, width = camera
    with part("rays"):
        origins, dirs = image_rays(pose.to(device), intrinsics, height, width, settings.ndc)
    packer = packer_for(device) if packer is None else packer
    while True:
        parts = []
        n_samples = n_color = 0
        for i in range(0, origins.shape[0], settings.chunk):
            o, d = origins[i : i + settings.chunk], dirs[i : i + settings.chunk]
            b = render_rays(field, o, d, settings, skip, packer=packer) if packer.static else render_rays_packed(
                field, o, d, settings, skip)
            parts.append((b.color, b.depth, b.acc))
            n_samples += b.n_samples
            n_color += b.n_color
        if not packer.settle():  # static: every chunk fitted its budgets (the one wait of the image)
            break
    color, depth, acc = (torch.cat(p).cpu() for p in zip(*parts))
    return {
        "rgb": color.reshape(height, width, 3).clamp(0, 1),
        "depth": depth.reshape(height, width),
        "acc": acc.reshape(height, width),
        "n_samples": int(n_samples),
        "n_color": int(n_color),
    }


class Views(Protocol):
    """Posed cameras of one size, e.g. a dataset split: poses (N, 4, 4), intrinsics (N, 3, 3)."""

    poses: Tensor
    intrinsics: Tensor
    height: int
    width: int


def render_view(field: Field, views: Views, i: int, settings: RenderSettings,
                skip: Callable[[Tensor], Tensor] | None = None, device: torch.device | str = "cpu",
                packer: Packer | None = None) -> dict:
    """`render_image` of camera `i` of `views` (a dataset split)."""
    return render_image(field, Camera(views.poses[i], views.intrinsics[i], views.height, views.width), settings, skip,
                        device=device, packer=packer)
