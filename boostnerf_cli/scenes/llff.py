"""Loader for LLFF forward-facing captures (`poses_bounds.npy` + `images/`, `images_<N>/`).

`poses_bounds.npy` holds one row of 17 numbers per image (images in sorted file-name order):
a 3x5 matrix [R | t | hwf] flattened row by row, then the near and far depth bounds of the view.
R's columns are the camera axes in LLFF order (down, right, backwards); t is the camera centre;
hwf = (height, width, focal) of the full-resolution images. `images_<N>/` holds the images
downscaled N times; the focal length is scaled by the size of the images actually read.

What the loader does, in this order:
1. axes: (down, right, backwards) -> (right, up, backwards), the OpenGL convention of `scene.py`;
2. bounds rescaling: world units are scaled by 1 / (0.75 * smallest near bound), so every view's
   near bound is at least 1 / 0.75 and the NDC near plane at depth 1 is in front of all content;
3. recentring: a rigid transform makes the average camera (mean centre, mean axes) the identity;
   `extra["world_from_data"]` is the 4x4 similarity from the file's world to the scene's;
4. normalized device coordinates of that average camera (`scene.ndc`, near plane 1): rays are
   sampled in NDC, where the scene from the near plane to infinity fills a bounded box
   (docs/datasets.md). `bbox` is that box: the NDC extent of every training frustum; near / far
   are along the NDC rays.
5. hold-out: every `holdout_every`-th view (0, 8, 16, ... for llffhold 8) is `test`.

Image folder: with `image_size` None the largest images available (`images/`, else the smallest
N); otherwise the folder with the smallest images whose longer side is still >= image_size,
area-downscaled to exactly image_size when it is larger.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from boostnerf_cli.cameras import Intrinsics
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import NDC, pixel_rays
from boostnerf_cli.scenes.frames import (
    IMAGE_SUFFIXES,
    Frame,
    SceneSpace,
    hold_out,
    load_frames,
    one_line,
    orientation_note,
    scene_from_splits,
)
from boostnerf_cli.scenes.scene import Scene, Split

BOUND_FACTOR = 0.75
NDC_NEAR = 1.0
FOLDER = re.compile(r"^images(_\d+)?$")


def is_llff(path: Path) -> str:
    """What was found when `path` holds `poses_bounds.npy`, else ""."""
    folder = Path(path)
    if not (folder / "poses_bounds.npy").is_file():
        return ""
    found = sorted(p.name for p in folder.iterdir() if p.is_dir() and FOLDER.match(p.name))
    return "poses_bounds.npy" + (f" and {', '.join(f + '/' for f in found)}" if found else "")


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir()
                  if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file())


def _image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.height, im.width
    except (OSError, ValueError) as err:
        raise BoostNerfError(f"cannot read image {path} (corrupt or not an image: {one_line(err)})") from None


def choose_folder(folder: Path, image_size: int | None) -> tuple[Path, list[Path]]:
    """The images folder to read (see the module docstring) and its sorted image files."""
    candidates = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and FOLDER.match(p.name)):
        files = _image_files(sub)
        if files:
            h, w = _image_size(files[0])
            candidates.append((max(h, w), sub, files))
    if not candidates:
        raise BoostNerfError(f"{folder} has poses_bounds.npy but no images/ or images_<N>/ folder with images")
    candidates.sort(key=lambda c: -c[0])  # largest images first
    if image_size is None:
        return candidates[0][1], candidates[0][2]
    fitting = [c for c in candidates if c[0] >= image_size]
    if not fitting:
        sizes = ", ".join(f"{c[1].name}/ {c[0]} px" for c in candidates)
        raise BoostNerfError(f"image_size {image_size} is larger than every images folder of {folder} ({sizes}); "
                             f"images are never upscaled")
    return fitting[-1][1], fitting[-1][2]


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> poses (N, 3, 4) in LLFF axis order, hwf (N, 3), bounds (N, 2), all checked."""
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise BoostNerfError(f"cannot read {path}: {one_line(err)}; fix or regenerate the file") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise BoostNerfError(f"{path} has shape {arr.shape}: expected (N, 17), a 3x5 pose and 2 bounds per image")
    arr = arr.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
    if bad.size:
        raise BoostNerfError(f"{path}: row {bad[0]} (image {bad[0]}) contains NaN or infinite values; fix the pose")
    mats = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:]
    if (bounds <= 0).any() or (bounds[:, 1] <= bounds[:, 0]).any():
        i = int(np.flatnonzero((bounds <= 0).any(1) | (bounds[:, 1] <= bounds[:, 0]))[0])
        raise BoostNerfError(f"{path}: row {i} has depth bounds {bounds[i].tolist()}; need 0 < near < far")
    hwf = mats[:, :, 4]
    if (hwf <= 0).any():
        raise BoostNerfError(f"{path}: the hwf column (height, width, focal) must be positive")
    return mats[:, :, :4], hwf, bounds


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """(N, 3, 4) with axis columns (down, right, backwards) -> (N, 4, 4) with (right, up, backwards)."""
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, 0] = poses[:, :, 1]
    out[:, :3, 1] = -poses[:, :, 0]
    out[:, :3, 2:4] = poses[:, :, 2:4]
    return out


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def average_pose(poses: np.ndarray) -> np.ndarray:
    """The mean camera of (N, 4, 4) OpenGL poses: mean centre, backwards axis the normalised mean of
    the backwards axes, right axis orthogonal to it and to the mean up axis -> (4, 4)."""
    z = _normalize(poses[:, :3, 2].sum(0))
    up = poses[:, :3, 1].sum(0)
    x = _normalize(np.cross(up, z))
    avg = np.eye(4)
    avg[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    avg[:3, 3] = poses[:, :3, 3].mean(0)
    return avg


def frame_border(height: int, width: int, per_side: int = 1) -> torch.Tensor:
    """Pixel positions (u, v) along an image's border, (4 * per_side, 2) float64: the 4 corners for `per_side` 1,
    more points along each side for a lens (whose border is no straight line in the pinhole picture)."""
    s = torch.linspace(0, 1, per_side + 1, dtype=torch.float64)[:-1]
    top = torch.stack([s * width, torch.zeros_like(s)], -1)
    right = torch.stack([torch.full_like(s, width), s * height], -1)
    bottom = torch.stack([(1 - s) * width, torch.full_like(s, height)], -1)
    left = torch.stack([torch.zeros_like(s), (1 - s) * height], -1)
    return torch.cat([top, right, bottom, left])


def ndc_bbox(ndc: NDC, poses: torch.Tensor, intrinsics: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """The NDC box of every camera's frustum from the near plane to infinity -> (2, 3).

    The frustum part beyond the near plane is convex with its corners on the 4 image-corner rays,
    and the NDC map is projective there, so the box of the corner rays' NDC end points (on the
    near plane z = -1 and at infinity z = 1) holds every NDC ray of every pixel. A camera with a lens takes 16
    rays along each side of its border (render/rays.py `pixel_rays`) instead of the corners.
    """
    pts = []
    for pose, row in zip(poses.double(), intrinsics.double()):
        k = Intrinsics.of(row)
        uv = frame_border(height, width, 16 if k.lens is not None else 1)
        d = pixel_rays(uv, k) @ pose[:3, :3].T
        o, dn = ndc.rays(pose[:3, 3].expand(len(d), 3), d)
        end = o + ((1.0 - o[:, 2]) / dn[:, 2].clamp_min(1e-12))[:, None] * dn
        pts += [o, end]
    pts = torch.cat(pts)
    return torch.stack([pts.amin(0), pts.amax(0)]).float()


def forward_facing_world(poses: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Steps 2 and 3 of the module docstring for OpenGL camera-to-world `poses` (N, 4, 4) with depth `bounds`
    (N, 2): -> (the scene's poses, the 4x4 similarity world_from_data, the scale)."""
    poses = poses.copy()
    scale = 1.0 / (bounds.min() * BOUND_FACTOR)
    poses[:, :3, 3] *= scale
    to_scene = np.linalg.inv(average_pose(poses))
    return to_scene @ poses, to_scene @ np.diag([scale, scale, scale, 1.0]), scale


def ndc_space(train: Split, background: tuple[float, float, float]) -> SceneSpace:
    """Step 4: where a forward-facing scene's rays are sampled, in the NDC of the average camera (the identity after
    `forward_facing_world`) with the first training view's focal lengths."""
    fx, fy = float(train.intrinsics[0, 0]), float(train.intrinsics[0, 1])
    ndc = NDC(sx=2 * fx / train.width, sy=2 * fy / train.height, near=NDC_NEAR)
    bbox = ndc_bbox(ndc, train.poses, train.intrinsics, train.height, train.width)
    return SceneSpace(0.0, float((bbox[1] - bbox[0]).norm()), bbox, background, ndc)


def load_llff(
    path: Path,
    image_size: int | None = None,
    holdout_every: int = 8,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> Scene:
    """Load an LLFF folder into a forward-facing `Scene` with `ndc` set (see the module docstring)."""
    folder = Path(path)
    if not folder.is_dir():
        raise BoostNerfError(f"scene folder {folder} does not exist: check the path")
    pb = folder / "poses_bounds.npy"
    if not pb.is_file():
        raise BoostNerfError(f"no poses_bounds.npy in {folder}: not an LLFF scene")
    raw, hwf, bounds = read_poses_bounds(pb)
    sub, files = choose_folder(folder, image_size)
    if len(files) != len(raw):
        raise BoostNerfError(
            f"{pb.name} has {len(raw)} poses but {sub.name}/ holds {len(files)} images: "
            "each image needs exactly one pose row"
        )
    poses, world_from_data, scale = forward_facing_world(llff_to_opengl(raw), bounds)
    frames = [Frame(f, f.stem, p, {}, f"{sub.name}/{f.name}") for f, p in zip(files, poses)]
    bg = torch.tensor(background, dtype=torch.float32)
    images, alpha, native = load_frames(frames, image_size, bg)
    size = tuple(images.shape[1:3])
    bad = np.flatnonzero(~np.isclose(hwf[:, 1] / hwf[:, 0], native[1] / native[0], rtol=0.02))
    if bad.size:
        i = int(bad[0])
        raise BoostNerfError(
            f"{pb.name} row {i}: hwf's w x h = {hwf[i, 1]:g} x {hwf[i, 0]:g} does not match the images' aspect "
            f"({native[1]} x {native[0]} in {sub.name}/): fix the poses or the images{orientation_note(files[i])}")
    # hwf is for the full-resolution images; scale per axis to the images actually stored
    k = np.stack([hwf[:, 2] * size[1] / hwf[:, 1], hwf[:, 2] * size[0] / hwf[:, 0],
                  np.full(len(hwf), size[1] / 2), np.full(len(hwf), size[0] / 2)], axis=1)
    splits = {"train": Split(images, torch.tensor(poses, dtype=torch.float32), torch.tensor(k, dtype=torch.float32),
                             tuple(f.name for f in frames), alpha)}
    holdout = ""
    if holdout_every:
        splits["train"], splits["test"], holdout = hold_out(splits["train"], holdout_every)
    return scene_from_splits(folder, splits, ndc_space(splits["train"], background), "llff", holdout, native,
                             extra={"images_folder": sub.name, "world_from_data": world_from_data.tolist(),
                                    "bounds": (bounds * scale).tolist()})
