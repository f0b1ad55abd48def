"""Loader for nerfstudio's `transforms.json` (one file for all views, as `ns-process-data` writes it).

Layout: `transforms.json` with `frames`, each with a `file_path` (relative to the folder) and a
4x4 camera-to-world `transform_matrix` in the OpenGL convention (as Blender). Intrinsics
`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` are global (top level) or per frame (a frame's value wins);
`fl_y` defaults to `fl_x`, `cx`/`cy` to the image centre, `w`/`h` to the image size. Lens distortion is read as
it is: `camera_model` one of COLMAP's models whose lens nerfstudio's keys hold (`frames.lens_models`: PINHOLE,
SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV with radial `k1 k2 k3 k4` and tangential `p1 p2`, and the fisheyes
OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE with `k1..k4`; cameras.py); rays go through the inverse
distortion.
Frames whose image is missing are left out, with a warning that says how many (a deleted blurry photo).

There are no splits: every `holdout_every`-th view (in file order) is held out as `test`. nerfstudio
records no near / far or scene box; they are derived from the cameras (`camera_near_far`,
`frustum_overlap_bbox`), which assumes an object-centric capture.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import rows
from boostnerf_cli.errors import BoostNerfError, DataWarning
from boostnerf_cli.scenes.bounds import camera_near_far, frustum_overlap_bbox
from boostnerf_cli.scenes.frames import (
    FOCAL_KEYS,
    Frame,
    SceneSpace,
    check_lens,
    find_image,
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


def is_nerfstudio(path: Path) -> str:
    """What was found when `path` holds a nerfstudio `transforms.json`, else ""."""
    return "transforms.json" if (Path(path) / "transforms.json").is_file() else ""


def load_nerfstudio(
    path: Path,
    image_size: int | None = None,
    holdout_every: int = 8,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> Scene:
    """Load a nerfstudio folder into a `Scene` (image_size / holdout_every as in `load_blender`)."""
    folder = Path(path)
    if not folder.is_dir():
        raise BoostNerfError(f"scene folder {folder} does not exist: check the path")
    path = folder / "transforms.json"
    if not path.is_file():
        raise BoostNerfError(f"no transforms.json in {folder}: not a nerfstudio scene")
    meta = read_transforms(path)
    check_lens(meta, str(path))
    frames, missing = [], []
    for i, frame in enumerate(meta["frames"]):
        source = f"{path} frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise BoostNerfError(f"{source}: needs 'file_path' and 'transform_matrix'")
        check_lens(frame, source)
        image = find_image(folder, str(frame["file_path"]))
        if image is None and not (folder / str(frame["file_path"])).is_dir():  # a deleted photo (a blurry one)
            missing.append(str(frame["file_path"]))
            continue
        image = image or resolve_image(folder, str(frame["file_path"]), source)  # a folder: says so
        camera = frame_camera(frame, meta)
        if all(camera[k] is None for keys in FOCAL_KEYS for k in keys):  # before the images are read
            raise BoostNerfError(f"{source}: no fl_x, neither in the frame nor at the top level; add the intrinsics")
        name = str(image.relative_to(folder).with_suffix("")) if image.is_relative_to(folder) else image.stem
        frames.append(Frame(image, name, parse_pose(frame["transform_matrix"], source), camera, source))
    if missing:
        if not frames:  # the reason, as for one frame
            resolve_image(folder, missing[0], f"{path} frame 0")
        warnings.warn(DataWarning(
            f"{len(missing)} of {len(meta['frames'])} frames of {path.name} name images that are not there "
            f"({missing[0]}{', ...' if len(missing) > 1 else ''}): training on the other {len(frames)}"), stacklevel=2)
    bg = torch.tensor(background, dtype=torch.float32)
    images, alpha, native = load_frames(frames, image_size, bg)
    size = tuple(images.shape[1:3])
    k = rows([frame_intrinsics(f.camera, native, size, f.source, f.image) for f in frames])
    poses = torch.tensor(np.stack([f.pose for f in frames]), dtype=torch.float32)
    splits = {"train": Split(images, poses, k, tuple(f.name for f in frames), alpha)}
    holdout = ""
    if holdout_every:
        splits["train"], splits["test"], holdout = hold_out(splits["train"], holdout_every)
    train = splits["train"]
    near, far = camera_near_far(train.poses)
    bbox = frustum_overlap_bbox(train, near, far)
    return scene_from_splits(folder, splits, SceneSpace(near, far, bbox, background), "nerfstudio", holdout, native,
                             extra=lossy_extra(frames))


