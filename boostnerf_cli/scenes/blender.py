"""Loader for Blender / "nerf_synthetic" style datasets (`transforms_{train,val,test}.json`).

Layout: a folder with `transforms_<split>.json` files. Each holds `camera_angle_x` (or `fl_x`,
optionally `fl_y`, `cx`, `cy`, `w`, `h`, also allowed per frame) and `frames`, each with a
`file_path` (relative to the folder, `.png` optional) and a 4x4 camera-to-world
`transform_matrix` in the OpenGL convention. Optional top-level `near` / `far` are honoured;
a bound the files do not record comes from the cameras (`camera_near_far`: 0.1 r and R + r, r the median
and R the largest camera distance to the point they look at), as for nerfstudio and NSVF folders without a box. The
original NeRF loader's fixed 2 / 6 suit only cameras about 4 units from the subject: cameras 16 units
away would see nothing at all through them, and the box and the coarse stage's samples depend on them.

Images: RGB or RGBA, 8 or 16 bit (Pillow reads 16-bit colour at 8-bit precision; grey keeps 16). Downscaling is
area averaging (`frames.area_downscale`) of the premultiplied colour and of alpha; the result is then composited
on the background colour.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import rows
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.scenes.bounds import camera_near_far, frustum_overlap_bbox
from boostnerf_cli.scenes.frames import (
    Frame,
    SceneSpace,
    check_lens,
    frame_camera,
    frame_intrinsics,
    hold_out,
    load_frames,
    lossy_extra,
    parse_pose,
    read_transforms,
    resolve_image,
    scene_from_splits,
)
from boostnerf_cli.scenes.scene import Scene, Split

SPLITS = ("train", "val", "test")


def is_blender(path: Path) -> str:
    """What was found when `path` is a folder holding `transforms_<split>.json` files, else ""."""
    found = [f"transforms_{s}.json" for s in SPLITS if (Path(path) / f"transforms_{s}.json").is_file()]
    return ", ".join(found)


# ----------------------------------------------------------------------------- JSON


def _parse_split(folder: Path, split: str) -> tuple[list[Frame], dict]:
    """Frames of `transforms_<split>.json` and the file's top-level metadata."""
    path = folder / f"transforms_{split}.json"
    meta = read_transforms(path, may_be_empty=split != "train")
    check_lens(meta, str(path))
    frames = []
    for i, frame in enumerate(meta["frames"]):
        source = f"{path.name} frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise BoostNerfError(f"{source} in {folder}: needs 'file_path' and 'transform_matrix'")
        check_lens(frame, f"{source} in {folder}")
        image = resolve_image(folder, str(frame["file_path"]), f"{source} in {folder}")
        camera = frame_camera(frame, meta)
        name = str(image.relative_to(folder).with_suffix("")) if image.is_relative_to(folder) else image.stem
        frames.append(Frame(image, name, parse_pose(frame["transform_matrix"], f"{source} in {folder}"), camera,
                            source))
    return frames, meta


# ----------------------------------------------------------------------------- scene


def _near_far(metas: dict[str, dict], folder: Path, poses) -> tuple[float, float, str]:
    """`near` / `far` from the first transforms file (train, val, test) that has each, else from the train
    cameras (`camera_near_far`); and where they came from ("transforms", "cameras" or both, comma-joined)."""
    derived = camera_near_far(poses)
    values, sources = [], []
    for key, default in zip(("near", "far"), derived):
        value = next((m[key] for m in metas.values() if key in m), None)
        sources.append("cameras" if value is None else "transforms")
        try:
            values.append(default if value is None else float(value))
        except (TypeError, ValueError):
            raise BoostNerfError(f"transforms files in {folder}: {key} must be a number, got {value!r}") from None
    return values[0], values[1], ",".join(dict.fromkeys(sources))


def load_blender(
    path: Path,
    image_size: int | None = None,
    holdout_every: int = 8,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> Scene:
    """Load a Blender-format folder into a `Scene`.

    image_size: the longer image side after area downscaling (None: native size; never upscales).
    holdout_every: when the folder has only a train split, views 0, k, 2k, ... become split "test"
    (0 disables). With its own test (or val) split nothing is held out.
    Splits: images (N, h, w, 3) float32 composited on `background`, poses (N, 4, 4), intrinsics (N, 4).
    bbox: `frustum_overlap_bbox` of the (kept) train cameras. extra: native_size and image_size
    as [height, width], near_far_source ("transforms", "cameras" or "transforms,cameras").
    """
    folder = Path(path)
    if not folder.is_dir():
        raise BoostNerfError(f"scene folder {folder} does not exist: check the path")
    found = [s for s in SPLITS if (folder / f"transforms_{s}.json").is_file()]
    if not found:
        raise BoostNerfError(f"no transforms_{{train,val,test}}.json in {folder}: not a Blender-format scene")
    if "train" not in found:
        raise BoostNerfError(f"{folder} has {', '.join(f'transforms_{s}.json' for s in found)} "
                             "but no transforms_train.json")
    parsed = {s: _parse_split(folder, s) for s in found}
    found = [s for s in found if parsed[s][0]]  # a val / test file with no frames: no such split
    frames = [f for s in found for f in parsed[s][0]]
    bg = torch.tensor(background, dtype=torch.float32)
    images, alpha, native = load_frames(frames, image_size, bg)
    size = tuple(images.shape[1:3])
    splits, start = {}, 0
    for s in found:
        fs = parsed[s][0]
        k = rows([frame_intrinsics(f.camera, native, size, f"{f.source} in {folder}", f.image)
                               for f in fs])
        poses = torch.tensor(np.stack([f.pose for f in fs]), dtype=torch.float32)
        splits[s] = Split(images[start : start + len(fs)], poses, k.float(), tuple(f.name for f in fs),
                          None if alpha is None else alpha[start : start + len(fs)])
        start += len(fs)
    holdout = ""
    if found == ["train"] and holdout_every:
        splits["train"], splits["test"], holdout = hold_out(splits["train"], holdout_every)
    train = splits["train"]
    near, far, source = _near_far({s: parsed[s][1] for s in found}, folder, train.poses)
    bbox = frustum_overlap_bbox(train, near, far)
    return scene_from_splits(folder, splits, SceneSpace(near, far, bbox, background), "blender", holdout, native,
                             extra={"near_far_source": source, **lossy_extra(frames)})
