"""`boostnerf render`: every view of a split as PNG colour and 16-bit depth, camera-path videos, side-by-side
comparisons with error heat maps, and each expert's share of a mixture with the gate's probability maps.

Files (all under WS/renders/, see docs/stages.md):
- `render`: `<model>/<split>/<view>.png` and `<view>_depth.png`;
- `render --path orbit|spiral`: `<model>/<path>.mp4` (or `--video FILE`, .mp4 or .gif) and
  `<...>_depth.mp4`; an MP4 without the ffmpeg backend is refused before anything is rendered;
- `render --compare`: `compare/<split>/<view>.png`;
- `render --per-expert` (mixtures): `<model>/<split>/<view>_expert<i>-<name>.png`,
  `<view>_gate<i>-<name>.png` and the montage `<view>_experts.png` (the maps: `viewpoint/maps.py`, which the viewer
  shares);
- `render --camera VIEW.json`: `<model>/views/VIEW.png`, a view `boostnerf view` saved, rendered again;
- `render --camera-path FILE.json` (nerfstudio's camera-path layout: `viewpoint/camera_path.py`): `<model>/FILE.mp4`
  (or `--video`), `FILE_depth.mp4` and for a mixture `FILE_routing.mp4`, one frame per entry of the file.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import DataFrame
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.images import (
    colorbar,
    colorize_depth,
    depth_to_uint16,
    heat,
    panel_grid,
    to_uint8,
    video_target,
    write_png,
    write_videos,
)
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import LoadedModel, Skips, Viewing, load_model, n_views, render_split
from boostnerf_cli.render.packing import Packer, packer_for
from boostnerf_cli.render.paths import camera_path
from boostnerf_cli.render.renderer import Camera, render_image
from boostnerf_cli.scenes import Scene, Split
from boostnerf_cli.viewpoint.camera import dataset_camera
from boostnerf_cli.viewpoint.camera_path import path_cameras, read_camera_path, through_views, write_camera_path
from boostnerf_cli.viewpoint.frame import Look, picture
from boostnerf_cli.viewpoint.maps import expert_share, gate_probability, grey, routing_colours
from boostnerf_cli.viewpoint.saved import read_view
from boostnerf_cli.workspace import check_writable, remove

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)

COMPARED = ("baseline", "top1", "top2", "ens")  # the paper's comparison models, in its order


def run(survey: Survey, names: list[str] | None, viewing: Viewing, device: str,
        per_expert: bool = False) -> list[Path]:
    """Render `viewing`'s views with every model of `names` (default: all): PNG colour and 16-bit depth; with
    `per_expert` a mixture's expert shares and gate maps too. -> the files written."""
    split_name, views, skips, exact_gate = viewing.split, viewing.views, viewing.skips, viewing.exact_gate
    ws, scene = survey.ws, survey.scene()
    split = scene.split(split_name)
    names = survey.current(names)
    radius = scene.contraction.radius if scene.contraction is not None else None  # depth PNGs: contracted (unbounded)
    written = []
    for name in names:
        model = load_model(ws, name, device, exact_gate)
        folder = ws.renders_dir(name, split_name)
        mine = []
        for i, r in enumerate(render_split(model, scene, split, device, skips, views)):
            stem = split.stems[i]
            write_png(folder / f"{stem}.png", to_uint8(r["rgb"]))
            write_png(folder / f"{stem}_depth.png", depth_to_uint16(r["depth"], scene.far, radius))
            mine.append(folder / f"{stem}.png")
        n_drawn = len(mine)
        extra = []
        if per_expert and model.kind == "mixture":
            extra = render_experts_and_gate(model, scene, split, folder, device, skips, views)
        elif per_expert:
            log(f"note: {name} is not a mixture, so --per-expert draws nothing more for it (it has no gate or shares)")
        log(f"{name}: wrote {n_drawn} view{'s' if n_drawn != 1 else ''} (a colour and a 16-bit depth PNG each"
            + (f"; and {len(extra)} per-expert and gate images" if extra else "") + f") to {folder}")
        mine += extra
        written += mine
    return written


# --- a saved view ----------------------------------------------------------------------------------------------------
def run_camera(survey: Survey, names: list[str] | None, file: Path, device: str, skips: Skips) -> list[Path]:
    """Render a view `boostnerf view` saved (its camera, at its full size, and what it shows) with the model it names,
    or the one `--model` names -> WS/renders/MODEL/views/<file's stem>.png."""
    camera, saved_model, look = read_view(file)
    if names and len(names) != 1:
        raise BoostNerfError(f"--camera renders one model: keep one of {', '.join(names)}")
    ws, scene = survey.ws, survey.scene()
    name = survey.current(names or [saved_model])[0]
    model = load_model(ws, name, device)
    image, _ = picture(model, scene, camera, look.check(model), device, skips=skips)
    target = ws.renders_dir(model.name) / "views" / f"{file.stem}.png"
    write_png(target, image)
    log(f"{model.name}: wrote the {look.mode} view of {file} ({camera.width}x{camera.height} px) to {target}")
    return [target]


# --- videos ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VideoPath:
    """A video along a camera path from the training cameras: `kind` (orbit, spiral), its frames and frames per
    second, and the file to write (None: WS/renders/MODEL/KIND.mp4)."""

    kind: str
    frames: int = 60
    fps: int = 24
    file: Path | None = None


def one_model(survey: Survey, names: list[str] | None, option: str) -> str:
    """The one model a video renders; one line when `names` holds none or several."""
    if not names or len(names) != 1:
        fix = f"keep one of {', '.join(names)}" if names else "add --model NAME"
        raise BoostNerfError(f"{option} renders one model: {fix} (models: {', '.join(survey.usable()) or 'none yet'})")
    return survey.current(names)[0]


FORWARD = 0.9  # `facing` above it: the cameras all look one way, a forward-facing capture (a spiral suits it)


def facing(poses: torch.Tensor) -> float:
    """How much cameras (N, 4, 4) look one way: the length of their mean viewing axis (1: all the same way)."""
    return float(torch.linalg.norm(poses[:, :3, 2].mean(0)))


def run_video(survey: Survey, names: list[str] | None, path: VideoPath, device: str, skips: Skips) -> list[Path]:
    """Render one model along a camera path derived from the training cameras -> colour and depth videos."""
    kind, n_frames, video, fps = path.kind, path.frames, path.file, path.fps
    name = one_model(survey, names, "--path")
    ws, scene = survey.ws, survey.scene()
    model = load_model(ws, name, device)
    target, fmt = video_target(video or ws.renders_dir(model.name) / f"{kind}.mp4")  # refused before rendering
    train = scene.split("train")
    look = facing(train.poses)
    if kind == "spiral" and look < 0.5:
        log("note: the training cameras look in many directions (a 360-degree capture?): --path orbit suits it better")
    if kind == "orbit" and look > FORWARD:
        log("note: the training cameras all look one way (a forward-facing capture?): --path spiral suits it better")
    poses = camera_path(kind, train.poses, model.bbox.cpu(), scene.near, scene.far, n_frames, scene.ndc)
    cameras = [Camera(pose, train.intrinsics[0], train.height, train.width) for pose in poses]
    check_writable(film_files(target, routing=False))
    return write_film(film(model, scene, cameras, device, skips, kind), target, fmt, fps, f"{kind} path")


def run_camera_path(survey: Survey, names: list[str] | None, file: Path, video: Path | None, device: str,
                    skips: Skips) -> list[Path]:
    """Render one model along a camera-path file (nerfstudio's layout: `viewpoint.camera_path`), each frame at the
    file's size and field of view -> colour and depth videos, and for a mixture its routing colours (the map of
    `render --per-expert` and the viewer) as a third."""
    name = one_model(survey, names, "--camera-path")
    ws, scene = survey.ws, survey.scene()
    read = read_camera_path(file, DataFrame.of(scene.extra))  # refused before anything is loaded or rendered
    model = load_model(ws, name, device)
    target, fmt = video_target(video or ws.renders_dir(model.name) / f"{Path(file).stem}.mp4")
    cameras = path_cameras(read.frames, read.path.height, read.path.width)
    check_writable(film_files(target, routing=model.kind == "mixture"))  # before a frame is rendered
    shots = film(model, scene, cameras, device, skips, "camera path", routing=model.kind == "mixture")
    return write_film(shots, target, fmt, read.path.fps, f"camera path {file}")


def run_path_through_views(survey: Survey, split: str, views: list[int], seconds: float, fps: float,
                           smoothness: float, cycle: bool, out: Path | None) -> Path:
    """Write a camera path with a keyframe at each of `views` of `split` (the dataset's own viewpoints, in that
    order), sampled as `view`'s panel samples it, to `out` (default WS/camera_paths/views.json) -> the file."""
    scene = survey.scene()
    data = scene.split(split)
    path = through_views(data.poses, data.intrinsics, data.height, data.width, views)
    path.configure(seconds, fps, smoothness, cycle, data.width, data.height)
    file = Path(out) if out is not None else survey.ws.camera_paths_dir / "views.json"
    if file.suffix != ".json":
        raise BoostNerfError(f"--out {file}: a camera path is a .json file")
    own = survey.ws.own_file(file)
    if own is not None:
        raise BoostNerfError(f"--out {file} is the workspace's own ({own}), which only its stages write: give another "
                             f"file, e.g. {survey.ws.camera_paths_dir / file.name}")
    write_camera_path(file, path, DataFrame.of(scene.extra))
    log(f"camera path: {path.summary()}")
    return file


@dataclass
class Film:
    """A video's frames: colour (uint8), each frame's expected depth and where it is opaque (opacity >= 0.5, what the
    depth video draws), and with a mixture the routing colours (uint8; empty otherwise)."""

    model: LoadedModel
    scene: Scene
    rgb: list[np.ndarray]
    depth: list[np.ndarray]
    opaque: list[np.ndarray]
    routing: list[np.ndarray]


def film(model: LoadedModel, scene: Scene, cameras: list[Camera], device: str, skips: Skips, what: str,
         routing: bool = False) -> Film:
    """Render `cameras` with `model` -> a `Film` (with `routing`, each frame's routing colours too)."""
    settings, skip = model.render_setup(scene, skips)
    packer = packer_for(device)  # one for the path: each frame reuses the budgets the ones before it sized
    packers: dict[str, Packer] = {}  # the routing map's, one per gate
    shots = Film(model, scene, [], [], [], [])
    for i, camera in enumerate(cameras):
        r = render_image(model.field, camera, settings, skip, device=device, packer=packer)
        shots.rgb.append(to_uint8(r["rgb"]))
        shots.depth.append((r["depth"] / r["acc"].clamp_min(1e-6)).numpy())  # expected depth of the surface hit
        shots.opaque.append(r["acc"].numpy() >= 0.5)
        if routing:
            shots.routing.append(picture(model, scene, camera, Look("routing"), device, packers, skips)[0])
        if (i + 1) % 10 == 0 or i + 1 == len(cameras):
            log(f"{model.name}: {what} frame {i + 1}/{len(cameras)}")
    return shots


def film_files(target: Path, routing: bool) -> list[Path]:
    """The videos of a film at `target`: colour, depth and, with `routing`, the routing colours."""
    kinds = ("", "_depth", "_routing") if routing else ("", "_depth")
    return [target.with_name(f"{target.stem}{kind}{target.suffix}") for kind in kinds]


def write_film(shots: Film, target: Path, fmt: str, fps: float, what: str) -> list[Path]:
    """Write `shots` as `target` (colour), `<target>_depth` (near bright, far dark, between the 1st and 99th
    percentile of every frame's opaque pixels) and, with routing colours, `<target>_routing` (`film_files`), as one
    set: all of them or none -> the files."""
    scene, model = shots.scene, shots.model
    seen = np.concatenate([d[o] for d, o in zip(shots.depth, shots.opaque)])
    lo, hi = (np.percentile(seen, [1, 99]) if seen.size else (scene.near, scene.far))
    depth_frames = [colorize_depth(d, o.astype(np.float32), float(lo), float(max(hi, lo + 1e-6)))
                    for d, o in zip(shots.depth, shots.opaque)]
    written = list(zip(film_files(target, bool(shots.routing)), (shots.rgb, depth_frames, shots.routing)))
    write_videos(written, fps, fmt)
    log(f"{model.name}: wrote {fmt.upper()} {', '.join(str(f) for f, _ in written)} ({len(shots.rgb)} frames, "
        f"{fps:g} fps, {what}; depth: near bright, far dark, {lo:.3g} .. {hi:.3g} "
        f"{'NDC' if scene.ndc is not None else 'world'} units" + ("; routing: blue = smallest expert, then cyan, "
                                                                  "green, orange, red" if shots.routing else "") + ")")
    return [f for f, _ in written]


# --- side-by-side comparison ------------------------------------------------------------------------
def compared_models(survey: Survey, names: list[str] | None) -> list[str]:
    """`names`, else the paper's comparison models the workspace has, else every model it has."""
    if names:
        return survey.current(names)
    have = survey.models
    chosen = [n for n in COMPARED if n in have] or have
    if not chosen:
        raise BoostNerfError(f"{survey.ws.root} has no trained models yet: "
                             f"run `boostnerf pretrain --workspace {survey.ws.root}` first")
    return survey.current(chosen)


def pixel_error(rgb: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Root-mean-square error over the colour channels per pixel, (H, W), in [0, 1]."""
    return np.sqrt(np.mean((rgb.astype(np.float64) - gt.astype(np.float64)) ** 2, axis=-1))


def run_compare(survey: Survey, names: list[str] | None, viewing: Viewing, device: str) -> list[Path]:
    """One image per view: ground truth and each model side by side, each model's error heat map below it."""
    split_name, views, skips = viewing.split, viewing.views, viewing.skips
    ws, scene = survey.ws, survey.scene()
    split = scene.split(split_name)
    names = compared_models(survey, names)
    n = n_views(split, views)
    renders = {}
    for name in names:
        renders[name] = [r["rgb"].numpy()
                         for r in render_split(load_model(ws, name, device), scene, split, device, skips, n)]
    folder = ws.renders_dir("compare", split_name)
    written = []
    for i in range(n):
        gt = split.images[i].numpy()
        errors = {name: pixel_error(renders[name][i], gt) for name in names}
        hi = max(max(float(np.percentile(e, 99.5)) for e in errors.values()), 1e-3)
        top = [("ground truth", to_uint8(gt))]
        bottom = [(f"RMS error: black 0, white {hi:.2f}", colorbar(gt.shape[0], gt.shape[1], 0.0, hi))]
        for name in names:
            mse = float(np.mean((renders[name][i].astype(np.float64) - gt) ** 2))
            psnr = -10.0 * np.log10(max(mse, 1e-10))
            top.append((f"{name}  {psnr:.2f} dB", to_uint8(renders[name][i])))
            bottom.append((f"{name} error", heat(errors[name], 0.0, hi)))
        path = folder / f"{split.stems[i]}.png"
        write_png(path, panel_grid([top, bottom], caption=f"{scene.name}, {split_name} view {split.names[i]}"))
        written.append(path)
    log(f"compared {', '.join(names)}: wrote {len(written)} image{'s' if len(written) != 1 else ''} to {folder}")
    return written


# --- per-expert pictures of a mixture -----------------------------------------------------------------
# the routing map's label in the montage, wider than its panel (images.panel_grid wraps it)
ROUTING_LEGEND = "routing (smallest first: blue, cyan, green, orange, red)"


def gate_by_detail(probs: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean gate probability per expert over the more detailed and the smoother half of the pixels.

    probs (H, W, M) per-pixel gate maps, gt (H, W, 3) ground truth, mask (H, W) pixels to use (the
    object). Detail = the ground truth's gradient magnitude (luminance, central differences); the
    halves split at its median over the mask -> (detailed (M,), smooth (M,)).
    """
    lum = gt.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    gy, gx = np.gradient(lum)
    detail = np.hypot(gx, gy)[mask]
    p = probs[mask]
    if detail.size < 2:
        return np.full(probs.shape[-1], np.nan), np.full(probs.shape[-1], np.nan)
    high = detail > np.median(detail)
    if not high.any():  # every pixel as detailed as the median (a flat colour): no halves, both the mean
        return p.mean(0), p.mean(0)
    return p[high].mean(0), p[~high].mean(0)


def render_experts_and_gate(model: LoadedModel, scene: Scene, split: Split, folder: Path, device: str, skips: Skips,
                            views: int | None) -> list[Path]:
    """Per expert (ordered by size): its contribution to the mixture, and the gate's probability map; plus a montage.

    - `<view>_expert<i>-<name>.png`: expert i's share of the mixture: its density times its routed weight,
      its own colour, composited on the scene's background;
    - `<view>_gate<i>-<name>.png`: greyscale probability G(x)_i averaged along each ray with the rendering
      weights (white = every visible sample prefers expert i); black where the ray hits nothing (opacity < 0.1);
    - `<view>_experts.png`: the mixture's render, the expert shares and the gate maps side by side, and a
      routing map (each pixel coloured by the gate's probabilities: blue = smallest expert, then cyan, green,
      orange, red = the fifth).
    The log says, per view, the mean gate probability of each expert over the more detailed and the smoother half
    of the object's pixels (`gate_by_detail`).
    """
    mix = model.field
    names = list(mix.cfg.expert_names)
    m = len(names)
    settings, skip = model.render_setup(scene, skips)
    packers: dict[str, Packer] = {}
    written = []
    for i in range(n_views(split, views)):
        stem = split.stems[i]
        for old in (*folder.glob(f"{stem}_expert[0-9]*-*.png"), *folder.glob(f"{stem}_gate[0-9]*-*.png")):
            remove(old)  # an earlier mixture's experts (build-moe --experts changed them): not beside this one's

        def packer(key):
            return packers.setdefault(key, packer_for(device))  # one per picture kind, reused from view to view

        camera = dataset_camera(split, i)
        full = render_image(mix, camera, settings, skip, device, packer("mixture"))
        shares, gates = [], []
        for e, ename in enumerate(names):
            share = expert_share(mix, e, camera, settings, skip, device, packer(f"expert{e}"))
            prob = gate_probability(mix, e, camera, settings, skip, device, packer(f"gate{e}"))
            gates.append(prob)
            shares.append(share)
            for kind, img in (("expert", share), ("gate", grey(prob))):
                path = folder / f"{stem}_{kind}{e}-{ename}.png"
                write_png(path, img)
                written.append(path)
        probs = np.stack(gates, -1)  # (H, W, M)
        hi, lo = gate_by_detail(probs, split.images[i].numpy(), full["acc"].numpy() > 0.5)
        if np.isnan(hi).any():
            log(f"{model.name} {stem}: no mean gate probability per expert: fewer than 2 pixels of the render "
                "are opaque (opacity > 0.5)")
        else:
            log(f"{model.name} {stem}: mean gate probability per expert ({', '.join(names)}) on detailed pixels "
                f"{[round(float(v), 2) for v in hi]}, on smooth pixels {[round(float(v), 2) for v in lo]}")
        routing = routing_colours(probs)
        top = [("mixture", to_uint8(full["rgb"]))] + [(f"{names[e]} share", shares[e]) for e in range(m)]
        bottom = [(ROUTING_LEGEND, routing)] + [
            (f"gate p({names[e]})", grey(gates[e])) for e in range(m)]
        path = folder / f"{stem}_experts.png"
        write_png(path, panel_grid([top, bottom], caption=f"{model.name}, {split.names[i]}: experts smallest first; "
                                    "gate: white = probability 1, black = 0 or empty"))
        written.append(path)
    return written
