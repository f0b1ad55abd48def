"""Conservative skipping: the box holds every foreground training ray's visible surface.

The coarse geometry stage decides, once, which cells of the scene box any later stage may sample
(its occupancy mask, and the box around it). A structure the coarse grid cannot resolve (a wire one
pixel wide) ends up with too little density to pass the threshold, and would then be cut away for
good. `cover_foreground` makes the mask and the box conservative by construction:

1. foreground rays: training pixels whose colour differs from the scene's known background colour
   by more than `tol` (for a scene with no known background, or a forward-facing one in NDC, whose white walls
   and sky are content, every pixel is foreground);
2. each foreground ray gets one point: where its visible surface starts, the first sample at which the
   opacity gathered in the occupied cells of the views' visual hull reaches `SURFACE_OPACITY`, or, on a ray
   that gathers less than twice that in all, `PARTIAL_SHARE` of what it gathers (a pixel the surface only
   partly covers, on an anti-aliased rim: its ray passes just beside the surface and would otherwise reach
   `SURFACE_OPACITY` only in the coarse model's blur behind it, under a floor's rim);
3. a ray that never reaches `SURFACE_OPACITY` (a wire the coarse grid blurs away) gets, instead, the sample where the
   coarse model puts most of the ray's rendering weight, among the ray's cells in the visual hull of the
   training views (cells that project onto foreground in every view that sees them: first at their
   centre, else anywhere in their footprint), or among all its cells where the hull has none;
4. the mask grows to hold every point's cell, and the box is drawn around the points, each widened by half
   its pixel's footprint at its depth (where in the pixel the surface lies is unknown to that half), so every
   foreground ray crosses kept space inside the box (`missed_after` counts the rays with no sample in the
   box at all). Half a pixel, not a coarse cell: a coarse cell adds 0.04-0.07 on each side, which costs the
   thin scene 0.3 dB against NSVF's bbox.txt and makes lego's box 1.25x the volume.

Nothing is removed from the mask: it only grows, so what the coarse stage kept stays kept. (Carving the
mask with the views' visual hull at each cell's centre cuts silhouette cells of lego: -0.47 dB for DVGO-80;
docs/results.md, thin structure.)

The box, though, holds only what the views show. `hull_cells` keeps the occupied cells inside the views'
visual hull (`visual_hull` with the footprint test, which keeps a cell as soon as any foreground pixel lies
in its footprint in every view that sees it, and seen by at least a quarter of the views), so a floater in
front of the cameras, which other views see against the background, does not count as surface.
Space that no view sees (under a floor, inside a solid) is inside the hull, but no ray's surface starts
there, so it does not stretch the box either (a box around every occupied cell in the hull reaches 0.75
under the thin scene's floor). Without a known background the hull says nothing and every pixel is
foreground: there a ray is covered when it crosses an occupied cell, and the box is drawn around the mask's
cells (docs/results.md, thin structure).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor

from boostnerf_cli.render.contraction import Contraction
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.rays import NDC, image_rays, project_points
from boostnerf_cli.render.volrend import render_weights

FOREGROUND_TOL = 0.03  # colour difference (max over channels, [0, 1]) from the background: foreground
# The same for lossy images (JPEG): its ringing and chroma bleed around a silhouette on white reach 0.05-0.1 (a
# 64 px procedural scene as JPEG q85, 4:2:0: 1,708 background pixels past 0.03, 24 past 0.1, of 8,936 foreground),
# and each such ray, beside the object, would draw a "surface" on the box's faces: a misleading data.bbox warning,
# and a box never shrunk. The lossless tolerance misses none of them at 0.1 either.
LOSSY_FOREGROUND_TOL = 0.1
SURFACE_OPACITY = 0.1  # a ray's visible surface starts where the opacity gathered along it reaches this
PARTIAL_SHARE = 0.5  # ... or, on a ray that gathers less than twice that in all (through a pixel the surface
# only partly covers: an anti-aliased rim), where it has gathered this share of all it gathers


def foreground_tol(extra: dict) -> float:
    """The foreground tolerance for a scene's images (`Scene.extra["lossy"]`: some are JPEG)."""
    return LOSSY_FOREGROUND_TOL if extra.get("lossy") else FOREGROUND_TOL


# A pixel of an image with alpha is foreground when the subject covers most of it, whatever its colour: a white
# subject on the white background. Fainter pixels (an anti-aliased rim) count by their colour alone, as without alpha,
# and so do images whose alpha marks no background (saved composited, or without alpha: the loader fills in 1).
ALPHA_FOREGROUND = 0.5


def foreground_masks(images: Tensor, background: tuple[float, float, float] | None, tol: float = FOREGROUND_TOL,
                     alpha: Tensor | None = None) -> Tensor:
    """(N, H, W, 3) images -> (N, H, W) bool: pixels that differ from the background colour by more than `tol`, or
    whose alpha (N, H, W; images that had one) exceeds `ALPHA_FOREGROUND` in an image whose alpha marks some pixel
    as background. All True when the background is unknown."""
    if background is None:
        return torch.ones(images.shape[:3], dtype=torch.bool, device=images.device)
    bg = torch.tensor(background, dtype=images.dtype, device=images.device)
    masks = (images - bg).abs().amax(-1) > tol
    if alpha is None:
        return masks
    covered = alpha.to(masks.device) > ALPHA_FOREGROUND
    marks_background = (~covered).flatten(1).any(1)  # (N,): an opaque-everywhere alpha tells nothing
    return masks | (covered & marks_background[:, None, None])


def ray_cells(origins: Tensor, dirs: Tensor, occ: OccupancyGrid, near: float,
              far: float, contraction: Contraction | None = None) -> tuple[Tensor, Tensor, float]:
    """Points along each ray, a quarter cell apart, inside the occupancy grid's box (with `contraction`, an unbounded
    scene's: its samples, contracted; the grid is over the contracted box).

    -> xyz (R, S, 3), valid (R, S) bool, the step between them."""
    from boostnerf_cli.render.renderer import RenderSettings, sample_rays

    cell = float(((occ.bbox[1] - occ.bbox[0]) / torch.tensor(occ.shape, device=occ.bbox.device)).min())
    settings = RenderSettings(step=cell / 4, near=near, far=far, bbox=occ.bbox, max_samples=4096,
                              contraction=contraction)
    _, valid, xyz, step = sample_rays(origins, dirs, settings, jitter=False)
    return xyz, valid, step


@torch.no_grad()
def visual_hull(occ: OccupancyGrid, poses: Tensor, intrinsics: Tensor, masks: Tensor, footprint: bool = True,
                min_views: int = 1) -> Tensor:
    """Cells (occupancy grid shape, bool) that at least one training view sees and that every view seeing
    them shows as foreground somewhere in their footprint: with `footprint`, the rectangle of half-sides
    fx, fy * (half the cell's diagonal) / depth pixels around the centre's projection, so a cell holding a
    thin structure anywhere inside is kept; without, the 3 x 3 pixels around the centre's projection (the
    cells a surface passes through near their centre). A cell seen by fewer than `min_views` views is left
    out (one view's hull is a whole cone: the space just in front of a camera passes it)."""
    centres = occ.cell_centers()
    cell = (occ.bbox[1] - occ.bbox[0]) / torch.tensor(occ.shape, device=occ.bbox.device)
    half_diag = 0.5 * float(cell.norm())
    h, w = masks.shape[1:]
    keep = torch.ones(centres.shape[0], dtype=torch.bool, device=centres.device)
    seen_by = torch.zeros(centres.shape[0], dtype=torch.long, device=centres.device)
    for pose, k, mask in zip(poses, intrinsics, masks):
        uv, depth = project_points(centres, pose.to(centres.device), k)
        front = depth > 1e-6
        seen = front & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if not bool(seen.any()):
            continue
        # foreground pixels in each footprint: a summed-area table of the mask, one box sum per cell
        sat = F.pad(mask.double().cumsum(0).cumsum(1), (1, 0, 1, 0))
        if footprint:  # each axis by its own focal length (fy != fx: pixels that are not square in the scene)
            ru, rv = ((float(f) * half_diag / depth[seen].clamp_min(1e-6)).ceil() for f in k[:2])
        else:
            ru = rv = torch.ones_like(depth[seen])
        u, v = uv[seen, 0], uv[seen, 1]
        u0 = (u - ru).floor().clamp(0, w).long()
        u1 = (u + ru).floor().add(1).clamp(0, w).long()
        v0 = (v - rv).floor().clamp(0, h).long()
        v1 = (v + rv).floor().add(1).clamp(0, h).long()
        count = sat[v1, u1] - sat[v0, u1] - sat[v1, u0] + sat[v0, u0]
        fg = torch.ones_like(keep)
        fg[seen] = count > 0.5
        keep &= fg
        seen_by += seen.long()
    return (keep & (seen_by >= min_views)).reshape(occ.shape)


def known_background(background: tuple[float, float, float] | None, ndc: NDC | None,
                     contraction: Contraction | None = None) -> tuple[float, float, float] | None:
    """The colour foreground pixels are told from: a scene's background, but none in a forward-facing capture (NDC)
    or an unbounded one (`contraction`), whose white walls and sky are content."""
    return background if ndc is None and contraction is None else None


@torch.no_grad()
def hull_cells(occ: OccupancyGrid, images: Tensor, poses: Tensor, intrinsics: Tensor,
               background: tuple[float, float, float] | None, tol: float = FOREGROUND_TOL,
               alpha: Tensor | None = None) -> OccupancyGrid:
    """The occupied cells of `occ` inside the training views' visual hull (module docstring), for the box to
    be drawn around. Without a known background (`known_background`) the hull says nothing: `occ` itself."""
    if background is None:
        return occ
    masks = foreground_masks(images, background, tol, alpha).to(occ.occupied.device)
    hull = visual_hull(occ, poses, intrinsics, masks, footprint=True, min_views=max(2, math.ceil(len(images) / 4)))
    return OccupancyGrid(occ.occupied & hull, occ.bbox)


class Photos(Protocol):
    """Posed images, e.g. a dataset split: images (N, H, W, 3), poses (N, 4, 4), intrinsics (N, 4) and alpha
    (N, H, W) or None."""

    images: Tensor
    poses: Tensor
    intrinsics: Tensor
    alpha: Tensor | None


class Capture(Protocol):
    """What a scene says of its rays: near and far, its background colour (None: unknown), its NDC warp and its
    contraction (an unbounded scene's)."""

    near: float
    far: float
    background: tuple[float, float, float] | None
    ndc: NDC | None
    contraction: Contraction | None


@torch.no_grad()
def cover_foreground(
    occ: OccupancyGrid,
    density: Callable[[Tensor], Tensor],
    photos: Photos,
    capture: Capture,
    tol: float = FOREGROUND_TOL,
    chunk: int = 4096,
) -> tuple[OccupancyGrid, Tensor, dict]:
    """One point on every foreground ray of `photos` (the training views of the scene `capture`), the mask grown to
    hold them and the box drawn around them (module docstring).

    Without a known background (or in NDC) every pixel is foreground and the hull says nothing: a ray that crosses
    an occupied cell is covered, the others get a cell each, and the box is drawn around the grown grid's cells (a
    surface point per ray would mean rendering every training ray, for a box that in a forward-facing or unbounded
    scene is the whole box anyway).

    -> (the grown grid, the box (2, 3): the points' bounds, each widened by half its pixel's footprint, clipped to
        the box of `occ` (the grown grid's occupied box without points), {"foreground_rays", "missed_before": rays
        on which the occupied cells never reach `SURFACE_OPACITY` (cross none, without a known background),
        "missed_after": rays that get no point, "cells_added", "edge_rays": rays whose point lies within a cell of
        the box's faces, where the coarse model draws content that reaches past the box; 0 without a known
        background}).
    """
    images, poses, intrinsics = photos.images, photos.poses, photos.intrinsics
    near, far, ndc = capture.near, capture.far, capture.ndc
    n, h, w = images.shape[:3]
    device = occ.occupied.device  # the scene's tensors stay on the CPU; the grid may be on the GPU
    contraction = capture.contraction  # an unbounded scene's
    background = known_background(capture.background, ndc, contraction)
    known = background is not None
    masks = foreground_masks(images, background, tol, photos.alpha).to(device)
    # the (tight, footprint) visual hulls, made when a first ray needs them (on most scenes none does)
    hulls = functools.cache(lambda: (
        visual_hull(occ, poses, intrinsics, masks, footprint=False, min_views=max(2, math.ceil(n / 4))),
        visual_hull(occ, poses, intrinsics, masks)) if known else ())
    cover = _Covering(occ, known)
    focal = intrinsics[:, :2].amin(-1).tolist()  # pixels per unit of depth, the smaller of fx and fy
    for i in range(n):
        o, d = _fg_rays(poses[i], intrinsics[i], h, w, ndc, masks[i])
        cover.total += o.shape[0]
        for j in range(0, o.shape[0], chunk):
            s = _sample_chunk(o[j : j + chunk], d[j : j + chunk], occ, near, far, contraction)
            cover.missed_after += int((~s.inside).sum())  # a foreground ray that misses the box: nothing can hold it
            if known:
                choice = _surface_starts(s, density)
                miss = (choice < 0) & s.inside
            else:  # every pixel is foreground: a ray is covered when it crosses an occupied cell
                choice = torch.full(s.inside.shape, -1, dtype=torch.long, device=device)
                miss = ~s.on.any(-1) & s.inside
            if bool(miss.any()):
                cover.missed_before += int(miss.sum())
                rows = miss.nonzero()[:, 0]
                choice[rows] = _heaviest_samples(s, rows, density, hulls())
            cover.add(s, choice, focal[i])
    return cover.result()


@dataclass(frozen=True)
class _Samples:
    """A chunk of foreground rays, sampled a quarter cell apart inside the occupancy grid's box."""

    origins: Tensor  # (R, 3)
    xyz: Tensor  # (R, S, 3)
    idx: Tensor  # (R, S) flat cell index, -1 outside the box
    ok: Tensor  # (R, S) bool: a valid sample inside the box
    on: Tensor  # (R, S) bool: ... in an occupied cell
    inside: Tensor  # (R,) bool: the ray has a sample inside the box
    step: float


def _sample_chunk(origins: Tensor, dirs: Tensor, occ: OccupancyGrid, near: float, far: float,
                  contraction: Contraction | None = None) -> _Samples:
    xyz, valid, step = ray_cells(origins, dirs, occ, near, far, contraction)
    idx = occ.cell_index(xyz)
    ok = valid & (idx >= 0)
    on = ok.clone()
    on[ok] = occ.occupied.reshape(-1)[idx[ok]]
    return _Samples(origins, xyz, idx, ok, on, ok.any(-1), step)


def _surface_starts(s: _Samples, density: Callable[[Tensor], Tensor]) -> Tensor:
    """(R,) each ray's surface sample (module docstring, step 2): the first at which the opacity gathered in occupied
    cells reaches `SURFACE_OPACITY`, or `PARTIAL_SHARE` of all the ray gathers when that is under twice as much;
    -1 on a ray that never reaches `SURFACE_OPACITY` or misses the box."""
    sigma = torch.zeros(s.ok.shape, device=s.xyz.device)
    sigma[s.on] = density(s.xyz[s.on])
    weights, _, _ = render_weights(sigma, torch.full_like(sigma, s.step))
    gathered = weights.sum(-1, keepdim=True)
    reach = (weights.cumsum(-1) >= (PARTIAL_SHARE * gathered).clamp(max=SURFACE_OPACITY)) & (
        gathered >= SURFACE_OPACITY)
    return torch.where(reach.any(-1) & s.inside, reach.float().argmax(-1), -1)


def _heaviest_samples(s: _Samples, rows: Tensor, density: Callable[[Tensor], Tensor],
                      hulls: tuple[Tensor, ...]) -> Tensor:
    """(len(rows),) for the rays `rows` (each with a sample in the box) the sample where the coarse model puts most of
    the ray's rendering weight (module docstring, step 3): among the ray's cells in the first of `hulls` that holds
    any, else among all its cells."""
    sel = s.ok[rows]
    cells = s.idx[rows][sel]
    sigma = torch.zeros(sel.shape, device=s.xyz.device)
    sigma[sel] = density(s.xyz[rows][sel])
    weights, _, _ = render_weights(sigma, torch.full_like(sigma, s.step))
    pick = torch.full(rows.shape, -1, dtype=torch.long, device=sel.device)
    for table in (*hulls, None):  # the last allows every cell: a ray with a sample in the box always gets one
        allowed = sel.clone()
        if table is not None:
            allowed[sel] = table.reshape(-1)[cells]
        todo = (pick < 0) & allowed.any(-1)
        score = torch.where(allowed, weights + 1e-12, torch.full_like(weights, -1.0))
        pick = torch.where(todo, score.argmax(-1), pick)
    return pick


class _Covering:
    """What `cover_foreground` gathers chunk by chunk: the grown mask, the points' widened bounds, the counts."""

    def __init__(self, occ: OccupancyGrid, known: bool):
        device = occ.occupied.device
        self.occ, self.known = occ, known
        self.occupied = occ.occupied.clone()
        self.lo = torch.full((3,), math.inf, device=device)
        self.hi = torch.full((3,), -math.inf, device=device)
        self.cell = (occ.bbox[1] - occ.bbox[0]) / torch.tensor(occ.shape, device=device)
        self.total = self.missed_before = self.missed_after = self.edge = 0

    def add(self, s: _Samples, choice: Tensor, focal: float) -> None:
        """Grow the mask by each chosen sample's cell (the ray crosses kept space) and, with a known background, the
        bounds by the sample widened by half its pixel's footprint (where in the pixel the surface lies)."""
        rows = (choice >= 0).nonzero()[:, 0]
        if not rows.numel():
            return
        if self.known:
            pts = s.xyz[rows, choice[rows]]
            # a surface within a cell of the box's faces: what lies past the box is drawn there
            bbox = self.occ.bbox
            self.edge += int(((pts - bbox[0] < self.cell) | (bbox[1] - pts < self.cell)).any(-1).sum())
            half = (pts - s.origins[rows]).norm(dim=-1, keepdim=True) * (0.5 / focal)
            self.lo = torch.minimum(self.lo, (pts - half).amin(0))
            self.hi = torch.maximum(self.hi, (pts + half).amax(0))
        self.occupied.view(-1)[s.idx[rows, choice[rows]]] = True

    def result(self) -> tuple[OccupancyGrid, Tensor, dict]:
        stats = {"foreground_rays": self.total, "missed_before": self.missed_before, "missed_after": self.missed_after,
                 "cells_added": int((self.occupied & ~self.occ.occupied).sum()), "edge_rays": self.edge}
        grid = OccupancyGrid(self.occupied, self.occ.bbox)
        if not self.known or not bool(torch.isfinite(self.lo).all()):
            return grid, grid.occupied_bbox(margin_cells=1), stats
        box = torch.stack([torch.maximum(self.lo, self.occ.bbox[0]), torch.minimum(self.hi, self.occ.bbox[1])])
        return grid, box, stats


def _fg_rays(pose: Tensor, k: Tensor, h: int, w: int, ndc: NDC | None, mask: Tensor) -> tuple[Tensor, Tensor]:
    o, d = image_rays(pose, k, h, w, ndc)  # built on the CPU, with the scene's cameras
    fg = mask.reshape(-1)
    return o.to(mask.device)[fg], d.to(mask.device)[fg]
