"""What the viewer draws around a frame, and where it stands first: the dataset's cameras as frustums with their
images, the box's edges, the density volume's kept cells coloured by the expert the gate picks there; the subject the
cameras look at, the first view (a training camera), and the sizes the frustums and cells are drawn at, from the
cameras' own spacing (a scene ten times larger draws them ten times larger)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields import grid as G
from boostnerf_cli.images import to_uint8
from boostnerf_cli.moe.mixture import Mixture
from boostnerf_cli.render.contraction import Contraction
from boostnerf_cli.render.paths import focus_point, mean_pose
from boostnerf_cli.render.renderer import Camera
from boostnerf_cli.scenes import Scene
from boostnerf_cli.viewpoint.camera import dataset_camera, fov_of, opencv_pose
from boostnerf_cli.viewpoint.maps import palette

# A frustum's depth (its size): at most this share of the median distance between neighbouring cameras (a neighbour's
# frustum then stays out of the middle of a training view) and of the cameras' median distance to their subject (a
# frustum across the scene, behind the subject, covers a twentieth of a view's height)
FRUSTUM_SPACING = 0.5
FRUSTUM_REACH = 0.1
HIDE_WITHIN = 2.0  # a frustum whose apex is within this many frustum sizes of a page's camera is not drawn
CELL_SHARE = 0.5  # a kept cell is drawn this share of its side wide: the render shows between the cells


@dataclass
class Frustum:
    """One dataset camera to draw: its split and name, OpenCV pose (4, 4), vertical field of view, aspect and a small
    copy of its image (uint8)."""

    split: str
    name: str
    pose: np.ndarray
    fov: float
    aspect: float
    thumbnail: np.ndarray


def frustums(scene: Scene, thumb: int = 64) -> list[Frustum]:
    """The scene's training and held-out cameras, each with its image shrunk to at most `thumb` pixels a side."""
    out = []
    held = scene.held_out()
    for name, split in (("train", scene.split("train")), *((("test", held),) if held is not None else ())):
        step = max(1, math.ceil(max(split.height, split.width) / thumb))
        for i in range(len(split)):
            cam = dataset_camera(split, i)
            out.append(Frustum(name, split.names[i], opencv_pose(cam.pose), fov_of(cam), split.width / split.height,
                               to_uint8(split.images[i][::step, ::step])))
    return out


def box_edges(bbox: torch.Tensor) -> np.ndarray:
    """The 12 edges of an axis-aligned box (2, 3) -> (12, 2, 3) segment end points."""
    lo, hi = bbox.double().cpu().numpy()
    corners = np.array([[(hi if (c >> k) & 1 else lo)[k] for k in range(3)] for c in range(8)])
    pairs = [(a, a | (1 << k)) for a in range(8) for k in range(3) if not (a >> k) & 1]
    return np.stack([corners[[a, b]] for a, b in pairs])


def world_box(bbox: torch.Tensor, contraction: Contraction | None) -> torch.Tensor:
    """The box to draw in the world (2, 3): a bounded scene's own; an unbounded scene's is the box of contracted
    space, whose world is the box around the sphere kept linear (centre +- radius)."""
    if contraction is None:
        return bbox
    c = torch.tensor(contraction.centre, dtype=torch.float64)
    return torch.stack([c - contraction.radius, c + contraction.radius])


def in_world(points: torch.Tensor, contraction: Contraction | None) -> torch.Tensor:
    """(N,) bool: which points (N, 3) of the space the fields see are where they are in the world, at world size: all
    of a bounded scene's; of an unbounded scene's contracted space, those in the sphere kept linear (the shell beyond
    holds the rest of the world squashed, out to infinity)."""
    if contraction is None:
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    centre = torch.tensor(contraction.centre, dtype=points.dtype, device=points.device)
    return (points - centre).norm(dim=-1) <= contraction.radius


class Cells(NamedTuple):
    """The kept cells to draw: points (N, 3) float32 in the world, colours (N, 3) uint8, and the width each is drawn
    at (world units: `CELL_SHARE` of the cell's side)."""

    points: np.ndarray
    colours: np.ndarray
    width: float


@torch.no_grad()
def routed_cells(mix: Mixture, contraction: Contraction | None = None, limit: int = 50_000, seed: int = 0) -> Cells:
    """The density volume's kept cells (lattice points in an occupied cell whose V_D opacity over one step exceeds T:
    what the mixture's empty-space filter keeps) that lie in the world at world size (`in_world`: an unbounded
    scene's, those of the sphere kept linear), at most `limit` of them (an even draw), each coloured by the expert
    the gate picks there (its largest logit; `palette`), drawn `CELL_SHARE` of a cell's side wide."""
    vd = mix.vd
    pts = G.lattice_points(vd.bbox, vd.shape)
    kept = torch.cat([mix.skip(pts[i : i + (1 << 18)]) for i in range(0, pts.shape[0], 1 << 18)])
    pts = pts[kept & in_world(pts, contraction)]
    if pts.shape[0] > limit:
        pick = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(seed))[:limit]
        pts = pts[pick.sort().values.to(pts.device)]
    choice = torch.cat([mix.gate.logits(pts[i : i + (1 << 16)]).argmax(-1) for i in range(0, pts.shape[0], 1 << 16)]) \
        if pts.shape[0] else torch.zeros(0, dtype=torch.long)
    colours = (palette(mix.m)[choice.cpu().numpy()] * 255 + 0.5).astype(np.uint8)
    return Cells(pts.float().cpu().numpy(), colours, CELL_SHARE * vd.unit)


# --- where the viewer stands, and the frustums' size ------------------------------------------------------------------
def camera_positions(scene: Scene) -> np.ndarray:
    """The centres (N, 3) float64 of the cameras `frustums` draws, in its order (train, then held-out)."""
    held = scene.held_out()
    poses = [scene.split("train").poses, *((held.poses,) if held is not None else ())]
    return torch.cat(poses)[:, :3, 3].double().numpy()


def subject(scene: Scene) -> np.ndarray:
    """The point the training cameras look at (world, (3,) float64): the point nearest their optical axes
    (`render.paths.focus_point`); where the axes are parallel (a forward-facing capture, one camera), the point on
    the mean camera's axis at the depth of the box's centre (a forward-facing scene's box is in NDC: its z is the
    depth 2 near / (1 - z))."""
    poses = scene.split("train").poses
    try:
        return focus_point(poses).double().numpy()
    except BoostNerfError:
        pass
    mean = mean_pose(poses).double().numpy()
    position, forward = mean[:3, 3], -mean[:3, 2]
    centre = scene.bbox.double().mean(0).numpy()
    if scene.ndc is not None:
        depth = scene.ndc.depth(min(float(centre[2]), 0.9))  # z -> 1 is infinitely far
    else:
        depth = float((centre - position) @ forward)
        depth = depth if depth > 0 else float(np.linalg.norm(centre - position)) or 1.0
    return position + depth * forward


def frustum_size(positions: np.ndarray, target: np.ndarray) -> float:
    """The depth the cameras' frustums are drawn at, for cameras at `positions` (N, 3) looking at `target` (3,):
    `FRUSTUM_SPACING` of the median distance from a camera to its nearest neighbour, at most `FRUSTUM_REACH` of the
    cameras' median distance to `target` (one camera: that alone). Proportional to the scene's scale."""
    positions = np.asarray(positions, np.float64)
    sizes = [FRUSTUM_REACH * float(np.median(np.linalg.norm(positions - target, axis=-1)))]
    if len(positions) > 1:
        nearest = np.concatenate([_nearest(positions, i) for i in range(0, len(positions), 512)])
        nearest = nearest[nearest > 0]  # cameras at one place (a rig's) do not make the frustums vanish
        if len(nearest):
            sizes.append(FRUSTUM_SPACING * float(np.median(nearest)))
    return min(s for s in sizes if s > 0) if any(s > 0 for s in sizes) else 1.0


def _nearest(positions: np.ndarray, start: int, rows: int = 512) -> np.ndarray:
    """The distance from each of the cameras `start` .. `start + rows` to its nearest other camera: a block of rows
    of the N x N distances at a time (all of them at once: 600 MB for 5,000 cameras)."""
    block = positions[start : start + rows]
    gaps = np.linalg.norm(block[:, None] - positions[None], axis=-1)
    gaps[np.arange(len(block)), start + np.arange(len(block))] = np.inf
    return gaps.min(1)


def hidden_frustums(positions: np.ndarray, eyes: list[np.ndarray], size: float) -> set[int]:
    """The frustums (indices into `positions`, their apexes) not drawn while pages look from `eyes` (world
    positions): those within `HIDE_WITHIN` frustum sizes of an eye; the camera a page stands at would fill its view
    with its own image, a close neighbour's cover part of it."""
    if not eyes or len(positions) == 0:
        return set()
    gaps = np.linalg.norm(np.asarray(positions)[:, None] - np.asarray(eyes, np.float64)[None], axis=-1)
    return {int(k) for k in np.flatnonzero(gaps.min(1) <= HIDE_WITHIN * size)}


def first_view(poses: torch.Tensor) -> int:
    """The training view the viewer shows first: the one whose viewing direction is nearest the cameras' mean
    direction (the middle of a walk part way round, the front of a forward-facing capture); the first of those that
    tie (cameras all round at one height)."""
    forward = -poses[:, :3, 2].double()
    forward = forward / forward.norm(dim=-1, keepdim=True)
    score = (forward @ forward.mean(0)).numpy()
    return int(np.flatnonzero(score >= score.max() - 1e-6)[0])


@dataclass(frozen=True)
class Eye:
    """The browser's camera (world): where it stands, the point it looks at (and orbits), its image's up, its
    vertical field of view (radians)."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov: float


def eye_at(camera: Camera, target: np.ndarray) -> Eye:
    """The browser's camera at dataset camera `camera`: at its centre, looking down its axis with its up and its
    field of view; the point it looks at is on its axis at `target`'s depth (`target`'s distance when that lies
    beside or behind it), so the page orbits the subject."""
    pose = camera.pose.double().numpy()
    position, forward = pose[:3, 3], -pose[:3, 2]
    to = np.asarray(target, np.float64) - position
    distance = float(np.linalg.norm(to))
    depth = float(to @ forward)
    depth = depth if depth > 0.1 * distance else distance
    depth = max(depth, 1e-6 * max(1.0, float(np.linalg.norm(position))))
    return Eye(position, position + depth * forward, pose[:3, 1], fov_of(camera))
