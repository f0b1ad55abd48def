"""Loader for the NSVF layout: Synthetic-NSVF, and the masked Tanks and Temples scenes NSVF released.

Layout (one folder per scene):
- `rgb/<k>_<name>.png` (or .jpg): the images; the prefix k is the split: 0 train, 1 val, 2 test.
  Synthetic-NSVF images are RGBA (transparent background); masked Tanks and Temples images are
  RGB with the background already painted white;
- `pose/<k>_<name>.txt`: a 4x4 (or 3x4) camera-to-world matrix per image, same stem as the image,
  in the OpenCV convention (camera looks down +z, +y down), converted here to the OpenGL
  convention of `scene.py` (columns y and z negated);
- `intrinsics.txt`: either a 3x3 / 4x4 matrix K (fx, fy, cx, cy from it) or the DeepVoxels
  style whose first line is `f cx cy [0]`; values in pixels of the native images;
- `bbox.txt` (optional): `xmin ymin zmin xmax ymax zmax [voxel_size]`, the scene box in world
  units. Without it the box is derived from the cameras (`frustum_overlap_bbox`).

A split prefix whose poses have no images at all (a pose-only camera path) is ignored; otherwise
every image needs its pose and every pose its image. With no val or test images, every
`holdout_every`-th train view is held out as `test`; with val images and no test images, `test`
falls back to val (`Scene.split`), which is how the Tanks and Temples release is evaluated.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from boostnerf_cli.cameras import Intrinsics, flip_axes
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.scenes.bounds import (
    box_near_far,
    camera_near_far,
    frustum_overlap_bbox,
)
from boostnerf_cli.scenes.frames import (
    IMAGE_SUFFIXES,
    Frame,
    SceneSpace,
    hold_out,
    load_frames,
    lossy_extra,
    one_line,
    scene_from_splits,
)
from boostnerf_cli.scenes.scene import Scene, Split

PREFIXES = {"0": "train", "1": "val", "2": "test"}


def _images(folder: Path) -> list[Path]:
    rgb = folder / "rgb"
    if not rgb.is_dir():
        return []
    return sorted(p for p in rgb.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.name[:2] in ("0_", "1_", "2_"))


def _has_alpha(path: Path) -> bool:
    try:
        with Image.open(path) as im:
            return im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info
    except (OSError, ValueError):  # unreadable: let the loader report it
        return False


def _layout(path: Path) -> list[Path]:
    """The split-prefixed images of an NSVF-layout folder (rgb/ and pose/ present), else []."""
    folder = Path(path)
    return _images(folder) if (folder / "pose").is_dir() else []


def is_nsvf(path: Path) -> str:
    """What was found when `path` is an NSVF-layout folder with RGBA images, else ""."""
    images = _layout(path)
    if images and _has_alpha(images[0]):
        return f"rgb/ ({len(images)} split-prefixed RGBA images) and pose/"
    return ""


def is_tanks(path: Path) -> str:
    """What was found when `path` is an NSVF-layout folder with RGB (masked) images, else ""."""
    images = _layout(path)
    if images and not _has_alpha(images[0]):
        return f"rgb/ ({len(images)} split-prefixed RGB images, masked on white) and pose/"
    return ""


def _numbers(path: Path, what: str) -> list[list[float]]:
    """Rows of numbers of a text file (blank lines skipped)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise BoostNerfError(f"cannot read {what} {path}: {one_line(err)}") from None
    try:
        return [[float(v) for v in line.split()] for line in text.splitlines() if line.strip()]
    except ValueError:
        raise BoostNerfError(f"{what} {path} holds something that is not a number; fix the file") from None


def read_intrinsics(folder: Path) -> list[float]:
    """fx, fy, cx, cy from `intrinsics.txt`: a K matrix (3x3, 3x4 or 4x4, as rows or on one line; its top-left 3x3
    must end in the row 0 0 1), or the DeepVoxels layout whose first line is `f cx cy [0]`."""
    path = folder / "intrinsics.txt"
    if not path.is_file():
        raise BoostNerfError(
            f"{folder} has no intrinsics.txt: NSVF-layout scenes need one (a 3x3/4x4 matrix K or a line 'f cx cy 0')"
        )
    rows = _numbers(path, "intrinsics file")
    flat = [v for r in rows for v in r]
    expected = f"{path}: expected a 3x3, 3x4 or 4x4 matrix K or a first line 'f cx cy 0'"
    shape = {9: (3, 3), 12: (3, 4), 16: (4, 4)}.get(len(flat)) if len(rows) == 1 else None
    if len(rows) in (3, 4) and len({len(r) for r in rows}) == 1 and len(rows[0]) in (3, 4):
        shape = (len(rows), len(rows[0]))
    if shape:
        k = np.array(flat).reshape(shape)[:3, :3]
        tiny = 1e-6 * abs(k[0, 0])  # a K computed numerically (a decomposed projection) carries float noise
        if not np.allclose(k[2], [0, 0, 1]) or abs(k[1, 0]) > tiny:
            raise BoostNerfError(f"{expected}; its matrix {k.tolist()} is not a K (rows fx 0 cx / 0 fy cy / 0 0 1)")
        if abs(k[0, 1]) > tiny:
            raise BoostNerfError(f"{path}: skew s = {k[0, 1]:g} (row 1, column 2 of K) is not zero; boostnerf renders "
                                 "skew-free pinhole cameras: resample the images to a skew-free camera")
        values = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]]
    elif rows and (len(rows[0]) == 3 or (len(rows[0]) == 4 and rows[0][3] == 0)):
        values = [rows[0][0], rows[0][0], rows[0][1], rows[0][2]]
    else:
        raise BoostNerfError(f"{expected}, got {len(flat)} numbers in {len(rows)} lines")
    if not np.isfinite(values).all() or values[0] <= 0 or values[1] <= 0:
        raise BoostNerfError(f"{path}: focal lengths must be positive finite numbers, "
                             f"got fx={values[0]} fy={values[1]}")
    return [float(v) for v in values]


def read_pose(path: Path) -> np.ndarray:
    """A 4x4 (or 3x4) OpenCV camera-to-world matrix -> (4, 4) OpenGL camera-to-world."""
    flat = [v for r in _numbers(path, "pose file") for v in r]
    if len(flat) not in (12, 16):
        raise BoostNerfError(f"pose file {path} holds {len(flat)} numbers: expected a 4x4 or 3x4 matrix")
    pose = np.eye(4)
    pose[: len(flat) // 4] = np.array(flat).reshape(-1, 4)
    if not np.isfinite(pose).all():
        raise BoostNerfError(f"pose file {path} contains NaN or infinite values; fix the pose")
    return flip_axes(pose)


def read_bbox(folder: Path) -> torch.Tensor | None:
    path = folder / "bbox.txt"
    if not path.is_file():
        return None
    flat = [v for r in _numbers(path, "box file") for v in r]
    if len(flat) < 6 or not np.isfinite(flat[:6]).all() or not all(flat[i + 3] > flat[i] for i in range(3)):
        raise BoostNerfError(f"{path}: expected 'xmin ymin zmin xmax ymax zmax [voxel_size]' with max > min")
    return torch.tensor([flat[:3], flat[3:6]], dtype=torch.float32)


def _frames(folder: Path) -> dict[str, list[Frame]]:
    """Frames per split, images matched to poses by file stem."""
    images = _images(folder)
    if not images:
        raise BoostNerfError(f"{folder}/rgb has no images named 0_*.png / 1_*.png / 2_*.png: not an NSVF-layout scene")
    poses = {p.stem: p for p in (folder / "pose").glob("*.txt") if p.name[:2] in ("0_", "1_", "2_")}
    splits: dict[str, list[Frame]] = {}
    for prefix, split in PREFIXES.items():
        imgs = [p for p in images if p.name.startswith(prefix + "_")]
        if not imgs:
            continue  # a pose-only prefix (a camera path to render) is not a split
        stems = {p.stem for p in imgs}
        missing = [p.name for p in imgs if p.stem not in poses]
        extra = sorted(s for s in poses if s.startswith(prefix + "_") and s not in stems)
        if missing or extra:
            n_poses = sum(s.startswith(prefix + "_") for s in poses)
            detail = (f"rgb/{missing[0]} has no pose/{Path(missing[0]).stem}.txt" if missing
                      else f"pose/{extra[0]}.txt has no image in rgb/")
            raise BoostNerfError(
                f"{folder}: split {split} ({prefix}_*) has {len(imgs)} images but {n_poses} poses ({detail}): "
                f"every image needs exactly one pose"
            )
        splits[split] = [Frame(p, p.stem, read_pose(poses[p.stem]), {}, f"rgb/{p.name}") for p in imgs]
    if "train" not in splits:
        raise BoostNerfError(f"{folder}/rgb has no training images (0_*.png)")
    return splits


def load_nsvf(
    path: Path,
    image_size: int | None = None,
    holdout_every: int = 8,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    format: str = "nsvf",
) -> Scene:
    """Load an NSVF-layout folder (Synthetic-NSVF, or masked Tanks and Temples with `format="tanks"`).

    image_size: the longer image side after area downscaling (None: native). Intrinsics are scaled
    per axis by stored / native size. bbox: bbox.txt when present, else the frustum overlap of the
    train cameras; near / far: from the cameras and that box.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise BoostNerfError(f"scene folder {folder} does not exist: check the path")
    if not (folder / "rgb").is_dir() or not (folder / "pose").is_dir():
        raise BoostNerfError(f"{folder} has no rgb/ and pose/ folders: not an NSVF-layout scene")
    frames = _frames(folder)
    fx, fy, cx, cy = read_intrinsics(folder)
    order = list(frames)
    bg = torch.tensor(background, dtype=torch.float32)
    ordered = [f for s in order for f in frames[s]]
    images, alpha, native = load_frames(ordered, image_size, bg)
    size = tuple(images.shape[1:3])
    sx, sy = size[1] / native[1], size[0] / native[0]
    k = torch.tensor(Intrinsics(fx, fy, cx, cy).scaled(sx, sy).row(), dtype=torch.float32)
    splits, start = {}, 0
    for s in order:
        fs = frames[s]
        poses = torch.tensor(np.stack([f.pose for f in fs]), dtype=torch.float32)
        splits[s] = Split(images[start : start + len(fs)], poses, k.expand(len(fs), 4).clone(),
                          tuple(f.name for f in fs), None if alpha is None else alpha[start : start + len(fs)])
        start += len(fs)
    holdout = ""
    if order == ["train"] and holdout_every:
        splits["train"], splits["test"], holdout = hold_out(splits["train"], holdout_every)
    train = splits["train"]
    bbox = read_bbox(folder)
    if bbox is not None:
        near, far = box_near_far(train.poses, bbox)
    else:
        near, far = camera_near_far(train.poses)
        bbox = frustum_overlap_bbox(train, near, far)
    return scene_from_splits(folder, splits, SceneSpace(near, far, bbox, background), format, holdout, native,
                             extra={"bbox_source": "bbox.txt" if (folder / "bbox.txt").is_file() else "cameras",
                                    **lossy_extra(ordered)})


def load_tanks(path: Path, image_size: int | None = None, holdout_every: int = 8) -> Scene:
    """Masked Tanks and Temples in the NSVF layout (RGB images on white): `load_nsvf` with its label."""
    return load_nsvf(path, image_size=image_size, holdout_every=holdout_every, format="tanks")
