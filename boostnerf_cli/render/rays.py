"""Camera rays and ray/box clipping (pure functions).

Cameras follow the OpenGL / Blender convention of `boostnerf_cli.scenes.scene`: the camera looks
down -z, +y is up. Pixel (u, v) has its centre at (u + 0.5, v + 0.5); v grows downwards. A camera's
intrinsics and lens are `boostnerf_cli.cameras.Intrinsics` (a split's row of them is read with `Intrinsics.of`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from boostnerf_cli.cameras import Intrinsics, ideal_grid


@dataclass(frozen=True)
class NDC:
    """Normalized device coordinates of one reference camera, for forward-facing scenes (LLFF).

    The reference camera sits at the world origin looking down -z with focal lengths fx, fy for an
    image of W x H pixels (centred principal point). A world point p with depth -p_z >= `near` maps to

        ndc(p) = (-sx * p_x / p_z,  -sy * p_y / p_z,  1 + 2 * near / p_z),   sx = 2 fx / W, sy = 2 fy / H,

    so the whole half-space in front of the near plane, out to infinity, lands in z in [-1, 1)
    and the reference view's frustum in x, y in [-1, 1]. Straight lines stay straight lines (the
    map is projective), so a world ray becomes an NDC ray and the renderer samples it uniformly in
    NDC, i.e. uniformly in inverse depth (docs/datasets.md).
    """

    sx: float
    sy: float
    near: float = 1.0

    def points(self, xyz: Tensor) -> Tensor:
        """World points (..., 3) in front of the near plane -> NDC points (..., 3)."""
        x, y, z = xyz.unbind(-1)
        return torch.stack([-self.sx * x / z, -self.sy * y / z, 1 + 2 * self.near / z], dim=-1)

    def depth(self, z):
        """The world depth -p_z that NDC z (< 1; a number or a tensor) comes from: 2 near / (1 - z)."""
        return 2 * self.near / (1 - z)

    def z(self, depth):
        """The NDC z of world depth `depth` (>= near): 1 - 2 near / depth (`depth`'s inverse)."""
        return 1 - 2 * self.near / depth

    def world(self, ndc: Tensor) -> Tensor:
        """NDC points (..., 3) with z < 1 -> the world points `points` maps there (its inverse): depth -p_z =
        `depth(z)`, then x and y scaled back by it. z = 1 is infinitely far."""
        a, b, c = ndc.unbind(-1)
        z = -self.depth(c)
        return torch.stack([-a * z / self.sx, -b * z / self.sy, z], dim=-1)

    def rays(self, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        """World rays (R, 3), (R, 3) -> NDC rays: origins on the NDC near plane z = -1, unit directions.

        Each ray is first moved along itself to the world near plane z = -near; the NDC segment from
        there to infinity is origin + s * dir for s in [0, |end - origin|], end at z = 1. Rays must
        point away from the camera (d_z < 0, true for every ray of a forward-facing capture); a
        d_z >= 0 is clamped to a tiny negative value instead of producing NaN.
        """
        dz = torch.minimum(dirs[:, 2], torch.full_like(dirs[:, 2], -1e-6))
        d = torch.cat([dirs[:, :2], dz[:, None]], dim=-1)
        o = origins + (-(self.near + origins[:, 2]) / dz)[:, None] * d
        o_ndc = self.points(o)
        ox, oy, oz = o.unbind(-1)
        d_ndc = torch.stack([
            -self.sx * (d[:, 0] / dz - ox / oz),
            -self.sy * (d[:, 1] / dz - oy / oz),
            -2 * self.near / oz,
        ], dim=-1)
        return o_ndc, d_ndc / torch.linalg.norm(d_ndc, dim=-1, keepdim=True)

    def to_dict(self) -> dict:
        return {"sx": self.sx, "sy": self.sy, "near": self.near}


# ----------------------------------------------------------------------------- pixels

def pixel_directions(height: int, width: int, intrinsics: Intrinsics | Tensor,
                     device: torch.device | str = "cpu") -> Tensor:
    """Camera-space ray directions for every pixel centre, not normalised, on `device`.

    intrinsics: `cameras.Intrinsics`, or a split's row of them -> (H, W, 3) with z = -1. A lens bends each pixel's
    ray through the inverse distortion (`cameras.ideal_grid`, cached per camera), so the images are used as recorded,
    never resampled.
    """
    camera = Intrinsics.of(intrinsics)
    if camera.lens is not None:
        xy = ideal_grid(height, width, camera).to(device)
        return torch.stack([xy[..., 0], -xy[..., 1], -torch.ones_like(xy[..., 0])], dim=-1)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float32, device=device) + 0.5,
        torch.arange(width, dtype=torch.float32, device=device) + 0.5,
        indexing="ij",
    )
    return torch.stack([(u - camera.cx) / camera.fx, -(v - camera.cy) / camera.fy, -torch.ones_like(u)], dim=-1)


def pixel_rays(uv: Tensor, intrinsics: Intrinsics | Tensor) -> Tensor:
    """Camera-space directions (N, 3) (z = -1, float64) of arbitrary pixel positions uv (N, 2), through the lens
    when the camera has one: for a frustum's border (bounds), where the pixel centres of `pixel_directions` are not
    the points wanted."""
    xy = Intrinsics.of(intrinsics).normalized(uv)
    return torch.stack([xy[:, 0], -xy[:, 1], -torch.ones_like(xy[:, 0])], dim=-1)


def camera_rays(pose: Tensor, dirs_cam: Tensor) -> tuple[Tensor, Tensor]:
    """World-space rays for camera-space directions.

    pose (4, 4) camera-to-world, dirs_cam (..., 3) -> origins (..., 3), unit directions (..., 3).
    """
    rot, trans = pose[:3, :3].float(), pose[:3, 3].float()
    d = dirs_cam @ rot.T
    d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    return trans.expand_as(d), d


def image_rays(pose: Tensor, intrinsics: Intrinsics | Tensor, height: int, width: int,
               ndc: NDC | None = None) -> tuple[Tensor, Tensor]:
    """All rays of one image, flattened row-major: origins (H*W, 3), unit directions (H*W, 3).

    With `ndc` (forward-facing scenes) the rays are returned in normalized device coordinates. Built on the pose's
    device (the intrinsics are read on the host).
    """
    o, d = camera_rays(pose, pixel_directions(height, width, intrinsics, pose.device))
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    return ndc.rays(o, d) if ndc is not None else (o, d)


def project_points(points: Tensor, pose: Tensor, intrinsics: Intrinsics | Tensor) -> tuple[Tensor, Tensor]:
    """Project world points into a camera (through its lens, `cameras.Lens.distort`, when it has one): -> pixel
    coordinates (N, 2) (u, v) and depth (N,) along -z."""
    w2c = torch.linalg.inv(pose.double()).float()
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -pc[:, 2]
    safe = torch.where(depth.abs() > 1e-12, depth, torch.full_like(depth, 1e-12))
    xy = torch.stack([pc[:, 0] / safe, -pc[:, 1] / safe], dim=-1)
    return Intrinsics.of(intrinsics).pixels(xy), depth


def intersect_box(origins: Tensor, dirs: Tensor, bbox: Tensor, near: float,
                  far: float) -> tuple[Tensor, Tensor, Tensor]:
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
