"""A small generated Blender-format scene, rendered by exact analytic ray casting.

The scene (inside roughly [-1, 1]^2 x [-0.5, 0.3], z up) is a floor disc and four solids
placed and coloured by the seed:
- a floor disc (z = -0.5, radius 1) with a fine checkerboard (cell 0.05: period 0.1);
- a sphere with a smooth two-colour gradient;
- a sphere with thin latitude stripes (period 0.06);
- a box (rotated about z) with a fine 3-D checkerboard (cell 0.04: period 0.08);
- a box with a smooth gradient.
Shading is Lambertian under one fixed directional light plus ambient; no shadows. The background
is transparent. Each pixel averages `supersample`^2 sub-pixel rays (premultiplied colour), so the
silhouettes and texture edges are antialiased; the fine textures are near the Nyquist limit at
64-128 px, so low- and high-resolution grids differ in what they can represent.
"""

from __future__ import annotations

import json
import math
from contextlib import contextmanager
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import image_rays, intersect_box

CAMERA_ANGLE_X = 0.6911
RADIUS = 4.0
FLOOR_Z = -0.5
LIGHT = torch.tensor([0.4, 0.3, 0.85], dtype=torch.float64) / math.sqrt(0.4**2 + 0.3**2 + 0.85**2)
AMBIENT = 0.35


# ----------------------------------------------------------------------------- content


def _place(rng: np.random.Generator) -> np.ndarray:
    """Four xy centres, one per quadrant (in a seeded order), jittered: |x|, |y| <= 0.55, >= 0.7 apart."""
    quadrants = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float)[rng.permutation(4)]
    return quadrants * 0.45 + rng.uniform(-0.1, 0.1, (4, 2))


def scene_objects(seed: int = 0) -> list[dict]:
    """The seeded object list (JSON-able): kind, geometry, colours and texture of each object."""
    rng = np.random.default_rng(seed)
    colour = lambda: [round(float(v), 4) for v in rng.uniform(0.15, 0.95, 3)]  # noqa: E731
    xy = _place(rng)
    r1, r2 = float(rng.uniform(0.3, 0.4)), float(rng.uniform(0.22, 0.3))
    h1 = [float(v) for v in rng.uniform([0.18, 0.18, 0.15], [0.28, 0.28, 0.3])]
    h2 = [float(v) for v in rng.uniform([0.12, 0.12, 0.1], [0.25, 0.25, 0.3])]
    pos = lambda i, z: [float(xy[i][0]), float(xy[i][1]), z]  # noqa: E731
    return [
        {"kind": "disc", "centre": [0.0, 0.0, FLOOR_Z], "radius": 1.0, "texture": "checker", "cell": 0.05,
         "colours": [colour(), colour()]},
        {"kind": "sphere", "centre": pos(0, FLOOR_Z + r1), "radius": r1, "texture": "gradient",
         "colours": [colour(), colour()]},
        {"kind": "sphere", "centre": pos(1, FLOOR_Z + r2), "radius": r2, "texture": "stripes", "period": 0.06,
         "colours": [colour(), colour()]},
        {"kind": "box", "centre": pos(2, FLOOR_Z + h1[2]), "half": h1, "angle": float(rng.uniform(0, math.pi / 2)),
         "texture": "checker", "cell": 0.04, "colours": [colour(), colour()]},
        {"kind": "box", "centre": pos(3, FLOOR_Z + h2[2]), "half": h2, "angle": float(rng.uniform(0, math.pi / 2)),
         "texture": "gradient", "colours": [colour(), colour()]},
    ]


# ----------------------------------------------------------------------------- geometry


def _rot_z(angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def intersect(obj: dict, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """First hit of rays o, d (R, 3) (d unit) with `obj` -> t (R,) (inf on a miss), world normal (R, 3),
    texture coordinates (R, 3) (the hit point in the object's frame)."""
    c = torch.tensor(obj["centre"], dtype=torch.float64)
    inf = torch.full(o.shape[:1], math.inf, dtype=torch.float64)
    if obj["kind"] == "sphere":
        oc = o - c
        b = (d * oc).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + obj["radius"] ** 2
        t = -b - disc.clamp_min(0).sqrt()
        t = torch.where((disc >= 0) & (t > 0), t, inf)
        p = o + t.clamp_max(1e9)[:, None] * d
        return t, (p - c) / obj["radius"], p
    if obj["kind"] == "disc":
        dz = torch.where(d[:, 2] == 0, torch.full_like(d[:, 2], 1e-30), d[:, 2])
        t = (c[2] - o[:, 2]) / dz
        p = o + t[:, None] * d
        hit = (t > 0) & ((p[:, :2] - c[:2]).norm(dim=-1) <= obj["radius"])
        normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(p)
        return torch.where(hit, t, inf), normal, p
    rot = _rot_z(obj["angle"])  # box: local = rot^T (world - centre)
    half = torch.tensor(obj["half"], dtype=torch.float64)
    ol, dl = (o - c) @ rot, d @ rot
    t, _, hit = intersect_box(ol, dl, torch.stack([-half, half]), 0.0, math.inf)
    t = torch.where(hit & (t > 0), t, inf)
    pl = ol + t.clamp_max(1e9)[:, None] * dl
    axis = (pl.abs() / half).argmax(dim=-1)
    nl = torch.nn.functional.one_hot(axis, 3).double() * pl.gather(1, axis[:, None]).sign()
    return t, nl @ rot.T, pl


def shade(obj: dict, normal: Tensor, p: Tensor) -> Tensor:
    """Lambertian colour (R, 3) of `obj` at texture coordinates p (R, 3) with world normals (R, 3)."""
    a, b = (torch.tensor(col, dtype=torch.float64) for col in obj["colours"])
    if obj["texture"] == "gradient":  # smooth: blend weight varies slowly over the object
        w = 0.5 + 0.5 * torch.sin(2.0 * p[:, 0] + 1.5 * p[:, 1] + 3.0 * p[:, 2])
    elif obj["texture"] == "stripes":
        w = torch.floor(p[:, 2] / (obj["period"] / 2)).remainder(2)
    else:  # checker: 2-D on the disc (its z is constant), 3-D on boxes
        w = torch.floor(p / obj["cell"]).sum(-1).remainder(2)
    albedo = a + w[:, None] * (b - a)
    light = AMBIENT + (1 - AMBIENT) * (normal @ LIGHT).clamp_min(0)
    return (albedo * light[:, None]).clamp(0, 1)


def render_view(objects: list[dict], pose: Tensor, intrinsics: Tensor, size: int, supersample: int = 2) -> np.ndarray:
    """Ray-cast one square view -> (size, size, 4) float64 straight RGBA in [0, 1].

    pose (4, 4) camera-to-world, intrinsics (4,) fx, fy, cx, cy for `size` px. Sub-pixel rays are
    the pixel centres of a `supersample`-times larger image; their premultiplied colours are averaged.
    """
    s = supersample
    o, d = image_rays(pose, intrinsics * s, size * s, size * s)
    o, d = o.double(), d.double()
    hits = [intersect(obj, o, d) for obj in objects]
    t_all = torch.stack([h[0] for h in hits])  # (K, R)
    nearest = t_all.argmin(dim=0)
    alpha = torch.isfinite(t_all.min(dim=0).values).double()
    rgb = torch.zeros_like(o)
    for k, (obj, (t, n, p)) in enumerate(zip(objects, hits)):
        m = (nearest == k) & torch.isfinite(t)
        rgb[m] = shade(obj, n[m], p[m])
    rgba = torch.cat([rgb * alpha[:, None], alpha[:, None]], dim=-1)  # premultiplied
    rgba = rgba.reshape(size, s, size, s, 4).mean(dim=(1, 3))
    straight = rgba[..., :3] / rgba[..., 3:].clamp_min(1e-12)
    return torch.cat([straight.clamp(0, 1), rgba[..., 3:]], dim=-1).numpy()


# ----------------------------------------------------------------------------- cameras


def look_at(position: np.ndarray) -> np.ndarray:
    """Camera-to-world (4, 4), OpenGL convention, at `position` looking at the origin, z up."""
    z = position / np.linalg.norm(position)  # the camera looks down -z
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = position
    return pose


def camera_poses(n_train: int, n_test: int, radius: float = RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """Fibonacci spiral of n_train + n_test cameras, elevations 10-70 deg (equal-area), radius `radius`.

    Test cameras are evenly spaced members of the spiral, so they are distinct from the train ones.
    -> train (n_train, 4, 4), test (n_test, 4, 4).
    """
    n = n_train + n_test
    lo, hi = math.sin(math.radians(10)), math.sin(math.radians(70))
    i = np.arange(n)
    z = lo + (hi - lo) * (i + 0.5) / n
    az = i * math.pi * (3 - math.sqrt(5))  # golden angle
    pos = radius * np.stack([np.sqrt(1 - z**2) * np.cos(az), np.sqrt(1 - z**2) * np.sin(az), z], axis=1)
    poses = np.stack([look_at(p) for p in pos])
    test = np.round(np.linspace(0, n - 1, n_test)).astype(int) if n_test else np.zeros(0, int)
    train = np.setdiff1d(i, test)
    return poses[train], poses[test]


# ----------------------------------------------------------------------------- writing


README = """Procedurally generated test scene (boostnerf make-scene), seed {seed}.

Not captured data: every image is rendered by exact analytic ray casting (ray/sphere, ray/box,
ray/plane intersections) of the objects listed in objects.json, with {ss}x{ss} supersampling per
pixel. Blender / nerf_synthetic layout: transforms_train.json ({n_train} views) and
transforms_test.json ({n_test} views), {size}x{size} RGBA 8-bit PNGs, transparent background,
camera_angle_x {angle}, cameras at radius {radius} on the upper hemisphere (elevation 10-70 deg,
Fibonacci spiral) looking at the origin, OpenGL camera-to-world matrices, world z up.

Content (inside about [-1, 1]^2 x [-0.5, 0.3]): a floor disc with a fine checkerboard (cell 0.05),
a sphere with a smooth colour gradient, a sphere with thin stripes (period 0.06), a rotated box with a
fine 3-D checkerboard (cell 0.04) and a box with a smooth gradient; Lambertian shading under a fixed
directional light, no shadows. Free to use for any purpose.
"""


@contextmanager
def _single_thread():
    """Run torch ops on one thread: the per-view tensors are small (~10^4-10^5 rays), and on a busy
    machine the intra-op thread pool makes them several times slower, never faster."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _write_split(out_dir: Path, split: str, poses: np.ndarray, objects: list[dict], size: int, ss: int) -> None:
    focal = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    k = torch.tensor([focal, focal, size / 2, size / 2])
    (out_dir / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for i, pose in enumerate(poses):
        rgba = render_view(objects, torch.from_numpy(pose).float(), k, size, ss)
        iio.imwrite(out_dir / split / f"r_{i}.png", np.round(rgba * 255).astype(np.uint8))
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": pose.tolist()})
    meta = {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}
    (out_dir / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


def make_scene(out_dir: Path, size: int = 64, n_train: int = 24, n_test: int = 8, seed: int = 0, supersample: int = 2) -> Path:
    """Render the seeded procedural scene into `out_dir` (Blender layout) and return `out_dir`.

    Writes transforms_train.json, transforms_test.json (omitted when n_test = 0), train/r_*.png,
    test/r_*.png ((size, size) RGBA 8-bit), objects.json (the exact geometry) and README.txt.
    Deterministic: the same arguments give byte-identical files.
    """
    if size < 4 or n_train < 1 or n_test < 0 or supersample < 1:
        raise BoostNerfError(
            f"make-scene needs size >= 4, n_train >= 1, n_test >= 0, supersample >= 1 "
            f"(got size={size}, n_train={n_train}, n_test={n_test}, supersample={supersample})"
        )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    objects = scene_objects(seed)
    train, test = camera_poses(n_train, n_test)
    with _single_thread():
        _write_split(out_dir, "train", train, objects, size, supersample)
        if n_test:
            _write_split(out_dir, "test", test, objects, size, supersample)
    (out_dir / "objects.json").write_text(json.dumps({"seed": seed, "objects": objects}, indent=2))
    text = README.format(seed=seed, ss=supersample, n_train=n_train, n_test=n_test, size=size,
                         angle=CAMERA_ANGLE_X, radius=RADIUS)
    (out_dir / "README.txt").write_text(text)
    return out_dir
