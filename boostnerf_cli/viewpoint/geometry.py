"""What the viewer draws around a frame: the dataset's cameras as frustums with their images, the box's edges, and
the density volume's kept cells coloured by the expert the gate picks there."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from boostnerf_cli.fields import grid as G
from boostnerf_cli.images import to_uint8
from boostnerf_cli.moe.mixture import Mixture
from boostnerf_cli.scenes import Scene
from boostnerf_cli.viewpoint.camera import dataset_camera, fov_of, opencv_pose
from boostnerf_cli.viewpoint.maps import palette


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


@torch.no_grad()
def routed_cells(mix: Mixture, limit: int = 50_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The density volume's kept cells (lattice points in an occupied cell whose V_D opacity over one step exceeds T:
    what the mixture's empty-space filter keeps), at most `limit` of them (an even draw), each coloured by the expert
    the gate picks there (its largest logit; `palette`) -> points (N, 3) float32, colours (N, 3) uint8."""
    vd = mix.vd
    pts = G.lattice_points(vd.bbox, vd.shape)
    kept = torch.cat([mix.skip(pts[i : i + (1 << 18)]) for i in range(0, pts.shape[0], 1 << 18)])
    pts = pts[kept]
    if pts.shape[0] > limit:
        pick = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(seed))[:limit]
        pts = pts[pick.sort().values.to(pts.device)]
    choice = torch.cat([mix.gate.logits(pts[i : i + (1 << 16)]).argmax(-1) for i in range(0, pts.shape[0], 1 << 16)]) \
        if pts.shape[0] else torch.zeros(0, dtype=torch.long)
    colours = (palette(mix.m)[choice.cpu().numpy()] * 255 + 0.5).astype(np.uint8)
    return pts.float().cpu().numpy(), colours
