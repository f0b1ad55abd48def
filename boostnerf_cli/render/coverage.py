"""Conservative skipping: every training ray that shows foreground must cross kept space.

The coarse geometry stage decides, once, which cells of the scene box any later stage may sample
(its occupancy mask, and the box around it). A structure the coarse grid cannot resolve (a wire one
pixel wide) ends up with too little density to pass the threshold, and would then be cut away for
good. `cover_foreground` makes the mask conservative by construction:

1. foreground rays: training pixels whose colour differs from the scene's known background colour
   by more than `tol` (for a scene with no known background, every pixel is foreground);
2. a ray is covered when one of its samples inside the box falls in an occupied cell;
3. each uncovered foreground ray gets the cells along it that lie in the visual hull of the training
   views (cells that project onto foreground, with the masks dilated by the cell's footprint, in every
   view that sees them), or, where the hull gives none or there is no background, the cell where the
   coarse model puts most of the ray's rendering weight;
4. after that every foreground ray crosses an occupied cell, so a box drawn around the occupied cells
   (with a margin) holds every visible structure: `covered_fraction` checks it.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.rays import NDC, image_rays, project_points
from boostnerf_cli.render.volrend import render_weights

FOREGROUND_TOL = 0.03  # colour difference (max over channels, [0, 1]) from the background: foreground


def foreground_masks(images: Tensor, background: tuple[float, float, float] | None, tol: float = FOREGROUND_TOL) -> Tensor:
    """(N, H, W, 3) images -> (N, H, W) bool: pixels that differ from the background colour (all True
    when the background is unknown)."""
    if background is None:
        return torch.ones(images.shape[:3], dtype=torch.bool, device=images.device)
    bg = torch.tensor(background, dtype=images.dtype, device=images.device)
    return (images - bg).abs().amax(-1) > tol


def ray_cells(origins: Tensor, dirs: Tensor, occ: OccupancyGrid, near: float, far: float) -> tuple[Tensor, Tensor]:
    """Points along each ray, a quarter cell apart, inside the occupancy grid's box.

    -> xyz (R, S, 3), valid (R, S) bool, the step between them."""
    from boostnerf_cli.render.renderer import RenderSettings, sample_rays

    cell = float(((occ.bbox[1] - occ.bbox[0]) / torch.tensor(occ.shape, device=occ.bbox.device)).min())
    settings = RenderSettings(step=cell / 4, near=near, far=far, bbox=occ.bbox, max_samples=4096)
    _, valid, xyz, step = sample_rays(origins, dirs, settings, jitter=False)
    return xyz, valid, step


def covered(origins: Tensor, dirs: Tensor, occ: OccupancyGrid, near: float, far: float, chunk: int = 4096) -> Tensor:
    """(R,) bool: the ray has a sample in an occupied cell."""
    out = []
    for i in range(0, origins.shape[0], chunk):
        xyz, valid, _ = ray_cells(origins[i : i + chunk], dirs[i : i + chunk], occ, near, far)
        hit = torch.zeros(valid.shape, dtype=torch.bool, device=valid.device)
        hit[valid] = occ(xyz[valid])
        out.append(hit.any(-1))
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.bool)


@torch.no_grad()
def visual_hull(occ: OccupancyGrid, poses: Tensor, intrinsics: Tensor, masks: Tensor) -> Tensor:
    """Cells (occupancy grid shape, bool) whose centre projects onto foreground in every view that sees
    it, each view's mask dilated by the cell's footprint there (so a cell holding a thin structure
    anywhere inside it is kept); cells no view sees are kept too (nothing says they are empty)."""
    centres = occ.cell_centers()
    cell = (occ.bbox[1] - occ.bbox[0]) / torch.tensor(occ.shape, device=occ.bbox.device)
    half_diag = 0.5 * float(cell.norm())
    h, w = masks.shape[1:]
    keep = torch.ones(centres.shape[0], dtype=torch.bool, device=centres.device)
    for pose, k, mask in zip(poses, intrinsics, masks):
        uv, depth = project_points(centres, pose.to(centres.device), k)
        front = depth > 1e-6
        if not bool(front.any()):
            continue
        radius = int(math.ceil(float(k[0]) * half_diag / float(depth[front].min()))) if bool(front.any()) else 1
        radius = max(1, min(radius, 16))
        grown = F.max_pool2d(mask.float()[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0] > 0
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        seen = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        fg = torch.zeros_like(keep)
        fg[seen] = grown[v[seen], u[seen]]
        keep &= fg | ~seen
    return keep.reshape(occ.shape)


@torch.no_grad()
def cover_foreground(
    occ: OccupancyGrid,
    density: Callable[[Tensor], Tensor],
    images: Tensor,
    poses: Tensor,
    intrinsics: Tensor,
    background: tuple[float, float, float] | None,
    near: float,
    far: float,
    ndc: NDC | None = None,
    chunk: int = 4096,
) -> tuple[OccupancyGrid, dict]:
    """Grow `occ` until every foreground training ray crosses an occupied cell (module docstring).

    -> (the grown grid, {"foreground_rays", "missed_before", "missed_after", "cells_added"}).
    """
    n, h, w = images.shape[:3]
    device = occ.occupied.device  # the scene's tensors stay on the CPU; the grid may be on the GPU
    masks = foreground_masks(images, background).to(device)
    hull = visual_hull(occ, poses, intrinsics, masks) if background is not None and ndc is None else None
    occupied = occ.occupied.clone()
    total = missed_before = 0
    for i in range(n):
        o, d = _fg_rays(poses[i], intrinsics[i], h, w, ndc, masks[i])
        total += o.shape[0]
        for j in range(0, o.shape[0], chunk):
            oc, dc = o[j : j + chunk], d[j : j + chunk]
            xyz, valid, step = ray_cells(oc, dc, occ, near, far)
            grid = OccupancyGrid(occupied, occ.bbox)
            hit = torch.zeros(valid.shape, dtype=torch.bool, device=valid.device)
            hit[valid] = grid(xyz[valid])
            miss = ~hit.any(-1) & valid.any(-1)
            if not bool(miss.any()):
                continue
            missed_before += int(miss.sum())
            xyz, valid = xyz[miss], valid[miss]
            idx = _cell_index(xyz, occ)  # (R, S) flat cell index, -1 outside
            ok = valid & (idx >= 0)
            if hull is not None:
                in_hull = torch.zeros_like(ok)
                in_hull[ok] = hull.reshape(-1)[idx[ok]]
                chosen = ok & in_hull
            else:
                chosen = torch.zeros_like(ok)
            # rays the hull gives no cell for: the cell of the coarse model's largest rendering weight
            none = ~chosen.any(-1)
            if bool(none.any()):
                sigma = torch.zeros(valid[none].shape, device=xyz.device)
                sigma[valid[none]] = density(xyz[none][valid[none]])
                weights, _, _ = render_weights(sigma, torch.full_like(sigma, step))
                best = weights.argmax(-1)
                rows = none.nonzero()[:, 0]
                chosen[rows, best] = ok[rows, best]
            occupied.view(-1)[idx[chosen]] = True
    grown = OccupancyGrid(occupied, occ.bbox)
    missed_after = total - int(sum(int(covered(*_fg_rays(poses[i], intrinsics[i], h, w, ndc, masks[i]), grown, near, far).sum())
                                   for i in range(n)))
    stats = {"foreground_rays": total, "missed_before": missed_before, "missed_after": missed_after,
             "cells_added": int((occupied & ~occ.occupied).sum())}
    return grown, stats


def _fg_rays(pose: Tensor, k: Tensor, h: int, w: int, ndc: NDC | None, mask: Tensor) -> tuple[Tensor, Tensor]:
    o, d = image_rays(pose, k, h, w, ndc)  # built on the CPU, with the scene's cameras
    fg = mask.reshape(-1)
    return o.to(mask.device)[fg], d.to(mask.device)[fg]


def _cell_index(xyz: Tensor, occ: OccupancyGrid) -> Tensor:
    """Flat [x, y, z] cell index of each point (..., 3), -1 outside the box."""
    res = torch.tensor(occ.shape, device=xyz.device)
    u = ((xyz - occ.bbox[0]) / (occ.bbox[1] - occ.bbox[0]) * res).floor().long()
    u = torch.minimum(u, res - 1)  # the max face belongs to the last cell
    inside = ((u >= 0) & (u < res)).all(-1)
    flat = (u[..., 0] * res[1] + u[..., 1]) * res[2] + u[..., 2]
    return torch.where(inside, flat, torch.full_like(flat, -1))
