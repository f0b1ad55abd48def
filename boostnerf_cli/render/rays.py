"""Camera rays and ray/box clipping (pure functions).

Cameras follow the OpenGL / Blender convention of `boostnerf_cli.scenes.scene`: the camera looks
down -z, +y is up. Pixel (u, v) has its centre at (u + 0.5, v + 0.5); v grows downwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import torch
from torch import Tensor


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


# ----------------------------------------------------------------------------- lenses

# A camera's intrinsics row: fx, fy, cx, cy (pixels), then, for a camera with lens distortion, LENS: the radial
# coefficients k1..k4, the tangential p1, p2 and a flag, 1 for a fisheye. A pinhole camera's row is 4 long; every
# row of a split has one length (pinhole views of a split that has a distorted one carry zeros).
LENS = ("k1", "k2", "k3", "k4", "p1", "p2", "fisheye")
PINHOLE = 4
WITH_LENS = PINHOLE + len(LENS)


def lens_row(fx: float, fy: float, cx: float, cy: float, coefficients: dict | None = None,
             fisheye: bool = False) -> list[float]:
    """An intrinsics row: 4 numbers for a pinhole camera (no coefficient set, not a fisheye), else 11 (`LENS`)."""
    coefficients = {k: float(v) for k, v in (coefficients or {}).items() if v}
    if not coefficients and not fisheye:
        return [fx, fy, cx, cy]
    return [fx, fy, cx, cy, *(coefficients.get(k, 0.0) for k in LENS[:-1]), 1.0 if fisheye else 0.0]


def has_lens(intrinsics: Tensor) -> bool:
    """Whether an intrinsics row (or rows) carries a lens (`LENS`) that bends rays."""
    return intrinsics.shape[-1] > PINHOLE and bool((intrinsics[..., PINHOLE:] != 0).any())


def distort(xy: Tensor, lens: Tensor) -> Tensor:
    """Ideal (pinhole) normalized image coordinates (..., 2), OpenCV axes (x right, y down, z = 1), -> the distorted
    ones a camera with `lens` (7,) (`LENS`) records, as COLMAP's OPENCV / RADIAL / SIMPLE_RADIAL and OPENCV_FISHEYE
    models and nerfstudio do: radial 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 and tangential p1, p2; a fisheye maps the
    angle theta = atan(r) to theta (1 + k1 theta^2 + ... + k4 theta^8) (equidistant)."""
    k1, k2, k3, k4, p1, p2, fisheye = (float(v) for v in lens)
    x, y = xy.unbind(-1)
    r2 = x * x + y * y
    if fisheye:
        r = r2.sqrt()
        theta = torch.atan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = torch.where(r > 1e-12, theta_d / r.clamp_min(1e-12), torch.ones_like(r))
        return xy * scale[..., None]
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def undistort(xy_d: Tensor, lens: Tensor, iterations: int = 40) -> Tensor:
    """The inverse of `distort`: distorted normalized coordinates (..., 2) -> ideal ones, by Newton's method in
    float64 on x - distort^-1 (a numerical Jacobian, started at the distorted point), as COLMAP and nerfstudio
    undistort. A fisheye solves theta_d = f(theta) in one dimension. Converges to ~1e-12 within a few steps for the
    lenses of phones and action cameras."""
    lens = lens.double()
    target = xy_d.double()
    if float(lens[-1]):
        k1, k2, k3, k4 = (float(v) for v in lens[:4])
        theta_d = target.norm(dim=-1)
        theta = theta_d.clone()
        for _ in range(iterations):
            t2 = theta * theta
            f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            theta = (theta - f / torch.where(df.abs() > 1e-12, df, torch.full_like(df, 1e-12))).clamp(0, 1.55)
        scale = torch.where(theta_d > 1e-12, torch.tan(theta) / theta_d.clamp_min(1e-12), torch.ones_like(theta))
        return target * scale[..., None]
    xy, eps = target.clone(), 1e-7
    for _ in range(iterations):
        f = distort(xy, lens) - target
        jx = (distort(xy + torch.tensor([eps, 0.0], dtype=xy.dtype), lens) - f - target) / eps
        jy = (distort(xy + torch.tensor([0.0, eps], dtype=xy.dtype), lens) - f - target) / eps
        det = jx[..., 0] * jy[..., 1] - jy[..., 0] * jx[..., 1]
        det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
        dx = (jy[..., 1] * f[..., 0] - jy[..., 0] * f[..., 1]) / det
        dy = (jx[..., 0] * f[..., 1] - jx[..., 1] * f[..., 0]) / det
        xy = xy - torch.stack([dx, dy], dim=-1)
        if float(f.abs().max()) < 1e-12:
            break
    return xy


@lru_cache(maxsize=16)
def _ideal_grid(height: int, width: int, row: tuple[float, ...]) -> Tensor:
    """(H, W, 2) float32 ideal normalized coordinates (OpenCV axes) of every pixel centre of the camera `row`:
    computed once per camera and image size (the undistortion's Newton steps), then reused for every view."""
    fx, fy, cx, cy = row[:PINHOLE]
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                          torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    xy = torch.stack([(u - cx) / fx, (v - cy) / fy], dim=-1)
    return undistort(xy, torch.tensor(row[PINHOLE:], dtype=torch.float64)).float()


def pixel_directions(height: int, width: int, intrinsics: Tensor, device: torch.device | str = "cpu") -> Tensor:
    """Camera-space ray directions for every pixel centre, not normalised, on `device`.

    intrinsics (4,) = fx, fy, cx, cy, or (11,) with a lens (`LENS`) -> (H, W, 3) with z = -1. A lens bends each
    pixel's ray through the inverse distortion (`undistort`, cached per camera), so the images are used as recorded,
    never resampled.
    """
    if has_lens(intrinsics):
        xy = _ideal_grid(height, width, tuple(float(v) for v in intrinsics)).to(device)
        return torch.stack([xy[..., 0], -xy[..., 1], -torch.ones_like(xy[..., 0])], dim=-1)
    fx, fy, cx, cy = (float(v) for v in intrinsics[:PINHOLE])
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float32, device=device) + 0.5,
        torch.arange(width, dtype=torch.float32, device=device) + 0.5,
        indexing="ij",
    )
    return torch.stack([(u - cx) / fx, -(v - cy) / fy, -torch.ones_like(u)], dim=-1)


def pixel_rays(uv: Tensor, intrinsics: Tensor) -> Tensor:
    """Camera-space directions (N, 3) (z = -1, float64) of arbitrary pixel positions uv (N, 2), through the lens
    when the row has one: for a frustum's border (bounds), where the pixel centres of `pixel_directions` are not
    the points wanted."""
    fx, fy, cx, cy = (float(v) for v in intrinsics[:PINHOLE])
    uv = uv.double()
    xy = torch.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy], dim=-1)
    if has_lens(intrinsics):
        xy = undistort(xy, intrinsics[PINHOLE:])
    return torch.stack([xy[:, 0], -xy[:, 1], -torch.ones_like(xy[:, 0])], dim=-1)


def camera_rays(pose: Tensor, dirs_cam: Tensor) -> tuple[Tensor, Tensor]:
    """World-space rays for camera-space directions.

    pose (4, 4) camera-to-world, dirs_cam (..., 3) -> origins (..., 3), unit directions (..., 3).
    """
    rot, trans = pose[:3, :3].float(), pose[:3, 3].float()
    d = dirs_cam @ rot.T
    d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    return trans.expand_as(d), d


def image_rays(pose: Tensor, intrinsics: Tensor, height: int, width: int,
               ndc: NDC | None = None) -> tuple[Tensor, Tensor]:
    """All rays of one image, flattened row-major: origins (H*W, 3), unit directions (H*W, 3).

    With `ndc` (forward-facing scenes) the rays are returned in normalized device coordinates. Built on the pose's
    device (the intrinsics are read on the host).
    """
    o, d = camera_rays(pose, pixel_directions(height, width, intrinsics, pose.device))
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    return ndc.rays(o, d) if ndc is not None else (o, d)


def project_points(points: Tensor, pose: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor]:
    """Project world points into a camera (through its lens, `distort`, when it has one): -> pixel coordinates
    (N, 2) (u, v) and depth (N,) along -z."""
    w2c = torch.linalg.inv(pose.double()).float()
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -pc[:, 2]
    fx, fy, cx, cy = (float(v) for v in intrinsics[:PINHOLE])
    safe = torch.where(depth.abs() > 1e-12, depth, torch.full_like(depth, 1e-12))
    xy = torch.stack([pc[:, 0] / safe, -pc[:, 1] / safe], dim=-1)
    if has_lens(intrinsics):
        xy = distort(xy.double(), intrinsics[PINHOLE:].double()).float()
    return torch.stack([fx * xy[:, 0] + cx, fy * xy[:, 1] + cy], dim=-1), depth


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
