"""A small generated scene, rendered by exact analytic ray casting, written in any dataset layout.

The scene (inside roughly [-1, 1]^2 x [-0.5, 0.3], z up) is a floor disc and four solids
placed and coloured by the seed:
- a floor disc (z = -0.5, radius 1) with a fine checkerboard (cell 0.05: period 0.1);
- a sphere with a smooth two-colour gradient;
- a sphere with thin latitude stripes (period 0.06);
- a box (rotated about z) with a fine 3-D checkerboard (cell 0.04: period 0.08);
- a box with a smooth gradient.
Shading is Lambertian under one fixed directional light plus ambient; no shadows. The background
is transparent. Each pixel averages `SUPERSAMPLE`^2 sub-pixel rays (premultiplied colour), so the
silhouettes and texture edges are antialiased; the fine textures are near the Nyquist limit at
64-128 px, so low- and high-resolution grids differ in what they can represent.

The same rendered views can be written in every layout a loader reads (`LAYOUTS`: Blender, NSVF,
masked Tanks and Temples, LLFF, nerfstudio), with cameras on the upper hemisphere looking at the
scene (`rig="sphere"`) or a forward-facing capture (`rig="forward"`, the default for LLFF), so
the tests can check that every loader recovers the same cameras and images.
"""

from __future__ import annotations

import json
import math
import shutil
from contextlib import contextmanager
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from torch import Tensor

from boostnerf_cli.cameras import PINHOLE, Intrinsics, Lens, flip_axes, rows
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import image_rays, intersect_box, project_points

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


CONTENTS = ("objects", "thin", "large", "empty", "detail", "textured")
LARGE_FLOOR_RADIUS = 3.0  # the "large" content's floor: past the camera-derived box (about +-1.7) and out of every view
THIN_RADIUS = 0.018  # rods and cable of the "thin" content: about 1.2 px wide at 100 px (2 px at 160 px)


def thin_objects(seed: int = 0) -> list[dict]:
    """Thin structures far from the main mass, reaching the content box's edge (`CONTENT_BOX`): a cable
    lying on the floor near its rim, two upright rods at the rim and a slanted wire from a rod top to the
    far corner. Each is a capsule (a segment of radius `THIN_RADIUS`), dark on the light floor and background."""
    rng = np.random.default_rng(seed + 1000)
    dark = lambda: [round(float(v), 4) for v in rng.uniform(0.02, 0.2, 3)]  # noqa: E731
    r, z0 = THIN_RADIUS, FLOOR_Z + THIN_RADIUS
    a = float(rng.uniform(0, 2 * math.pi))
    rim = lambda ang, rad: [round(rad * math.cos(ang), 4), round(rad * math.sin(ang), 4)]  # noqa: E731
    p1, p2 = rim(a, 0.93), rim(a + 2.2, 0.93)
    return [
        {"kind": "capsule", "a": rim(a + 3.3, 0.95) + [z0], "b": rim(a + 4.9, 0.95) + [z0], "radius": r,
         "texture": "plain", "colours": [dark(), dark()]},  # the cable on the floor
        {"kind": "capsule", "a": p1 + [FLOOR_Z], "b": p1 + [0.35], "radius": r, "texture": "plain",
         "colours": [dark(), dark()]},
        {"kind": "capsule", "a": p2 + [FLOOR_Z], "b": p2 + [0.3], "radius": r, "texture": "plain",
         "colours": [dark(), dark()]},
        {"kind": "capsule", "a": p1 + [0.35],
         "b": [1.08 * math.copysign(1, -p1[0]), 1.08 * math.copysign(1, -p1[1]), 0.38],
         "radius": r, "texture": "plain", "colours": [dark(), dark()]},
    ]


DETAIL_CELL = 0.12  # the "detail" content's checker cell: about 2 px at 48 px, 2.4 voxels of a 32^3 grid, 1.2 of a 16^3


def detail_objects(seed: int = 0) -> list[dict]:
    """Fine detail in one half of the scene (x > 0), smooth content in the other (x < 0): a floor disc
    checkered (cell `DETAIL_CELL`) where x > 0 and with a smooth gradient where x < 0; in the two x > 0 quadrants a
    checkered box and a striped sphere (period 2 `DETAIL_CELL`), in light and dark colours; in the two x < 0
    quadrants two low domes (spheres sunk into the floor) in the floor's colours, shaded smoothly."""
    rng = np.random.default_rng(seed + 2000)

    def contrast() -> list[list[float]]:  # a light colour and a dark one: the detail is visible in every seed
        light = rng.uniform(0.6, 0.95, 3)
        return [[round(float(v), 4) for v in light], [round(float(v), 4) for v in light * rng.uniform(0.2, 0.35)]]

    xy = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=float)[[*rng.permutation(2), *(2 + rng.permutation(2))]]
    xy = xy * 0.5 + rng.uniform(-0.08, 0.08, (4, 2))
    r = float(rng.uniform(0.3, 0.36))
    half = [float(v) for v in rng.uniform([0.22, 0.22, 0.2], [0.28, 0.28, 0.3])]
    domes = [float(v) for v in rng.uniform(0.36, 0.4, 2)]  # sunk by 0.35 r: a cap 0.65 r high, 0.94 r wide
    floor = contrast()
    pos = lambda i, z: [float(xy[i][0]), float(xy[i][1]), z]  # noqa: E731
    return [
        {"kind": "disc", "centre": [0.0, 0.0, FLOOR_Z], "radius": 1.0, "texture": "half-checker", "cell": DETAIL_CELL,
         "colours": floor},
        {"kind": "box", "centre": pos(0, FLOOR_Z + half[2]), "half": half, "angle": float(rng.uniform(0, math.pi / 2)),
         "texture": "checker", "cell": DETAIL_CELL, "colours": contrast()},
        {"kind": "sphere", "centre": pos(1, FLOOR_Z + r), "radius": r, "texture": "stripes",
         "period": 2 * DETAIL_CELL, "colours": contrast()},
        *({"kind": "sphere", "centre": pos(i, FLOOR_Z - 0.35 * rd), "radius": rd, "texture": "gradient",
           "colours": floor} for i, rd in zip((2, 3), domes)),
    ]


def textured_objects(seed: int = 0) -> list[dict]:
    """The "objects" content with every surface speckled with round dots of three sizes ("dots"): blobs that SIFT
    finds and matches from view to view, for structure-from-motion (`boostnerf capture`) tests."""
    rng = np.random.default_rng(seed + 3000)

    def contrast() -> list[list[float]]:  # a light colour and a dark one
        light = rng.uniform(0.6, 0.95, 3)
        return [[round(float(v), 4) for v in light], [round(float(v), 4) for v in light * rng.uniform(0.1, 0.25)]]

    return [{**obj, "texture": "dots", "scales": [round(float(v), 3) for v in rng.uniform([2.5, 5, 10], [3.5, 7, 14])],
             "colours": contrast()} for obj in scene_objects(seed)]


def scene_objects(seed: int = 0, content: str = "objects") -> list[dict]:
    """The seeded object list (JSON-able): kind, geometry, colours and texture of each object.

    content: "objects" (the floor and four solids), "thin" (the same, plus `thin_objects`), "large" (the same
    with a floor of radius `LARGE_FLOOR_RADIUS`, which reaches past the scene box derived from the cameras and
    leaves every view at its edge), "empty" (nothing: every pixel is background) or "detail" (`detail_objects`)."""
    if content not in CONTENTS:
        raise BoostNerfError(f"unknown scene content {content!r}: use one of {', '.join(CONTENTS)}")
    if content == "thin":
        return scene_objects(seed) + thin_objects(seed)
    if content == "large":
        floor, *solids = scene_objects(seed)
        return [{**floor, "radius": LARGE_FLOOR_RADIUS}, *solids]
    if content == "empty":
        return []
    if content == "detail":
        return detail_objects(seed)
    if content == "textured":
        return textured_objects(seed)
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


# The unbounded rig's world: the content on a ground that reaches far past every box, under a sky dome
WORLD_RADIUS = 8.0  # the ground disc's and the sky dome's radius: 3x the cameras' ring, past any box the cameras give
RING_RADIUS = 2.6  # the unbounded rig's cameras circle at this distance from the up axis
RING_ANGLE_X = 1.0  # its cameras' horizontal field of view (radians): wider, so the views show sky and far ground


def environment() -> list[dict]:
    """The unbounded rig's background: a ground disc just below the content's floor, checkered in large cells, and
    a glowing sky dome with horizontal bands, both `WORLD_RADIUS` from the origin."""
    return [
        {"kind": "disc", "centre": [0.0, 0.0, FLOOR_Z - 0.01], "radius": WORLD_RADIUS, "texture": "checker",
         "cell": 0.7, "colours": [[0.35, 0.5, 0.25], [0.55, 0.45, 0.3]]},
        {"kind": "dome", "centre": [0.0, 0.0, FLOOR_Z], "radius": WORLD_RADIUS, "texture": "stripes", "period": 1.6,
         "colours": [[0.45, 0.65, 0.9], [0.85, 0.8, 0.6]], "emissive": True},
    ]


# ----------------------------------------------------------------------------- geometry


# The half-orbit rig's world (a phone walk around an object on a table): the content on a table in a closed room
ROOM_HALF = [4.5, 4.5, 1.75]  # the room's half extents: walls 4.5 from the table's middle, floor a table's height down
ROOM_CENTRE = [0.0, 0.0, FLOOR_Z - 1.0 + ROOM_HALF[2]]  # its floor 1.0 below the table top, its ceiling 2.5 above it
TABLE_HALF = [1.3, 0.9, 0.5]  # a table under the content's floor disc, its top just below the disc, down to the floor
ARC_RADIUS = 2.8  # the half-orbit rig's cameras stand this far from the object's middle (0, 0, FLOOR_Z + 0.25)
ARCS = {"half-orbit": 180.0, "quarter-orbit": 90.0}  # the rigs on an arc and the degrees their cameras span


def room() -> list[dict]:
    """The half-orbit rigs' background: a table under the content and a closed room around it (floor, four walls,
    ceiling), every surface speckled with dots of three sizes that SIFT can match, and lit as the content is."""
    return [
        {"kind": "box", "centre": [0.0, 0.0, FLOOR_Z - 0.005 - TABLE_HALF[2]], "half": TABLE_HALF, "angle": 0.0,
         "texture": "dots", "scales": [3.0, 6.0, 12.0], "colours": [[0.72, 0.55, 0.38], [0.25, 0.16, 0.1]]},
        {"kind": "room", "centre": ROOM_CENTRE, "half": ROOM_HALF, "texture": "dots", "scales": [0.9, 1.8, 3.6],
         "colours": [[0.85, 0.82, 0.74], [0.2, 0.24, 0.3]]},
    ]


def rot_z(angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def intersect(obj: dict, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """First hit of rays o, d (R, 3) (d unit) with `obj` -> t (R,) (inf on a miss), world normal (R, 3),
    texture coordinates (R, 3) (the hit point in the object's frame)."""
    inf = torch.full(o.shape[:1], math.inf, dtype=torch.float64)
    if obj["kind"] == "capsule":
        return _capsule(obj, o, d, inf)
    c = torch.tensor(obj["centre"], dtype=torch.float64)
    if obj["kind"] == "sphere":
        oc = o - c
        b = (d * oc).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + obj["radius"] ** 2
        t = -b - disc.clamp_min(0).sqrt()
        t = torch.where((disc >= 0) & (t > 0), t, inf)
        p = o + t.clamp_max(1e9)[:, None] * d
        return t, (p - c) / obj["radius"], p
    if obj["kind"] == "dome":  # the inside of a sphere (the sky of the unbounded rig): the far hit
        oc = o - c
        b = (d * oc).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + obj["radius"] ** 2
        t = -b + disc.clamp_min(0).sqrt()
        t = torch.where((disc >= 0) & (t > 0), t, inf)
        p = o + t.clamp_max(1e9)[:, None] * d
        return t, (c - p) / obj["radius"], p
    if obj["kind"] == "room":  # the inside of an axis-aligned box (the half-orbit rigs' room): where rays leave it
        half = torch.tensor(obj["half"], dtype=torch.float64)
        dd = torch.where(d == 0, torch.full_like(d, 1e-30), d)
        t_axes = (torch.where(dd > 0, half, -half) - (o - c)) / dd
        t, axis = t_axes.min(dim=-1)
        t = torch.where(((o - c).abs() < half).all(-1) & (t > 0), t, inf)
        normal = -torch.nn.functional.one_hot(axis, 3).double() * torch.sign(dd).gather(1, axis[:, None])
        return t, normal, o + t.clamp_max(1e9)[:, None] * d
    if obj["kind"] == "disc":
        dz = torch.where(d[:, 2] == 0, torch.full_like(d[:, 2], 1e-30), d[:, 2])
        t = (c[2] - o[:, 2]) / dz
        p = o + t[:, None] * d
        hit = (t > 0) & ((p[:, :2] - c[:2]).norm(dim=-1) <= obj["radius"])
        normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(p)
        return torch.where(hit, t, inf), normal, p
    rot = rot_z(obj["angle"])  # box: local = rot^T (world - centre)
    half = torch.tensor(obj["half"], dtype=torch.float64)
    ol, dl = (o - c) @ rot, d @ rot
    t, _, hit = intersect_box(ol, dl, torch.stack([-half, half]), 0.0, math.inf)
    t = torch.where(hit & (t > 0), t, inf)
    pl = ol + t.clamp_max(1e9)[:, None] * dl
    axis = (pl.abs() / half).argmax(dim=-1)
    nl = torch.nn.functional.one_hot(axis, 3).double() * pl.gather(1, axis[:, None]).sign()
    return t, nl @ rot.T, pl


def _capsule(obj: dict, o: Tensor, d: Tensor, inf: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Ray / capsule (segment a-b of radius r): the infinite cylinder's hit where it projects inside the
    segment, else the nearer end sphere's."""
    a, b = (torch.tensor(obj[k], dtype=torch.float64) for k in ("a", "b"))
    r = obj["radius"]
    ba, oa = b - a, o - a
    baba = float(ba @ ba)
    bard, baoa = d @ ba, oa @ ba
    rdoa, oaoa = (d * oa).sum(-1), (oa * oa).sum(-1)
    qa = baba - bard * bard
    qb = baba * rdoa - baoa * bard
    qc = baba * oaoa - baoa * baoa - r * r * baba
    disc = qb * qb - qa * qc
    t_cyl = (-qb - disc.clamp_min(0).sqrt()) / torch.where(qa.abs() > 1e-12, qa, torch.full_like(qa, 1e-12))
    y = baoa + t_cyl * bard
    cyl = (disc >= 0) & (qa.abs() > 1e-12) & (y > 0) & (y < baba) & (t_cyl > 0)
    t = torch.where(cyl, t_cyl, inf)
    for end in (a, b):  # the end caps
        oc = o - end
        bb = (d * oc).sum(-1)
        h = bb * bb - (oc * oc).sum(-1) + r * r
        ts = -bb - h.clamp_min(0).sqrt()
        t = torch.where((h >= 0) & (ts > 0) & (ts < t), ts, t)
    p = o + t.clamp_max(1e9)[:, None] * d
    axis_pt = a + ((p - a) @ ba / baba).clamp(0, 1)[:, None] * ba
    normal = (p - axis_pt) / r
    return t, normal, p


def shade(obj: dict, normal: Tensor, p: Tensor) -> Tensor:
    """Lambertian colour (R, 3) of `obj` at texture coordinates p (R, 3) with world normals (R, 3)."""
    a, b = (torch.tensor(col, dtype=torch.float64) for col in obj["colours"])
    if obj["texture"] == "plain":
        w = torch.zeros_like(p[:, 0])
    elif obj["texture"] == "gradient":  # smooth: blend weight varies slowly over the object
        w = 0.5 + 0.5 * torch.sin(2.0 * p[:, 0] + 1.5 * p[:, 1] + 3.0 * p[:, 2])
    elif obj["texture"] == "half-checker":  # checker (2-D) where x > 0, the smooth gradient where x < 0
        checker = torch.floor(p[:, :2] / obj["cell"]).sum(-1).remainder(2)
        w = torch.where(p[:, 0] > 0, checker, 0.5 + 0.5 * torch.sin(2.0 * p[:, 0] + 1.5 * p[:, 1]))
    elif obj["texture"] == "dots":  # a dot (a ball cut by the surface) at a random place in each cell of 3 lattices
        w = torch.zeros_like(p[:, 0])
        for scale in obj["scales"]:
            q = p * scale
            cell = torch.floor(q)
            h = [torch.frac(torch.sin(cell @ torch.tensor(v, dtype=torch.float64)) * 43758.5453).abs()
                 for v in ((12.9898, 78.233, 37.719), (39.346, 11.135, 83.155), (73.156, 52.235, 9.151),
                           (27.17, 61.93, 44.71))]
            centre = cell + 0.25 + 0.5 * torch.stack(h[:3], -1)
            w = w + ((q - centre).norm(dim=-1) < 0.2 + 0.2 * h[3]).double()
        w = w.remainder(2)
    elif obj["texture"] == "stripes":
        w = torch.floor(p[:, 2] / (obj["period"] / 2)).remainder(2)
    else:  # checker: 2-D on the disc (its z is constant), 3-D on boxes
        w = torch.floor(p / obj["cell"]).sum(-1).remainder(2)
    albedo = a + w[:, None] * (b - a)
    if obj.get("emissive"):  # the sky glows: no shading
        return albedo.clamp(0, 1)
    light = AMBIENT + (1 - AMBIENT) * (normal @ LIGHT).clamp_min(0)
    return (albedo * light[:, None]).clamp(0, 1)


SUPERSAMPLE = 2  # each pixel averages SUPERSAMPLE^2 sub-pixel rays


def render_view(objects: list[dict], pose: Tensor, intrinsics: Tensor, size: int,
                supersample: int = SUPERSAMPLE) -> np.ndarray:
    """Ray-cast one square view -> (size, size, 4) float64 straight RGBA in [0, 1].

    pose (4, 4) camera-to-world, intrinsics (4,) fx, fy, cx, cy for `size` px. Sub-pixel rays are
    the pixel centres of a `supersample`-times larger image; their premultiplied colours are averaged.
    """
    s = supersample
    o, d = image_rays(pose, Intrinsics.of(intrinsics).scaled(s), size * s, size * s)
    o, d = o.double(), d.double()
    hits = [intersect(obj, o, d) for obj in objects]
    if not hits:  # no object: every ray misses
        return np.zeros((size, size, 4))
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


def _split_test(poses: np.ndarray, n_test: int) -> tuple[np.ndarray, np.ndarray]:
    n = len(poses)
    test = np.round(np.linspace(0, n - 1, n_test)).astype(int) if n_test else np.zeros(0, int)
    return poses[np.setdiff1d(np.arange(n), test)], poses[test]


def forward_poses(n_train: int, n_test: int, radius: float = RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """A forward-facing capture (as LLFF): n_train + n_test cameras spread over a disc of radius
    0.6 facing the scene from elevation 30 deg, each looking at the origin; test cameras are evenly
    spaced members of the sequence. -> train (n_train, 4, 4), test (n_test, 4, 4)."""
    n = n_train + n_test
    el = math.radians(30)
    base = radius * np.array([0.0, -math.cos(el), math.sin(el)])
    frame = look_at(base)
    i = np.arange(n)
    r = 0.6 * np.sqrt((i + 0.5) / n)
    a = i * math.pi * (3 - math.sqrt(5))
    pos = base + (r * np.cos(a))[:, None] * frame[:3, 0] + (r * np.sin(a))[:, None] * frame[:3, 1]
    return _split_test(np.stack([look_at(p) for p in pos]), n_test)


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
    return _split_test(np.stack([look_at(p) for p in pos]), n_test)


def orbit_poses(n_train: int, n_test: int, radius: float = RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """A walk around the scene, as a phone capture: n_train + n_test cameras evenly spaced on a circle, at elevations
    alternating between 25 and 40 deg, each looking at the origin. -> train (n_train, 4, 4), test (n_test, 4, 4)."""
    n = n_train + n_test
    az = 2 * math.pi * np.arange(n) / n
    el = np.radians(np.where(np.arange(n) % 2 == 0, 25.0, 40.0))
    pos = radius * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    return _split_test(np.stack([look_at(p) for p in pos]), n_test)


def ring_poses(n_train: int, n_test: int, radius: float = RING_RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """Cameras circling the content inside its world (the unbounded rig): n_train + n_test evenly around the up
    axis at distance `radius`, elevations alternating 8 and 20 deg, each looking at the content's middle
    (0, 0, FLOOR_Z + 0.2). -> train (n_train, 4, 4), test (n_test, 4, 4)."""
    n = n_train + n_test
    target = np.array([0.0, 0.0, FLOOR_Z + 0.2])
    poses = []
    for i in range(n):
        az, el = 2 * math.pi * i / n, math.radians(8 if i % 2 else 20)
        pos = target + radius * np.array([math.cos(az), math.sin(az), math.tan(el)])
        pose = look_at(pos - target)
        pose[:3, 3] = pos
        poses.append(pose)
    return _split_test(np.stack(poses), n_test)


def arc_poses(n_train: int, n_test: int, degrees: float, radius: float = ARC_RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """A phone walk part way around an object on a table (the half- and quarter-orbit rigs): n_train + n_test cameras
    evenly over `degrees` of azimuth centred on -y, `radius` from the object's middle (0, 0, FLOOR_Z + 0.25), at
    elevations alternating 10 and 25 deg (table height and a little above), each looking at that middle.
    -> train (n_train, 4, 4), test (n_test, 4, 4)."""
    n = n_train + n_test
    target = np.array([0.0, 0.0, FLOOR_Z + 0.25])
    azimuths = -0.5 * math.pi + math.radians(degrees) * (np.arange(n) / max(1, n - 1) - 0.5)
    poses = []
    for i, az in enumerate(azimuths):
        el = math.radians(25 if i % 2 else 10)
        way = radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        pose = look_at(way)
        pose[:3, 3] = target + way
        poses.append(pose)
    return _split_test(np.stack(poses), n_test)


# ----------------------------------------------------------------------------- writing

LAYOUTS = ("blender", "nsvf", "tanks", "llff", "nerfstudio", "colmap")
# lenses make-scene can render through (exactly: every sub-pixel ray goes through the inverse distortion), in the
# layouts that record one; coefficients as COLMAP's OPENCV and OPENCV_FISHEYE models take them (render/rays.py)
LENSES = {"pinhole": ({}, False), "opencv": ({"k1": -0.3, "k2": 0.1, "p1": 0.003, "p2": -0.002}, False),
          "fisheye": ({"k1": 0.08, "k2": -0.03, "k3": 0.01, "k4": -0.002}, True)}
LENS_LAYOUTS = ("nerfstudio", "colmap")
RIGS = ("sphere", "forward", "orbit", "unbounded", *ARCS)
OPAQUE_RIGS = ("unbounded", *ARCS)  # rigs inside a world of their own: every pixel shows a surface
CONTENT_BOX = [[-1.1, -1.1, -0.6], [1.1, 1.1, 0.4]]  # holds every object of every seed (within 0.002 in x, y)
# bbox.txt's room around CONTENT_BOX: more than a coarse cell of the demo recipe's 16^3 geometry grid (0.17), as
# docs/datasets.md asks of a given box. With none, the floor lay 0.1 above the bottom face, within a cell, and 4-5%
# of the foreground rays counted as content past the box (a false warning).
BBOX_ROOM = 0.25
CONTENT_RADIUS = 1.25  # every object of the default content lies within this distance of the origin


def content_radius(objects: list[dict]) -> float:
    """A distance from the origin that every point of `objects` lies within (the LLFF depth bounds): the thin
    content's wire reaches 1.57, the large content's floor 3.04. `CONTENT_RADIUS` for no object."""
    norm = lambda v: math.sqrt(sum(float(x) ** 2 for x in v))  # noqa: E731
    reach = [CONTENT_RADIUS]
    for obj in objects:
        kind = obj["kind"]
        if kind == "disc":
            c = obj["centre"]
            reach.append(math.hypot(norm(c[:2]) + obj["radius"], c[2]))
        elif kind == "sphere":
            reach.append(norm(obj["centre"]) + obj["radius"])
        elif kind == "box":
            reach.append(norm(obj["centre"]) + norm(obj["half"]))
        elif kind == "capsule":
            reach.append(max(norm(obj["a"]), norm(obj["b"])) + obj["radius"])
        else:
            raise ValueError(f"content_radius: unknown object kind {kind!r}")
    return max(reach)

LAYOUT_TEXT = {
    "blender": "Blender / nerf_synthetic layout: transforms_train.json and transforms_test.json, train/r_*.png and "
               "test/r_*.png RGBA 8-bit with a transparent background, camera_angle_x, OpenGL camera-to-world "
               "matrices.",
    "nsvf": "NSVF layout: rgb/0_*.png (train) and rgb/2_*.png (test) RGBA 8-bit with a transparent background, "
            "pose/<same name>.txt OpenCV camera-to-world 4x4 matrices, intrinsics.txt ('f cx cy 0' first line), "
            "bbox.txt (xmin ymin zmin xmax ymax zmax voxel_size).",
    "tanks": "Masked Tanks and Temples in the NSVF layout: rgb/0_*.png (train) and rgb/1_*.png (the val split, used "
             "as test) RGB 8-bit on a white background, pose/<same name>.txt OpenCV camera-to-world 4x4 matrices, "
             "intrinsics.txt (4x4 matrix K), bbox.txt.",
    "llff": "LLFF layout: poses_bounds.npy (3x5 [R|t|hwf] per image in LLFF axis order down/right/backwards, then "
            "near and far depth bounds), images/ and images_2/ (2x area-downscaled) RGB 8-bit PNGs on a white "
            "background; the test views at every 8th position (0, 8, ...), so the loader's every-8th hold-out gives "
            "the test split.",
    "nerfstudio": "nerfstudio layout: transforms.json (CAMERA_MODEL, fl_x fl_y cx cy w h, "
                  "OpenGL camera-to-world matrices), images/frame_*.png RGBA 8-bit, the test views at every 8th "
                  "position (0, 8, ...), so the loader's every-8th hold-out gives the test split.",
    "colmap": "COLMAP layout: sparse/0/cameras.bin, images.bin, points3D.bin (COLMAP's binary model: one shared "
              "camera, PINHOLE or the lens's OPENCV / OPENCV_FISHEYE; world-to-camera poses in OpenCV axes; surface "
              "points ray-cast from a grid of pixels of every view, with the views that see each), images/ and "
              "images_2/ RGB 8-bit PNGs on a white background, the test views at every 8th position (0, 8, ...).",
}

README = """Procedurally generated test scene (boostnerf make-scene), seed {seed}.

Not captured data: every image is rendered by exact analytic ray casting (ray/sphere, ray/box,
ray/plane intersections) of the objects listed in objects.json, with {ss}x{ss} supersampling per
pixel. {n_train} train and {n_test} test views, {size}x{size} pixels, camera_angle_x {angle}.
Cameras: {rig_text} World z up.

{layout_text}

{content_text} Free to use for any purpose.
"""

OBJECTS_TEXT = """Content (inside about [-1, 1]^2 x [-0.5, 0.3]): a floor disc with a fine checkerboard (cell 0.05),
a sphere with a smooth colour gradient, a sphere with thin stripes (period 0.06), a rotated box with a
fine 3-D checkerboard (cell 0.04) and a box with a smooth gradient; Lambertian shading under a fixed
directional light, no shadows."""
CONTENT_TEXT = {
    "objects": OBJECTS_TEXT,
    "thin": OBJECTS_TEXT + f""" Thin structures (content 'thin'): a cable on the floor near its rim, two upright rods at
the rim and a slanted wire to the far corner, capsules of radius {THIN_RADIUS}.""",
    "large": OBJECTS_TEXT.replace("a floor disc", f"a floor disc of radius {LARGE_FLOOR_RADIUS}").replace(
        "Content (inside about [-1, 1]^2 x [-0.5, 0.3])",
        "Content (content 'large': the floor reaches past every view's edge)"),
    "empty": "Content (content 'empty'): none; every pixel is background.",
    "detail": f"""Content (content 'detail', inside about [-1, 1]^2 x [-0.5, 0.2]): fine detail where x > 0 and smooth
content where x < 0. A floor disc with a checkerboard (cell {DETAIL_CELL}) on its x > 0 half and a smooth colour
gradient on the other; on the detailed half a rotated box with a 3-D checkerboard (cell {DETAIL_CELL}) and a sphere
with stripes (period {2 * DETAIL_CELL:g}), on the smooth half a sphere and a box with smooth gradients; Lambertian
shading under a fixed directional light, no shadows.""",
    "textured": """Content (content 'textured', inside about [-1, 1]^2 x [-0.5, 0.3]): the floor disc, two spheres and
two boxes of the default content, every surface speckled with round dots of three sizes in a light and a dark colour:
texture that SIFT finds and matches, for structure from motion; Lambertian shading under a fixed directional light,
no shadows.""",
}

RIG_TEXT = {
    "sphere": "radius {radius} on the upper hemisphere (elevation 10-70 deg, Fibonacci spiral) looking at the origin.",
    "forward": "forward-facing, spread over a disc of radius 0.6 at distance {radius} and elevation 30 deg, each "
               "looking at the origin.",
    "orbit": "radius {radius} on a circle around the scene (a walk around it), elevations alternating 25 and 40 deg, "
             "each looking at the origin.",
    "unbounded": f"a ring at distance {RING_RADIUS} around the content (elevations 8 and 20 deg), inside its world: a "
                 f"checkered ground and a banded, glowing sky dome, both of radius {WORLD_RADIUS}; every pixel "
                 "is opaque (an unbounded capture: its background is content).",
    **{rig: f"{degrees:g} deg of a walk around the content at distance {ARC_RADIUS} (elevations 10 and 25 deg), "
            f"as a phone capture of an object on a table: the content stands on a table in a closed room whose "
            "floor, walls and ceiling are speckled with dots; every pixel is opaque."
       for rig, degrees in ARCS.items()},
}


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


def _to8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)


def _on_white(rgba: np.ndarray) -> np.ndarray:
    """Straight RGBA (h, w, 4) float -> RGB composited on white, 8-bit."""
    return _to8(rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]))


def _write_blender(out: Path, views: dict, focal: float, size: int) -> None:
    for split, (poses, rgbas) in views.items():
        (out / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i, (pose, rgba) in enumerate(zip(poses, rgbas)):
            iio.imwrite(out / split / f"r_{i}.png", _to8(rgba))
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": pose.tolist()})
        meta = {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}
        (out / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


def _write_nsvf(out: Path, views: dict, focal: float, size: int, masked: bool) -> None:
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "pose").mkdir(parents=True, exist_ok=True)
    prefix = {"train": "0", "test": "1" if masked else "2"}
    for split, (poses, rgbas) in views.items():
        for i, (pose, rgba) in enumerate(zip(poses, rgbas)):
            stem = f"{prefix[split]}_{split}_{i:04d}"
            iio.imwrite(out / "rgb" / f"{stem}.png", _on_white(rgba) if masked else _to8(rgba))
            np.savetxt(out / "pose" / f"{stem}.txt", flip_axes(pose), fmt="%.17g")
    c = size / 2
    if masked:
        k = np.array([[focal, 0, c, 0], [0, focal, c, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
        np.savetxt(out / "intrinsics.txt", k, fmt="%.17g")
    else:
        (out / "intrinsics.txt").write_text(f"{focal!r} {c!r} {c!r} 0.\n0. 0. 0.\n1.\n{size} {size}\n")
    box = [[round(v - BBOX_ROOM, 6) for v in CONTENT_BOX[0]], [round(v + BBOX_ROOM, 6) for v in CONTENT_BOX[1]]]
    (out / "bbox.txt").write_text(" ".join(repr(float(v)) for v in box[0] + box[1]) + " 0.05\n")


HOLDOUT_EVERY = 8  # the loaders' default hold-out for layouts without a test split


SEQUENCE_LAYOUTS = ("llff", "nerfstudio", "colmap")  # one sequence of views, no split files: the loader holds views out


def written_test_views(layout: str, n_train: int, n_test: int) -> int:
    """How many test views `make_scene` writes in `layout` when `n_test` are asked for. A layout without splits
    holds out every 8th view (places 0, 8, 16, ...), so its test split is exactly its test views only when they
    fill those places: t test views with t = ceil((n_train + t) / 8), that is ceil(n_train / 7) <= t <= 1 +
    n_train // 7 (24 train views take 4; 28 take 4 or 5). `n_test` when it is such a t, else the nearest one:
    more test views would be trained on, fewer would leave train views held out. None stay none."""
    if layout not in SEQUENCE_LAYOUTS or not n_test:
        return n_test
    step = HOLDOUT_EVERY - 1
    return min(max(n_test, -(-n_train // step)), 1 + n_train // step)


def sequence_order(n_train: int, n_test: int) -> list[tuple[str, int]]:
    """The order of the views in layouts without splits (LLFF, nerfstudio): test view j at position
    8 j while test views last, the train views in order around them, so that the loaders' every-8th
    hold-out gives back exactly the test split (and the same training views as the Blender layout)."""
    order, train, test = [], iter(range(n_train)), iter(range(n_test))
    for pos in range(n_train + n_test):
        j = next(test, None) if pos % HOLDOUT_EVERY == 0 else None
        if j is None:
            i = next(train, None)
            order.append(("train", i) if i is not None else ("test", next(test)))
        else:
            order.append(("test", j))
    return order


def _all_views(views: dict) -> tuple[np.ndarray, list[np.ndarray]]:
    """Every view as one sequence (layouts without splits), in `sequence_order`."""
    n_test = len(views["test"][0]) if "test" in views else 0
    order = sequence_order(len(views["train"][0]), n_test)
    return np.stack([views[s][0][i] for s, i in order]), [views[s][1][i] for s, i in order]


def _write_llff(out: Path, views: dict, focal: float, size: int, radius: float) -> None:
    poses, rgbas = _all_views(views)
    for folder, factor in (("images", 1), ("images_2", 2)):
        (out / folder).mkdir(parents=True, exist_ok=True)
        for i, rgba in enumerate(rgbas):
            rgb = _on_white(rgba if factor == 1 else _premultiplied_mean(rgba, factor))
            iio.imwrite(out / folder / f"image{i:03d}.png", rgb)
    rows = []
    for pose in poses:
        llff = np.stack([-pose[:3, 1], pose[:3, 0], pose[:3, 2], pose[:3, 3]], axis=1)  # down, right, back, t
        depth = float(np.linalg.norm(pose[:3, 3]))  # the cameras look at the origin
        near, far = max(0.05, depth - radius), depth + radius
        hwf = np.array([[size], [size], [focal]], dtype=np.float64)
        rows.append(np.concatenate([np.concatenate([llff, hwf], axis=1).ravel(), [near, far]]))
    np.save(out / "poses_bounds.npy", np.stack(rows))


def _premultiplied_mean(rgba: np.ndarray, factor: int) -> np.ndarray:
    """Box-downscale straight RGBA by `factor` (premultiplied average), back to straight RGBA."""
    h, w = rgba.shape[0] // factor, rgba.shape[1] // factor
    pre = np.concatenate([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], axis=-1)[: h * factor, : w * factor]
    pre = pre.reshape(h, factor, w, factor, 4).mean(axis=(1, 3))
    return np.concatenate([pre[..., :3] / np.maximum(pre[..., 3:], 1e-12), pre[..., 3:]], axis=-1)


def _write_nerfstudio(out: Path, views: dict, focal: float, size: int, lens: str = "pinhole",
                      opaque: bool = False) -> None:
    """`opaque`: RGB images (every pixel hits the unbounded rig's world), else RGBA."""
    poses, rgbas = _all_views(views)
    (out / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (pose, rgba) in enumerate(zip(poses, rgbas)):
        iio.imwrite(out / "images" / f"frame_{i + 1:05d}.png", _to8(rgba[..., :3] if opaque else rgba))
        frames.append({"file_path": f"images/frame_{i + 1:05d}.png", "transform_matrix": pose.tolist()})
    coefficients, fisheye = LENSES[lens]
    meta = {"camera_model": "OPENCV_FISHEYE" if fisheye else "OPENCV", "fl_x": focal, "fl_y": focal, "cx": size / 2,
            "cy": size / 2, "w": size, "h": size, "k1": 0.0, "k2": 0.0, **({} if fisheye else {"p1": 0.0, "p2": 0.0}),
            **coefficients, "frames": frames}
    (out / "transforms.json").write_text(json.dumps(meta, indent=2))


def _colmap_points(objects: list[dict], poses: np.ndarray, k: Tensor, size: int,
                   per_side: int = 12) -> tuple[np.ndarray, np.ndarray, list[list[tuple[int, float, float]]]]:
    """Surface points for a COLMAP model: the first hits of a `per_side`^2 grid of pixel rays of every view, and for
    each the views that see it (in the image, nothing nearer on the way) with where: -> xyz (P, 3), rgb (P, 3) uint8,
    observations[p] = [(view, u, v), ...]. A scene without objects has none (an empty model)."""
    if not objects:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), []
    rows = torch.div(torch.arange(per_side) * size, per_side, rounding_mode="floor") + size // (2 * per_side)
    index = (rows[:, None] * size + rows[None, :]).reshape(-1)
    xyz, rgb = [], []
    for pose in poses:
        o, d = image_rays(torch.from_numpy(pose).float(), k, size, size)
        o, d = o[index].double(), d[index].double()
        hits = [intersect(obj, o, d) for obj in objects]
        if not hits:
            continue
        t_all = torch.stack([h[0] for h in hits])
        nearest, t = t_all.argmin(0), t_all.min(0).values
        for kk, (obj, (_, n, pk)) in enumerate(zip(objects, hits)):
            m = (nearest == kk) & torch.isfinite(t)
            xyz.append((o + t[:, None] * d)[m])
            rgb.append(shade(obj, n[m], pk[m]))
    xyz_t = torch.cat(xyz) if xyz else torch.zeros(0, 3, dtype=torch.float64)
    seen: list[list[tuple[int, float, float]]] = [[] for _ in range(len(xyz_t))]
    for j, pose in enumerate(poses):
        p = torch.from_numpy(pose)
        uv, depth = project_points(xyz_t.float(), p.float(), k)
        inside = (depth > 0) & (uv >= 0).all(-1) & (uv < size).all(-1)
        way = xyz_t - p[:3, 3]
        dist = way.norm(dim=-1)
        d = way / dist[:, None]
        t_first = torch.stack([intersect(obj, p[:3, 3].expand_as(d), d)[0] for obj in objects]).min(0).values
        for i in torch.nonzero(inside & ((t_first - dist).abs() < 1e-6 * dist + 1e-9)).flatten().tolist():
            seen[i].append((j, float(uv[i, 0]), float(uv[i, 1])))
    return xyz_t.numpy(), _to8(torch.cat(rgb).numpy()) if rgb else np.zeros((0, 3), np.uint8), seen


def _write_colmap(out: Path, views: dict, k: Tensor, size: int, lens: str, objects: list[dict]) -> None:
    from boostnerf_cli.scenes.colmap_model import Model, ModelCamera, ModelImage, quaternion, write_model

    poses, rgbas = _all_views(views)
    for folder, factor in (("images", 1), ("images_2", 2)):
        (out / folder).mkdir(parents=True, exist_ok=True)
        for i, rgba in enumerate(rgbas):
            iio.imwrite(out / folder / f"image{i:03d}.png",
                        _on_white(rgba if factor == 1 else _premultiplied_mean(rgba, factor)))
    coefficients, fisheye = LENSES[lens]
    fx, fy, cx, cy = (float(v) for v in k[:PINHOLE])
    if fisheye:
        camera = ModelCamera("OPENCV_FISHEYE", size, size, [fx, fy, cx, cy] + [coefficients.get(n, 0.0)
                                                                             for n in ("k1", "k2", "k3", "k4")])
    elif coefficients:
        camera = ModelCamera("OPENCV", size, size, [fx, fy, cx, cy] + [coefficients.get(n, 0.0)
                                                                     for n in ("k1", "k2", "p1", "p2")])
    else:
        camera = ModelCamera("PINHOLE", size, size, [fx, fy, cx, cy])
    xyz, rgb, seen = _colmap_points(objects, poses, k, size)
    keep = [i for i, s in enumerate(seen) if len(s) >= 2]  # a point of a model is seen twice at least
    observations: list[list] = [[] for _ in poses]
    tracks = []
    for pid, i in enumerate(keep):
        track = []
        for j, u, v in seen[i]:
            track.append((j + 1, len(observations[j])))
            observations[j].append((u, v, pid + 1))
        tracks.append(np.array(track, dtype=np.int64))
    images = {}
    for j, pose in enumerate(poses):
        w2c = np.linalg.inv(flip_axes(pose))
        obs = np.array(observations[j], dtype=np.float64).reshape(-1, 3)
        images[j + 1] = ModelImage(quaternion(w2c[:3, :3]), w2c[:3, 3], 1, f"image{j:03d}.png", obs[:, :2],
                                   obs[:, 2].astype(np.int64))
    model = Model({1: camera}, images, xyz[keep].reshape(-1, 3), rgb[keep].reshape(-1, 3), np.full(len(keep), 0.1),
                  np.arange(1, len(keep) + 1, dtype=np.int64), tracks)
    write_model(model, out / "sparse" / "0", "bin")


def _camera_model_text(lens: str) -> str:
    """How transforms.json names the camera of `lens` (`_write_nerfstudio`), for README.txt."""
    if lens == "fisheye":
        return "camera_model OPENCV_FISHEYE, its k1 k2 k3 k4"
    return "camera_model OPENCV, " + ("zero distortion" if lens == "pinhole" else "its k1 k2 p1 p2")


def _checked_arguments(size: int, n_train: int, n_test: int, seed: int, layout: str, rig: str | None,
                       lens: str) -> str:
    """make-scene's arguments checked, one line for the first wrong one (before anything is written). -> the rig."""
    if size < 4 or n_train < 1 or n_test < 0 or seed < 0:
        raise BoostNerfError(
            f"make-scene needs size >= 4, n_train >= 1, n_test >= 0, seed >= 0 "
            f"(got size={size}, n_train={n_train}, n_test={n_test}, seed={seed})"
        )
    if layout not in LAYOUTS:
        raise BoostNerfError(f"unknown scene layout {layout!r}: use one of {', '.join(LAYOUTS)}")
    rig = rig or ("forward" if layout == "llff" else "sphere")
    if rig not in RIGS:
        raise BoostNerfError(f"unknown camera rig {rig!r}: use one of {', '.join(RIGS)}")
    if lens not in LENSES:
        raise BoostNerfError(f"unknown lens {lens!r}: use one of {', '.join(LENSES)}")
    if lens != "pinhole" and layout not in LENS_LAYOUTS:
        raise BoostNerfError(f"the {layout} layout records no lens distortion: use --lens with "
                             f"{' or '.join(LENS_LAYOUTS)}")
    if layout == "llff" and rig != "forward":
        raise BoostNerfError(f"the llff layout is forward-facing: --rig {rig} looks all around the scene; use --rig "
                             "forward, or another --format (blender, nerfstudio, colmap ...) for this rig")
    if rig in OPAQUE_RIGS and layout != "nerfstudio":
        raise BoostNerfError(f"--rig {rig} writes an opaque capture in the nerfstudio layout, not {layout}: "
                             "add --format nerfstudio")
    return rig


def make_scene(out_dir: Path, size: int = 64, n_train: int = 24, n_test: int = 8, seed: int = 0,
               layout: str = "blender", rig: str | None = None, content: str = "objects",
               lens: str = "pinhole") -> Path:
    """Render the seeded procedural scene into `out_dir` in `layout` (one of `LAYOUTS`) and return `out_dir`.

    rig: "sphere" (cameras on the upper hemisphere), "forward" (forward-facing), "unbounded" (nerfstudio layout
    only: `ring_poses` inside the content's `environment`, opaque images), or "half-orbit" / "quarter-orbit"
    (nerfstudio layout only: `arc_poses` around the content on a table in a `room`, opaque images); default
    forward for llff, sphere otherwise. Every layout gets the same views for the same arguments and the same number of
    test views written (`written_test_views`: LLFF and nerfstudio may write another number than asked, and
    then every camera moves along the spiral, which spans train and test views). Blender:
    transforms_train.json, transforms_test.json (omitted when n_test = 0), train/r_*.png, test/r_*.png;
    the other layouts as `LAYOUT_TEXT` says. Always objects.json (the exact geometry) and README.txt.
    content: "objects" (default), "thin" (plus rods and a cable one to two pixels wide at 100 px,
    reaching the content box's edge: the scene that checks that skipping never cuts thin structure),
    "large" (a floor reaching past the camera-derived box) or "empty" (`scene_objects`).
    lens: "pinhole", or a distorting lens of `LENSES` ("opencv", "fisheye") for the layouts that record one
    (`LENS_LAYOUTS`): every view is ray-cast through it exactly, and the files name its model and coefficients.
    Deterministic: the same arguments give byte-identical files. Refuses a folder that already holds files.
    """
    rig = _checked_arguments(size, n_train, n_test, seed, layout, rig, lens)
    objects = scene_objects(seed, content)  # checks `content`, before anything is written
    if rig == "unbounded":
        objects = objects + environment()
    elif rig in ARCS:
        objects = objects + room()
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise BoostNerfError(f"{out_dir} is a file: make-scene writes a scene folder; choose a new folder")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        raise BoostNerfError(f"{out_dir} already holds files: make-scene writes into a new or empty folder (another "
                             "scene's files would mix with this one's); choose a new folder or delete this one")
    n_test = written_test_views(layout, n_train, n_test)  # the views of a Blender scene with that many test views
    if rig in ARCS:
        train, test = arc_poses(n_train, n_test, ARCS[rig])
    else:
        train, test = {"forward": forward_poses, "orbit": orbit_poses, "sphere": camera_poses,
                       "unbounded": ring_poses}[rig](n_train, n_test)
    angle = RING_ANGLE_X if rig in OPAQUE_RIGS else CAMERA_ANGLE_X
    focal = 0.5 * size / math.tan(0.5 * angle)
    k = rows([Intrinsics(focal, focal, size / 2, size / 2, Lens(**LENSES[lens][0], fisheye=LENSES[lens][1]))])[0]
    views = {}
    with _single_thread():
        for split, poses in (("train", train), ("test", test)):
            if len(poses):
                views[split] = (poses, [render_view(objects, torch.from_numpy(p).float(), k, size, SUPERSAMPLE)
                                        for p in poses])
    # Written to `.NAME.tmp` beside the folder and renamed when complete: a run stopped half way never leaves a
    # half-written scene that a later run would take for a complete one (a workspace's lock removes the leftover).
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.parent / f".{out_dir.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        if layout == "blender":
            _write_blender(tmp, views, focal, size)
        elif layout in ("nsvf", "tanks"):
            _write_nsvf(tmp, views, focal, size, masked=layout == "tanks")
        elif layout == "llff":
            _write_llff(tmp, views, focal, size, content_radius(objects))
        elif layout == "colmap":
            _write_colmap(tmp, views, k, size, lens, objects)
        else:
            _write_nerfstudio(tmp, views, focal, size, lens, opaque=rig in OPAQUE_RIGS)
        (tmp / "objects.json").write_text(json.dumps({"seed": seed, "content": content, "objects": objects}, indent=2))
        text = README.format(seed=seed, ss=SUPERSAMPLE, n_train=n_train, n_test=n_test, size=size,
                             angle=angle,
                             rig_text=RIG_TEXT[rig].format(radius=RADIUS),
                             layout_text=LAYOUT_TEXT[layout].replace("CAMERA_MODEL", _camera_model_text(lens))
                             + (f" Lens: {lens}, {LENSES[lens][0]}." if lens != "pinhole" else ""),
                             content_text=CONTENT_TEXT[content])
        (tmp / "README.txt").write_text(text)
        if out_dir.is_dir():
            out_dir.rmdir()  # empty (checked above)
        tmp.rename(out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def content_outside(folder: Path, poses: Tensor, intrinsics: Tensor, height: int, width: int, box: Tensor) -> float:
    """The share of the pixels of views (poses (N, 4, 4), intrinsics (N, 4), height x width) of the procedural scene
    in `folder` (its objects.json) whose first surface, by exact ray casting through the pixel centres, lies outside
    `box` (2, 3): what a bounded scene cannot place where it is (the unbounded rig's far ground and sky)."""
    objects = json.loads((Path(folder) / "objects.json").read_text())["objects"]
    outside = total = 0
    lo, hi = box[0].double(), box[1].double()
    for pose, k in zip(poses, intrinsics):
        o, d = (v.double() for v in image_rays(pose, k, height, width))
        t = torch.stack([intersect(obj, o, d)[0] for obj in objects]).min(0).values
        p = o + t.clamp_max(1e9)[:, None] * d
        outside += int(((p < lo) | (p > hi)).any(-1).sum())
        total += p.shape[0]
    return outside / max(1, total)
