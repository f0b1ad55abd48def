"""Camera paths for videos, derived from the training cameras alone (any dataset format).

Poses are camera-to-world 4x4 matrices in the OpenGL / Blender convention (`scenes/scene.py`):
the camera looks down its -z axis, +y is up.

- `orbit_path`: for 360-degree captures. The cameras circle the point their optical axes pass
  closest to; the path circles the scene's up axis (the mean of the cameras' up vectors) through
  that point, at the training cameras' mean radius and mean height, looking at the point.
- `spiral_path`: for forward-facing captures. An ellipse-with-depth spiral around the mean pose,
  with radii from the spread of the camera positions, looking at a focus point on the mean
  viewing axis at the depth of the scene box's centre.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import NDC


def _normalize(v: Tensor) -> Tensor:
    return v / torch.linalg.norm(v, dim=-1, keepdim=True).clamp_min(1e-12)


def look_at(position: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """Camera-to-world (4, 4) at `position` looking at `target` with `up` as image-up (OpenGL: looks down -z)."""
    z = _normalize(position - target)  # the camera's +z points away from what it looks at
    x = torch.linalg.cross(up, z)
    if float(torch.linalg.norm(x)) < 1e-9:  # looking straight along `up`: pick any perpendicular
        x = torch.linalg.cross(torch.tensor([1.0, 0.0, 0.0], dtype=z.dtype) if abs(float(z[0])) < 0.9
                               else torch.tensor([0.0, 1.0, 0.0], dtype=z.dtype), z)
    x = _normalize(x)
    y = torch.linalg.cross(z, x)
    pose = torch.eye(4, dtype=position.dtype)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, position
    return pose


def focus_point(poses: Tensor) -> Tensor:
    """The point nearest (least squares) to every camera's optical axis -> (3,)."""
    p = poses.double()
    o, d = p[:, :3, 3], _normalize(-p[:, :3, 2])
    proj = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]  # (N, 3, 3): I - d d^T
    a, b = proj.sum(0), (proj @ o[:, :, None]).sum(0)[:, 0]
    if float(torch.linalg.matrix_rank(a)) < 3:  # all axes parallel: no single nearest point
        raise BoostNerfError("the cameras' viewing axes are parallel: use --path spiral for a forward-facing scene")
    return torch.linalg.solve(a, b).to(poses.dtype)


def scene_up(poses: Tensor) -> Tensor:
    """The scene's up axis: the mean of the cameras' up vectors (their +y), normalised -> (3,)."""
    up = poses[:, :3, 1].double().mean(0)
    if float(torch.linalg.norm(up)) < 1e-6:
        raise BoostNerfError("the training cameras disagree on which way is up: cannot derive an orbit")
    return _normalize(up).to(poses.dtype)


def orbit_path(poses: Tensor, n_frames: int) -> Tensor:
    """`n_frames` poses (n_frames, 4, 4) on one full circle around the scene's up axis.

    Centre: `focus_point`; radius and height: the training cameras' mean distance from the up axis
    and mean height along it (relative to the centre); the first frame is at the azimuth of the
    first training camera.
    """
    if n_frames < 1:
        raise BoostNerfError("--frames must be at least 1")
    p = poses.double()
    up = scene_up(p)
    centre = focus_point(p)
    rel = p[:, :3, 3] - centre
    height = rel @ up
    flat = rel - height[:, None] * up
    radius = float(torch.linalg.norm(flat, dim=-1).mean())
    if radius < 1e-6:
        raise BoostNerfError("the training cameras sit on the scene's up axis: cannot derive an orbit")
    a = _normalize(flat[0]) if float(torch.linalg.norm(flat[0])) > 1e-6 else _normalize(flat.mean(0))
    b = torch.linalg.cross(up, a)
    h = float(height.mean())
    out = []
    for i in range(n_frames):
        t = 2.0 * math.pi * i / n_frames
        pos = centre + h * up + radius * (math.cos(t) * a + math.sin(t) * b)
        out.append(look_at(pos, centre, up))
    return torch.stack(out).to(poses.dtype)


def mean_pose(poses: Tensor) -> Tensor:
    """The average camera: mean position, mean viewing axis and mean up, orthonormalised -> (4, 4)."""
    p = poses.double()
    z = _normalize(p[:, :3, 2].mean(0))
    y_mean = p[:, :3, 1].mean(0)
    x = _normalize(torch.linalg.cross(y_mean, z))
    y = torch.linalg.cross(z, x)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, p[:, :3, 3].mean(0)
    return pose.to(poses.dtype)


SPIRAL_TURNS = 2.0  # turns of the spiral in the mean camera's x-y plane, per pass forward and back along z
SPIRAL_PERCENTILE = 90.0  # the spiral's radii: this percentile of the cameras' offsets from the mean position


def spiral_path(poses: Tensor, bbox: Tensor, near: float, far: float, n_frames: int,
                focus: float | None = None) -> Tensor:
    """`n_frames` poses (n_frames, 4, 4) on a spiral around the mean pose, looking at a focus point.

    Focus depth: the distance of the scene box's centre along the mean viewing axis (the middle of
    [near, far] when the box centre is not in front of the cameras), or `focus` when given. Radii along the mean
    camera's x, y, z: the `SPIRAL_PERCENTILE` of the training cameras' offsets from the mean position (a
    twentieth of the focus depth where the cameras do not move along an axis). The path turns
    `SPIRAL_TURNS` times in x-y while moving once forward and back along z.
    """
    if n_frames < 1:
        raise BoostNerfError("--frames must be at least 1")
    p = poses.double()
    c = mean_pose(p)
    rot, centre = c[:3, :3], c[:3, 3]
    forward = -rot[:, 2]
    box_centre = bbox.double().mean(0)
    focus = float((box_centre - centre) @ forward) if focus is None else focus
    if not near < focus < far:
        focus = 0.5 * (near + far)
    offsets = (p[:, :3, 3] - centre) @ rot  # in the mean camera's frame
    radii = torch.quantile(offsets.abs(), SPIRAL_PERCENTILE / 100.0, dim=0)
    radii = torch.where(radii > 1e-6 * max(focus, 1e-6), radii, torch.full_like(radii, focus / 20.0))
    target = centre + focus * forward
    up = rot[:, 1]
    out = []
    for i in range(n_frames):
        t = 2.0 * math.pi * SPIRAL_TURNS * i / n_frames
        local = torch.tensor([math.cos(t), -math.sin(t), -math.sin(t / SPIRAL_TURNS)], dtype=torch.float64) * radii
        out.append(look_at(centre + rot @ local, target, up))
    return torch.stack(out).to(poses.dtype)


PATHS = ("orbit", "spiral")


def camera_path(kind: str, poses: Tensor, bbox: Tensor, near: float, far: float, n_frames: int,
                ndc: NDC | None = None) -> Tensor:
    """Poses along path `kind`. With `ndc` (a forward-facing scene), `bbox`, `near` and `far` are in NDC while the
    poses are in world units: the spiral's focus is the world depth of the box centre's NDC depth (z = 1 - 2 near /
    depth; the middle of NDC's [-1, 1] is depth 2 near), not a distance read off the NDC box as if it were world
    units (that puts the focus beside the mean camera, and every frame looks sideways at empty space)."""
    if kind == "orbit":
        return orbit_path(poses, n_frames)
    if kind == "spiral":
        if ndc is not None:
            z = min(float(bbox[:, 2].double().mean()), 0.9)  # NDC z -> 1 means infinitely far
            return spiral_path(poses, bbox, ndc.near, math.inf, n_frames, focus=ndc.depth(z))
        return spiral_path(poses, bbox, near, far, n_frames)
    raise BoostNerfError(f"unknown camera path {kind!r}: use {' or '.join(PATHS)}")
