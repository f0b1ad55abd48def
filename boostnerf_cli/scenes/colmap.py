"""Loader for COLMAP models: `sparse/0/{cameras,images,points3D}.{bin,txt}` beside `images/` (and `images_2/`,
`images_4/`, `images_8/`, downscaled copies), as COLMAP, `boostnerf capture` and the mip-NeRF 360 release lay them out.

The model is read by `colmap_model.py` (no COLMAP or pycolmap needed). Images are taken in file-name order; the image
folder is chosen as for LLFF (`llff.choose_folder`) and the intrinsics are scaled from the camera's size to the images
read. Camera models: those of `cameras.MODELS` that boostnerf renders (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL,
OPENCV, OPENCV_FISHEYE, FULL_OPENCV, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE) are rendered as they are (rays through the
inverse distortion, cameras.py); any other (FOV, the thin-prism fisheyes) is refused in one line. Images the model
names that are not in the folder are left out, with a warning saying how many.

Two kinds of capture, told apart by the cameras' viewing directions:
- **forward-facing** (every camera within `FORWARD_DEGREES` of the mean viewing direction, as LLFF's fern): each view's
  depth bounds are the 0.1th and 99.9th percentiles of the depths of the points it sees (what LLFF's imgs2poses wrote
  into poses_bounds.npy), of those `BOUND_TRACK` or more images see where it sees any, and the scene is then made
  exactly as the LLFF loader makes it (bounds rescaling, recentring, NDC of the average camera: llff.py);
- otherwise (around an object): near / far and the box come from the sparse points (`bounds.point_bounds`), or, with
  too few points, from the cameras as for nerfstudio.
Every 8th view (in name order) is held out as test (`holdout_every`). The points stay on the scene (`Scene.points`),
in the scene's world, with the views of each split that see them.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import Intrinsics, flip_axes, rows
from boostnerf_cli.errors import BoostNerfError, DataWarning
from boostnerf_cli.scenes.bounds import camera_near_far, frustum_overlap_bbox, point_bounds, point_near_far
from boostnerf_cli.scenes.colmap_model import Model, ModelImage, model_files, read_model
from boostnerf_cli.scenes.frames import (
    Frame,
    SceneSpace,
    hold_out,
    load_frames,
    lossy_extra,
    orientation_note,
    scene_from_splits,
)
from boostnerf_cli.scenes.llff import choose_folder, forward_facing_world, ndc_space
from boostnerf_cli.scenes.scene import Scene, SparsePoints, Split

FORWARD_DEGREES = 30.0  # every camera's axis within this of the mean axis: a forward-facing capture (NDC)
# a forward-facing view's depth bounds come from the points this many images or more see: the few points two images
# triangulate hold its outliers, and with a thousand points the 0.1th percentile is the nearest one. Too near a bound
# scales the world up: the cameras spread wider in the NDC, and its box too (docs/datasets.md, "Forward-facing
# captures")
BOUND_TRACK = 3
def model_folder(folder: Path) -> Path | None:
    """The COLMAP model of a scene folder: `sparse/0`, else the first other `sparse/<n>`, else `sparse` itself."""
    sparse = Path(folder) / "sparse"
    if not sparse.is_dir():
        return None
    numbered = sorted((p for p in sparse.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))
    return next((p for p in (*numbered, sparse) if model_files(p)), None)


def is_colmap(path: Path) -> str:
    """What was found when `path` holds a COLMAP model (and image folders), else ""."""
    sub = model_folder(Path(path))
    if sub is None:
        return ""
    ext = model_files(sub)
    found = sorted(p.name + "/" for p in Path(path).iterdir() if p.is_dir() and p.name.startswith("images"))
    return (f"{sub.relative_to(path).as_posix()}/{{cameras,images,points3D}}.{ext}"
            + (f" and {', '.join(found)}" if found else ""))


def _frames(folder: Path, model: Model, image_size: int | None) -> tuple[list[Frame], list[int], Path]:
    """The frames of the model's images found in the chosen image folder (in name order), their image ids, the
    folder; a warning for those not found."""
    sub, files = choose_folder(folder, image_size)
    by_name = {f.relative_to(sub).as_posix(): f for f in files}
    by_name.update({f.name: f for f in files if f.name not in by_name})
    frames, ids, missing = [], [], []
    for iid, image in sorted(model.images.items(), key=lambda kv: kv[1].name):
        path = by_name.get(image.name) or (sub / image.name if (sub / image.name).is_file() else None)
        if path is None:
            missing.append(image.name)
            continue
        pose = flip_axes(image.world_from_camera())
        frames.append(Frame(path, Path(image.name).with_suffix("").as_posix(), pose, {}, f"{sub.name}/{image.name}"))
        ids.append(iid)
    if not frames:
        raise BoostNerfError(f"none of the {len(model.images)} images of the COLMAP model in {folder} is in "
                             f"{sub.name}/ (e.g. {sorted(i.name for i in model.images.values())[0]}): put the photos "
                             "the model was made from there")
    if missing:
        warnings.warn(DataWarning(
            f"{len(missing)} of {len(model.images)} images of the COLMAP model are not in {sub.name}/ ({missing[0]}"
            f"{', ...' if len(missing) > 1 else ''}): training on the other {len(frames)}"), stacklevel=3)
    return frames, ids, sub


def _intrinsics(model: Model, images: list[ModelImage], size: tuple[int, int], native: tuple[int, int],
                files: list[Path], folder: Path) -> torch.Tensor:
    """Each view's intrinsics scaled from its camera's size to the images read (`size`, h w); the aspect checked."""
    cameras = []
    for image, file in zip(images, files):
        cam = model.cameras[image.camera_id]
        source = f"{folder}: camera {image.camera_id} of image {image.name}"
        if not math.isclose(cam.width / cam.height, native[1] / native[0],
                            rel_tol=max(0.005, 1 / native[0] + 1 / native[1])):
            raise BoostNerfError(f"{source} is {cam.width} x {cam.height} but the image is {native[1]} x {native[0]}: "
                                 f"not the images the model was made from?{orientation_note(file)}")
        cameras.append(Intrinsics.from_colmap(cam.model, cam.params, source).scaled(size[1] / cam.width,
                                                                                   size[0] / cam.height))
    return rows(cameras)


def forward_facing(poses: np.ndarray) -> bool:
    """Whether every camera (OpenGL camera-to-world, N) looks within `FORWARD_DEGREES` of their mean direction."""
    axes = -poses[:, :3, 2]
    mean = axes.sum(0)
    if np.linalg.norm(mean) < 1e-9:
        return False
    cos = axes @ (mean / np.linalg.norm(mean))
    return bool(np.degrees(np.arccos(np.clip(cos, -1, 1))).max() <= FORWARD_DEGREES)


def _seen(model: Model, ids: list[int]) -> list[torch.Tensor]:
    """For each image id of `ids`, the indices (into the model's point arrays) of the points it sees."""
    index = {int(pid): i for i, pid in enumerate(model.point_ids)}
    out = []
    for iid in ids:
        pids = model.images[iid].point_ids
        out.append(torch.tensor(sorted({index[int(p)] for p in pids[pids >= 0] if int(p) in index}), dtype=torch.long))
    return out


def _visibility(seen: list[torch.Tensor], names: list[str], splits: dict[str, Split]) -> dict[str, torch.Tensor]:
    by_name = dict(zip(names, seen))
    out = {}
    for split_name, split in splits.items():
        rows = [torch.stack([torch.full_like(by_name[n], i), by_name[n]], -1) for i, n in enumerate(split.names)]
        out[split_name] = torch.cat(rows) if rows else torch.zeros(0, 2, dtype=torch.long)
    return out


def load_colmap(
    path: Path,
    image_size: int | None = None,
    holdout_every: int = 8,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> Scene:
    """Load a COLMAP scene folder into a `Scene` (see the module docstring)."""
    folder = Path(path)
    sub_model = model_folder(folder)
    if sub_model is None:
        raise BoostNerfError(f"no COLMAP model in {folder}: expected sparse/0/{{cameras,images,points3D}}.bin or .txt")
    model = read_model(sub_model)
    if not model.images:
        raise BoostNerfError(f"the COLMAP model in {sub_model} has no registered images: run the reconstruction "
                             "again (boostnerf capture)")
    for cid, cam in model.cameras.items():  # before any image is read
        Intrinsics.from_colmap(cam.model, cam.params, f"{sub_model}: camera {cid}")
    frames, ids, sub = _frames(folder, model, image_size)
    poses = np.stack([f.pose for f in frames])
    seen = _seen(model, ids)
    xyz = torch.tensor(model.xyz, dtype=torch.float64)
    forward = forward_facing(poses) and len(model.xyz) > 0
    extra: dict = {"images_folder": sub.name, "model": sub_model.relative_to(folder).as_posix()}
    if forward:
        tracked = torch.tensor([len(t) for t in model.tracks], dtype=torch.long) >= BOUND_TRACK
        sure = [s[tracked[s]] if bool(tracked[s].any()) else s for s in seen]
        bounds = point_near_far(xyz, torch.tensor(poses), sure, (0.1, 99.9)).numpy()
        if np.isnan(bounds).any():
            i = int(np.flatnonzero(np.isnan(bounds).any(1))[0])
            raise BoostNerfError(f"{frames[i].source} sees too few of the model's points to bound its depth: a "
                                 "forward-facing capture needs points in every view; run the capture again")
        poses, world_from_data, scale = forward_facing_world(poses, bounds)
        xyz = xyz @ torch.tensor(world_from_data[:3, :3]).T + torch.tensor(world_from_data[:3, 3])
        extra.update(world_from_data=world_from_data.tolist(), bounds=(bounds * scale).tolist(), forward_facing=True)
    bg = torch.tensor(background, dtype=torch.float32)
    images, alpha, native = load_frames(frames, image_size, bg)
    k = _intrinsics(model, [model.images[i] for i in ids], tuple(images.shape[1:3]), native,
                    [f.image for f in frames], folder)
    names = [f.name for f in frames]
    splits = {"train": Split(images, torch.tensor(poses, dtype=torch.float32), k, tuple(names), alpha)}
    holdout = ""
    if holdout_every:
        splits["train"], splits["test"], holdout = hold_out(splits["train"], holdout_every)
    train = splits["train"]
    if forward:
        space = ndc_space(train, background)
        extra["box_from"] = "the NDC of the average camera (a forward-facing capture), depths from the sparse points"
    else:
        train_seen = [seen[names.index(n)] for n in train.names]
        found = point_bounds(xyz.float(), train.poses, train_seen)
        if found is None:
            near, far = camera_near_far(train.poses)
            bbox, box_from = frustum_overlap_bbox(train, near, far), "the cameras (too few sparse points)"
        else:
            near, far, bbox, box_from = found
        space = SceneSpace(near, far, bbox, background)
        extra["box_from"] = box_from
    points = SparsePoints(xyz.float(), torch.tensor(model.rgb), torch.tensor(model.error, dtype=torch.float32),
                          _visibility(seen, names, splits))
    scene = scene_from_splits(folder, splits, space, "colmap", holdout, native, extra={**extra, **lossy_extra(frames)})
    return dataclasses.replace(scene, points=points)
