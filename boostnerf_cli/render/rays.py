"""Camera rays and ray/box clipping (pure functions).

Cameras follow the OpenGL / Blender convention of `boostnerf_cli.scenes.scene`: the camera looks
down -z, +y is up. Pixel (u, v) has its centre at (u + 0.5, v + 0.5); v grows downwards.
"""

from __future__ import annotations

import torch
from torch import Tensor


def pixel_directions(height: int, width: int, intrinsics: Tensor) -> Tensor:
    """Camera-space ray directions for every pixel centre, not normalised.

    intrinsics (4,) = fx, fy, cx, cy -> (H, W, 3) with z = -1.
    """
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float32) + 0.5,
        torch.arange(width, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    return torch.stack([(u - cx) / fx, -(v - cy) / fy, -torch.ones_like(u)], dim=-1)


def camera_rays(pose: Tensor, dirs_cam: Tensor) -> tuple[Tensor, Tensor]:
    """World-space rays for camera-space directions.

    pose (4, 4) camera-to-world, dirs_cam (..., 3) -> origins (..., 3), unit directions (..., 3).
    """
    rot, trans = pose[:3, :3].float(), pose[:3, 3].float()
    d = dirs_cam @ rot.T
    d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    return trans.expand_as(d), d


def image_rays(pose: Tensor, intrinsics: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """All rays of one image, flattened row-major: origins (H*W, 3), unit directions (H*W, 3)."""
    o, d = camera_rays(pose, pixel_directions(height, width, intrinsics))
    return o.reshape(-1, 3), d.reshape(-1, 3)


def project_points(points: Tensor, pose: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor]:
    """Project world points into a camera: -> pixel coordinates (N, 2) (u, v) and depth (N,) along -z."""
    w2c = torch.linalg.inv(pose.double()).float()
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -pc[:, 2]
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    safe = torch.where(depth.abs() > 1e-12, depth, torch.full_like(depth, 1e-12))
    u = fx * pc[:, 0] / safe + cx
    v = -fy * pc[:, 1] / safe + cy
    return torch.stack([u, v], dim=-1), depth


def intersect_box(origins: Tensor, dirs: Tensor, bbox: Tensor, near: float, far: float) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test of rays against an axis-aligned box, clipped to [near, far].

    origins, dirs (R, 3); bbox (2, 3) -> t_enter (R,), t_exit (R,), hit (R,) bool.
    Rays parallel to a slab are handled without NaN: a zero direction component gives an infinite
    interval when the origin lies inside that slab and an empty one otherwise.
    """
    inv = 1.0 / torch.where(dirs == 0, torch.full_like(dirs, 1e-30), dirs)
    t0 = (bbox[0] - origins) * inv
    t1 = (bbox[1] - origins) * inv
    t_lo = torch.minimum(t0, t1).amax(dim=-1).clamp_min(near)
    t_hi = torch.maximum(t0, t1).amin(dim=-1).clamp_max(far)
    hit = t_hi > t_lo
    return t_lo, t_hi, hit
