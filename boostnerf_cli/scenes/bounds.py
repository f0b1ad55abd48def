"""Scene bounds derived from the cameras alone (no hard-coded boxes)."""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from boostnerf_cli.cameras import PINHOLE
from boostnerf_cli.errors import BoxWarning
from boostnerf_cli.render.renderer import Views


def box_text(box: Tensor) -> list[float]:
    """A box (2, 3) as six numbers for a message, to a thousandth of its longest side: a scene in millimetres
    or kilometres, or far from the origin, keeps its digits (a fixed 3 decimals printed a 2 mm box as +-0.001)."""
    values = box.flatten().tolist()
    extent = max(hi - lo for lo, hi in zip(values[:3], values[3:]))
    digits = max(0, 3 - math.floor(math.log10(extent))) if extent > 0 and math.isfinite(extent) else 3
    return [round(v, digits) for v in values]


def frustum_corners(poses: Tensor, intrinsics: Tensor, height: int, width: int, near: float, far: float) -> Tensor:
    """World positions of every camera's 4 image corners at depth `near` and at depth `far`.

    poses (N, 4, 4) camera-to-world, intrinsics (N, 4) fx, fy, cx, cy -> (N, 8, 3).
    """
    fx, fy, cx, cy = intrinsics[:, :PINHOLE].float().unbind(-1)  # each (N,); a lens's bend is left out
    u = torch.tensor([0.0, width, 0.0, width])
    v = torch.tensor([0.0, 0.0, height, height])
    x = (u[None] - cx[:, None]) / fx[:, None]  # (N, 4), camera space at z = -1
    y = -(v[None] - cy[:, None]) / fy[:, None]
    dirs = torch.stack([x, y, -torch.ones_like(x)], dim=-1)  # (N, 4, 3)
    depths = torch.tensor([near] * 4 + [far] * 4).view(1, 8, 1)
    pts_cam = torch.cat([dirs, dirs], dim=1) * depths  # (N, 8, 3), depth along -z
    rot, trans = poses[:, :3, :3].float(), poses[:, :3, 3].float()
    return pts_cam @ rot.transpose(1, 2) + trans[:, None]


def frustum_planes(poses: Tensor, intrinsics: Tensor, height: int, width: int, near: float, far: float) -> Tensor:
    """Each camera's viewing frustum as 6 world-space half-spaces n . p + d >= 0.

    poses (N, 4, 4), intrinsics (N, 4) -> (N, 6, 4) rows (n_x, n_y, n_z, d). A point is inside
    when it projects (as in `render.rays.project_points`) into [0, W] x [0, H] with depth along -z
    in [near, far]; the image bounds are tested as u * depth in [0, W * depth] (no division).
    """
    fx, fy, cx, cy = intrinsics[:, :PINHOLE].float().unbind(-1)  # each (N,); a lens's bend is left out
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    # camera-space normals a (N, 6, 3) and offsets b (N, 6): a . q + b >= 0, depth = -q_z
    a = torch.stack([
        torch.stack([zero, zero, -one], -1),  # depth >= near
        torch.stack([zero, zero, one], -1),  # depth <= far
        torch.stack([fx, zero, -cx], -1),  # u >= 0
        torch.stack([-fx, zero, -(width - cx)], -1),  # u <= W
        torch.stack([zero, -fy, -cy], -1),  # v >= 0
        torch.stack([zero, fy, -(height - cy)], -1),  # v <= H
    ], dim=1)
    b = torch.stack([-near * one, far * one, zero, zero, zero, zero], dim=1)
    rot, trans = poses[:, :3, :3].float(), poses[:, :3, 3].float()
    n = a @ rot.transpose(1, 2)  # world normal R a, as rows
    d = b - (n * trans[:, None]).sum(-1)
    return torch.cat([n, d[..., None]], dim=-1)


def lattice_visible_counts(axes: tuple[Tensor, Tensor, Tensor], planes: Tensor) -> Tensor:
    """How many frusta contain each point of the lattice axes[0] x axes[1] x axes[2].

    axes: three increasing, evenly spaced 1-D tensors (Gx,), (Gy,), (Gz,); planes (N, 6, 4) from
    `frustum_planes` -> (Gx, Gy, Gz) int64 counts. Exact and cheap: along each z column a frustum
    (an intersection of half-spaces) is one interval of lattice indices, so it is enough to find
    that interval per column and camera and add it to a difference array.
    """
    x, y, z = (a.double() for a in axes)
    n, d = planes[..., :3].double(), planes[..., 3].double()  # (N, 6, 3), (N, 6)
    step = float(z[1] - z[0]) if len(z) > 1 else 1.0
    # plane test along a column: a * k >= r, k the lattice index along z
    a = n[..., 2] * step  # (N, 6)
    r = -(x[:, None, None, None] * n[..., 0] + y[None, :, None, None] * n[..., 1] + d + n[..., 2] * z[0])
    ratio = r / torch.where(a == 0, torch.ones_like(a), a)  # (Gx, Gy, N, 6)
    inf = torch.full_like(ratio, math.inf)
    lower = torch.where(a > 0, ratio.ceil(), torch.where((a == 0) & (r > 0), inf, -inf)).amax(-1)
    upper = torch.where(a < 0, ratio.floor(), inf).amin(-1)  # (Gx, Gy, N)
    lo = lower.clamp(0, len(z)).long()
    hi = upper.clamp(-1, len(z) - 1).long()
    ones = (lo <= hi).long()
    diff = torch.zeros(len(x), len(y), len(z) + 1, dtype=torch.long)
    diff.scatter_add_(-1, lo.clamp_max(len(z)), ones).scatter_add_(-1, hi + 1, -ones)
    return diff.cumsum(-1)[..., : len(z)]


BOX_MARGIN = 0.1  # the camera-derived box grows by this fraction of its size on every side


def frustum_overlap_bbox(views: Views, near: float, far: float, min_fraction: float = 0.9, grid: int = 64) -> Tensor:
    """Axis-aligned box of the region that most cameras see, -> (2, 3) min corner, max corner.

    views: the cameras (a split): poses (N, 4, 4) camera-to-world, intrinsics (N, 4) fx, fy, cx, cy for images of
    height x width.

    Heuristic (object-centric captures, where the cameras look inwards at the subject):
    1. take the box spanned by all frustum corner points at depth `near` and `far`;
    2. sample a `grid`^3 lattice of cell centres in that box;
    3. keep the points that project inside the image with a depth in [near, far] for at least
       `min_fraction` of the cameras (the "frustum overlap");
    4. return the box of the kept points, grown by half a lattice cell (so a single kept point
       still gives a non-empty box) and then by `BOX_MARGIN` times its size on every side.
    If no point qualifies, the full frustum box of step 1 is returned, with a `BoxWarning`.
    """
    poses, intrinsics, height, width = views.poses, views.intrinsics, views.height, views.width
    corners = frustum_corners(poses, intrinsics, height, width, near, far).reshape(-1, 3)
    lo, hi = corners.amin(0), corners.amax(0)
    step = (hi - lo) / grid
    axes = tuple(lo[i] + step[i] * (torch.arange(grid, dtype=torch.float32) + 0.5) for i in range(3))
    counts = lattice_visible_counts(axes, frustum_planes(poses, intrinsics, height, width, near, far))
    need = math.ceil(min_fraction * len(poses) - 1e-9)
    keep = counts >= need
    if not bool(keep.any()):
        box = box_text(torch.stack([lo, hi]))
        warnings.warn(f"no point between near {near:.4g} and far {far:.4g} is seen by {need} of the {len(poses)} "
                      f"training cameras (at most {int(counts.max())}): the scene box is the extent of every camera's "
                      f"view, {box}; if the content lies elsewhere, give recipe key data.bbox a box that holds it "
                      "(docs/datasets.md, \"The scene box\")", BoxWarning, stacklevel=2)
        return torch.stack([lo, hi])
    index = keep.nonzero()  # (K, 3) lattice indices
    box_lo = torch.stack([axes[i][index[:, i].min()] for i in range(3)]) - step / 2
    box_hi = torch.stack([axes[i][index[:, i].max()] for i in range(3)]) + step / 2
    pad = BOX_MARGIN * (box_hi - box_lo)
    return torch.stack([box_lo - pad, box_hi + pad])


def camera_near_far(poses: Tensor) -> tuple[float, float]:
    """near / far for object-centric captures that record none, from the cameras alone.

    The subject is taken to sit at the point closest (least squares) to every camera's optical axis
    (the -z axis of each camera-to-world pose); with r the median camera distance to it and R the
    largest, near = 0.1 r and far = R + r (2 r when every camera is as far: the subject's far side,
    from the farthest camera too). When the axes are (nearly) parallel there is no such point and
    the camera centroid plus r along the mean viewing direction is used, r the camera spread (or 1).
    Cameras that do not face that point (most of them turned more than 60 degrees away: a room
    captured from inside, looking out) get a `BoxWarning`: near / far are then a guess.
    """
    p = poses.double()
    o, d = p[:, :3, 3], -p[:, :3, 2]
    d = d / d.norm(dim=-1, keepdim=True)
    proj = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]  # (N, 3, 3)
    a, b = proj.sum(0), (proj @ o[:, :, None]).sum(0)[:, 0]
    eig = torch.linalg.eigvalsh(a)
    if len(poses) > 1 and float(eig[0]) > 1e-3 * float(eig[-1]):
        centre = torch.linalg.solve(a, b)
    else:
        spread = float((o - o.mean(0)).norm(dim=-1).max()) if len(poses) > 1 else 0.0
        mean_dir = d.mean(0)
        centre = o.mean(0) + max(spread, 1.0) * mean_dir / mean_dir.norm().clamp_min(1e-12)
    dist = (o - centre).norm(dim=-1)
    r, r_max = float(dist.median()), float(dist.max())
    if r <= 1e-9:
        r = r_max = 1.0
    facing = ((centre - o) * d).sum(-1) / dist.clamp_min(1e-12)  # cosine between each axis and its way to the centre
    if len(poses) > 1 and float(facing.median()) < 0.5:
        warnings.warn(f"the training cameras do not face a common point (most look more than 60 degrees away from the "
                      f"point nearest their axes, as from inside a room looking out): near {0.1 * r:.4g} and far "
                      f"{r_max + r:.4g} are a guess; give recipe key data.bbox a box that holds the content (near and "
                      "far then reach it)", BoxWarning, stacklevel=2)
    return 0.1 * r, r_max + r


def box_near_far(poses: Tensor, bbox: Tensor) -> tuple[float, float]:
    """near / far that cover a known box from every camera: the smallest distance from a camera
    centre to the box (0 when a camera is inside it) and the largest distance to a box corner."""
    o = poses[:, :3, 3].double()
    lo, hi = bbox[0].double(), bbox[1].double()
    near = float(box_gaps(poses, bbox).min())
    corners = torch.stack([torch.stack([(lo, hi)[(k >> i) & 1][i] for i in range(3)]) for k in range(8)])
    far = float((o[:, None] - corners[None]).norm(dim=-1).max())
    return 0.9 * near, far


def box_gaps(poses: Tensor, bbox: Tensor) -> Tensor:
    """Each camera centre's distance to the box (N,), float64: 0 for a camera inside it."""
    o = poses[:, :3, 3].double()
    return (o - torch.maximum(torch.minimum(o, bbox[1].double()), bbox[0].double())).norm(dim=-1)


MIN_POINTS = 8  # a view that sees fewer sparse points gets no near / far of its own; a scene needs this many in all


def view_depths(xyz: Tensor, pose: Tensor) -> Tensor:
    """Depths along the camera's -z axis (its viewing direction) of world points (P, 3) -> (P,) float64."""
    p = pose.double()
    return -((xyz.double() - p[:3, 3]) @ p[:3, 2])


def point_near_far(xyz: Tensor, poses: Tensor, seen: list[Tensor], percentiles: tuple[float, float]) -> Tensor:
    """Each view's near and far from the depths of the sparse points it sees (the `percentiles` of them, robust to
    a stray point) -> (N, 2) float64; NaN for a view that sees fewer than `MIN_POINTS` points in front of it. This is
    how LLFF's own tool (imgs2poses) wrote poses_bounds.npy (0.1 and 99.9)."""
    out = torch.full((len(poses), 2), math.nan, dtype=torch.float64)
    q = torch.tensor(percentiles, dtype=torch.float64) / 100
    for i, (pose, index) in enumerate(zip(poses, seen)):
        depth = view_depths(xyz[index], pose)
        depth = depth[depth > 0]
        if len(depth) >= MIN_POINTS:
            out[i] = torch.quantile(depth, q)
    return out


POINT_PERCENTILES = (1.0, 99.0)  # the sparse points inside these percentiles (per axis, per view) bound the scene


def point_bounds(xyz: Tensor, poses: Tensor, seen: list[Tensor]) -> tuple[float, float, Tensor, str] | None:
    """near, far, box (2, 3) and a line saying where they came from, for a scene with sparse points: the box holds the
    `POINT_PERCENTILES` (per axis) of the points the cameras (`poses`, N) see, `seen[i]` the indices view i sees, grown
    by `BOX_MARGIN` of its longest side on every side (a tenth of a thin axis' own extent was less than a coarse cell
    below a table top); near / far from each view's depths of its points (`point_near_far`),
    near 0.9x the smallest, far 1.1x the largest. None when the views see fewer than `MIN_POINTS` points."""
    used = torch.unique(torch.cat(seen)) if seen else torch.zeros(0, dtype=torch.long)
    per_view = point_near_far(xyz, poses, seen, POINT_PERCENTILES)
    ok = ~per_view.isnan().any(-1)
    if len(used) < MIN_POINTS or not bool(ok.any()):
        return None
    q = torch.tensor(POINT_PERCENTILES, dtype=torch.float64) / 100
    lo, hi = torch.quantile(xyz[used].double(), q, dim=0)
    pad = BOX_MARGIN * float((hi - lo).max().clamp_min(1e-6))  # every side: a flat subject's thin axis too
    box = torch.stack([lo - pad, hi + pad]).float()
    near, far = 0.9 * float(per_view[ok, 0].min()), 1.1 * float(per_view[ok, 1].max())
    text = (f"the sparse points: percentiles {POINT_PERCENTILES[0]:g} to {POINT_PERCENTILES[1]:g} of the "
            f"{len(used)} points the {len(poses)} training views see, widened by {100 * BOX_MARGIN:.0f}% of the "
            "longest side")
    return near, far, box, text
