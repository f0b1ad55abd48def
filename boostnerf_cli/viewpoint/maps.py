"""A mixture's maps, as `render --per-expert` writes them and the viewer shows them: each expert's share of the
mixture, the gate's probability for one expert, the routing colours (every expert's probability in its `palette`
colour), and the depth picture of any model."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from boostnerf_cli.images import colorize_depth, to_uint8
from boostnerf_cli.moe.mixture import GateView, Mixture
from boostnerf_cli.render.packing import Packer
from boostnerf_cli.render.renderer import Camera, RenderSettings, render_image
from boostnerf_cli.scenes import Scene

# routing colours, smallest expert first: blue, cyan, green, orange, red, then grey
PALETTE = np.array([[40, 90, 255], [0, 200, 220], [60, 200, 60], [255, 160, 0], [230, 30, 30]], dtype=np.float64) / 255


def palette(m: int) -> np.ndarray:
    """(m, 3) routing colours in [0, 1], smallest expert first."""
    extra = np.full((max(0, m - len(PALETTE)), 3), 0.6)
    return np.concatenate([PALETTE[:m], extra])


def expert_share(mix: Mixture, e: int, camera: Camera, settings: RenderSettings, skip, device: str,
                 packer: Packer | None = None) -> np.ndarray:
    """Expert `e`'s share of the mixture: its density times its routed weight, its own colour, composited on the
    scene's background -> uint8 (H, W, 3)."""
    return to_uint8(render_image(mix.expert_only(e), camera, settings, skip, device, packer)["rgb"])


def gate_probability(mix: Mixture, e: int, camera: Camera, settings: RenderSettings, skip, device: str,
                     packer: Packer | None = None) -> np.ndarray:
    """The gate's probability G(x)_e averaged along each ray with the rendering weights, in [0, 1] -> (H, W); 0 where
    the ray hits nothing (opacity < 0.1)."""
    g = render_image(GateView(mix, e), camera, replace(settings, background=(0.0, 0.0, 0.0)), skip, device, packer)
    acc = g["acc"].numpy()
    return np.where(acc > 0.1, g["rgb"].numpy()[..., 0] / np.maximum(acc, 1e-6), 0.0).clip(0, 1)


def routing_colours(probs: np.ndarray) -> np.ndarray:
    """Per-pixel gate probabilities (H, W, M) -> uint8 (H, W, 3), each expert's colour (`palette`) weighted by them."""
    return to_uint8(probs @ palette(probs.shape[-1]))


def grey(prob: np.ndarray) -> np.ndarray:
    """(H, W) in [0, 1] -> uint8 (H, W, 3) greyscale, white = 1."""
    return to_uint8(np.repeat(prob[..., None], 3, -1))


def depth_picture(r: dict, scene: Scene) -> np.ndarray:
    """A render's expected surface depth (depth / opacity) -> uint8 (H, W, 3): near bright, far dark, between the
    frame's 1st and 99th percentile of the pixels with opacity >= 0.5; black where nothing is hit."""
    acc = r["acc"].numpy()
    depth = r["depth"].numpy() / np.maximum(acc, 1e-6)
    seen = depth[acc >= 0.5]
    lo, hi = np.percentile(seen, [1, 99]) if seen.size else (scene.near, scene.far)
    return colorize_depth(depth, acc, float(lo), float(max(hi, lo + 1e-6)))
