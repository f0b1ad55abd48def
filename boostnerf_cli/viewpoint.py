"""One camera's picture of a model, and the scene's geometry, for `boostnerf view` and `render --camera`.

Nothing here knows a browser: `frame` renders what a camera sees of a model as one of `MODES` (the same maps
`render --per-expert` writes: `expert_share`, `gate_probability`, `routing_colours`), `scene_geometry` gives the
cameras, the box and the density volume's kept cells coloured by the expert the gate picks there, and a saved view
(`save_view`, `read_view`) is a PNG and its camera as JSON that `render --camera FILE` renders again.

Poses are the scenes' OpenGL camera-to-world matrices (the camera looks down -z, +y up); `opencv_pose` turns one into
the OpenCV convention (looks down +z, +y down) that a browser viewer's cameras use, `camera_for_view` back.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import ROW_WIDTHS, Intrinsics, flip_axes
from boostnerf_cli.costs import gflops_of
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields import grid as G
from boostnerf_cli.images import colorize_depth, to_uint8, write_png
from boostnerf_cli.models import ALL_SKIPS, LoadedModel, Skips
from boostnerf_cli.moe.mixture import GateView, Mixture
from boostnerf_cli.render.packing import DYNAMIC, Packer, packer_for
from boostnerf_cli.render.renderer import Camera, RenderSettings, render_image
from boostnerf_cli.scenes import Scene, Split
from boostnerf_cli.workspace import MALFORMED, read_json, write_json

# what a frame shows: the render's colour, its depth, the routing colours (every expert's gate probability), one
# expert's share of the mixture, the gate's probability for one expert
MODES = ("colour", "depth", "routing", "share", "gate")
MIXTURE_MODES = ("routing", "share", "gate")  # only a mixture has them

# routing colours, smallest expert first: blue, cyan, green, orange, red, then grey
PALETTE = np.array([[40, 90, 255], [0, 200, 220], [60, 200, 60], [255, 160, 0], [230, 30, 30]], dtype=np.float64) / 255


def palette(m: int) -> np.ndarray:
    """(m, 3) routing colours in [0, 1], smallest expert first."""
    extra = np.full((max(0, m - len(PALETTE)), 3), 0.6)
    return np.concatenate([PALETTE[:m], extra])


# --- the maps of a mixture (render --per-expert draws the same) -----------------------------------------------------
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


# --- one frame ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Look:
    """What a frame shows: one of `MODES`, and for share and gate the expert (its index, smallest first)."""

    mode: str = "colour"
    expert: int = 0

    def check(self, model: LoadedModel) -> "Look":
        """This look, checked against `model`: one line for an unknown mode, a mixture's mode on an expert, or an
        expert index the mixture has not."""
        if self.mode not in MODES:
            raise BoostNerfError(f"unknown view mode {self.mode!r}: use one of {', '.join(MODES)}")
        if self.mode in MIXTURE_MODES and model.kind != "mixture":
            raise BoostNerfError(f"{model.name} is an expert, not a mixture: it has no {self.mode} map (the modes of "
                                 "an expert are colour and depth)")
        if self.mode in ("share", "gate") and not 0 <= self.expert < model.field.m:
            raise BoostNerfError(f"{model.name} has experts 0 to {model.field.m - 1}, not {self.expert}")
        return self


@dataclass
class Frame:
    """One rendered frame: the picture (uint8 (H, W, 3)), the colour render when the look is colour (for a PSNR),
    the seconds it took, and its GFLOPs (None when not counted)."""

    image: np.ndarray
    rgb: np.ndarray | None
    seconds: float
    gflops: float | None = None


def picture(model: LoadedModel, scene: Scene, camera: Camera, look: Look, device: str,
            packers: dict[str, Packer] | None = None, skips: Skips = ALL_SKIPS) -> tuple[np.ndarray, np.ndarray | None]:
    """What `camera` sees of `model` as `look` -> (uint8 (H, W, 3), the colour (H, W, 3) in [0, 1] or None).
    `packers`: one per picture kind, kept from frame to frame (their budgets carry over); `EXACT`: exact lists of the
    kept samples (no budget's pads), for counting."""
    look.check(model)
    packers = {} if packers is None else packers
    settings, skip = model.render_setup(scene, skips)

    def packer(key: str) -> Packer:
        return DYNAMIC if packers is EXACT else packers.setdefault(key, packer_for(device))

    if look.mode in ("colour", "depth"):
        r = render_image(model.field, camera, settings, skip, device, packer("mixture"))
        rgb = r["rgb"].numpy()
        return (to_uint8(rgb), rgb) if look.mode == "colour" else (depth_picture(r, scene), None)
    mix = model.field
    if look.mode == "share":
        return expert_share(mix, look.expert, camera, settings, skip, device, packer(f"expert{look.expert}")), None
    if look.mode == "gate":
        prob = gate_probability(mix, look.expert, camera, settings, skip, device, packer(f"gate{look.expert}"))
        return grey(prob), None
    probs = np.stack([gate_probability(mix, e, camera, settings, skip, device, packer(f"gate{e}"))
                      for e in range(mix.m)], -1)
    return routing_colours(probs), None


EXACT: dict[str, Packer] = {}  # `picture`'s packers that list exactly the kept samples


def frame(model: LoadedModel, scene: Scene, camera: Camera, look: Look, device: str,
          packers: dict[str, Packer] | None = None, count: bool = False) -> Frame:
    """`picture`, timed; with `count` its GFLOPs too (`costs.gflops_of`: counting slows the frame, so the time is
    then that of a second, uncounted render)."""
    t0 = time.perf_counter()
    image, rgb = picture(model, scene, camera, look, device, packers)
    seconds = time.perf_counter() - t0
    gflops = gflops_of(lambda: picture(model, scene, camera, look, device, EXACT))[1] if count else None
    return Frame(image, rgb, seconds, gflops)


def psnr(rgb: np.ndarray, gt: np.ndarray) -> float:
    """PSNR (dB) of a colour render against the ground truth, both in [0, 1]."""
    mse = float(np.mean((rgb.astype(np.float64) - gt.astype(np.float64)) ** 2))
    return -10.0 * math.log10(max(mse, 1e-10))


# --- cameras ----------------------------------------------------------------------------------------------------------
def dataset_camera(split: Split, i: int) -> Camera:
    """View `i` of `split` as a camera."""
    return Camera(split.poses[i], split.intrinsics[i], split.height, split.width)  # the split's row (float32)


def opencv_pose(pose: torch.Tensor) -> np.ndarray:
    """A camera-to-world pose (4, 4), OpenGL (looks down -z) -> OpenCV (looks down +z, y down), float64."""
    return flip_axes(pose.double()).numpy()


def camera_for_view(rotation: np.ndarray, position: np.ndarray, fov: float, aspect: float, height: int) -> Camera:
    """The camera a browser viewer shows: its rotation (3, 3) and position (3,) in the OpenCV convention, its vertical
    field of view (radians) and aspect (width / height), rendered `height` pixels high."""
    height = max(1, int(height))
    width = max(1, int(round(height * aspect)))
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    intrinsics = torch.tensor(Intrinsics.from_fov(fov, height, width).row(), dtype=torch.float32)
    return Camera(flip_axes(torch.from_numpy(pose).float()), intrinsics, height, width)


def fov_of(camera: Camera) -> float:
    """A camera's vertical field of view in radians."""
    return Intrinsics.of(camera.intrinsics).fov_y(camera.height)


def scaled(camera: Camera, height: int) -> Camera:
    """The same camera rendering `height` pixels high (the width and the intrinsics scaled alike; a lens is the same
    at any size)."""
    s = height / camera.height
    width = max(1, int(round(camera.width * s)))
    intrinsics = Intrinsics.of(camera.intrinsics).resized(camera.height, camera.width, height, width)
    return Camera(camera.pose, torch.tensor(intrinsics.row(), dtype=torch.float32), height, width)


# --- saved views ---------------------------------------------------------------------------------------------------
def view_dict(camera: Camera, model: str, look: Look) -> dict:
    """A saved view as JSON: the camera (pose, intrinsics: fx, fy, cx, cy and a lens's numbers,
    `cameras.Intrinsics.row`; size), the model and what it shows."""
    return {"pose": camera.pose.float().tolist(), "intrinsics": camera.intrinsics.float().tolist(),
            "height": camera.height, "width": camera.width, "model": model, "mode": look.mode, "expert": look.expert}


def save_view(folder: Path, image: np.ndarray, camera: Camera, model: str, look: Look) -> Path:
    """Write `image` as folder/view-N.png and its view as view-N.json (N: the next free number) -> the PNG."""
    folder.mkdir(parents=True, exist_ok=True)
    n = 1 + max((int(p.stem[5:]) for p in folder.glob("view-*.json") if p.stem[5:].isdigit()), default=0)
    png = folder / f"view-{n:03d}.png"
    write_png(png, image)
    write_json(png.with_suffix(".json"), view_dict(camera, model, look))
    return png


def read_view(path: Path) -> tuple[Camera, str, Look]:
    """A view `save_view` wrote -> (camera, model name, look); one line when the file is not one."""
    data = read_json(path, "view file")
    try:
        pose = torch.tensor(data["pose"], dtype=torch.float32)
        intrinsics = torch.tensor(data["intrinsics"], dtype=torch.float32)
        height, width = int(data["height"]), int(data["width"])
        look = Look(str(data.get("mode", "colour")), int(data.get("expert", 0)))
        model = str(data["model"])
        ok = pose.shape == (4, 4) and intrinsics.ndim == 1 and len(intrinsics) in ROW_WIDTHS and height > 0
        ok = ok and width > 0 and bool(torch.isfinite(pose).all() and torch.isfinite(intrinsics).all()
                                       and (intrinsics[:2] > 0).all())
    except (*MALFORMED, TypeError) as e:
        raise BoostNerfError(f"{path} is not a saved view ({type(e).__name__}: {e}): save one with `boostnerf view`'s "
                             "save button") from None
    if not ok:
        raise BoostNerfError(f"{path} is not a saved view: it needs a finite 4x4 pose, intrinsics fx, fy, cx, cy "
                             f"(and a lens: {ROW_WIDTHS[1]} numbers) with positive focal lengths, and a positive "
                             "height and width")
    return Camera(pose, intrinsics, height, width), model, look


# --- the scene's geometry ---------------------------------------------------------------------------------------------
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
