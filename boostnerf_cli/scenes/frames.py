"""What more than one dataset loader uses: frames, image reading and downscaling, pose and JSON
parsing, the hold-out split and the `Scene` a loader returns.

A loader parses its own files into `Frame`s (image path, name, OpenGL camera-to-world pose, camera
keys), reads all their images with `load_frames` (one size for the whole scene, area-downscaled,
composited on the background), builds its `Split`s, optionally holds views out with `hold_out`, and
returns `scene_from_splits(...)`. Every error is a one-line `BoostNerfError` naming the file.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from torch import Tensor

from boostnerf_cli.cameras import MODELS, Intrinsics, Lens, focal_for_fov
from boostnerf_cli.errors import BoostNerfError, DataWarning
from boostnerf_cli.render.rays import NDC
from boostnerf_cli.scenes.scene import Scene, Split


@dataclass(frozen=True)
class Frame:
    """One parsed frame: where its image is, its pose and the JSON it came from."""

    image: Path
    name: str
    pose: np.ndarray  # (4, 4) float64
    camera: dict  # intrinsics keys (camera_angle_x, fl_x, ...) of the frame, falling back to the file
    source: str  # "transforms_train.json frame 3", for error messages


def one_line(err: Exception) -> str:
    """An exception's message on one line (whitespace collapsed, at most 200 characters), or its type
    name when the message is empty: for quoting a library's error inside a `BoostNerfError`. An error that quotes
    ffmpeg's output (imageio-ffmpeg's, after "=== stderr ==="), whose first lines are its version and build: the last
    line, where ffmpeg says what went wrong."""
    text = str(err)
    if "=== stderr ===" in text:
        said = [ln for ln in text.split("=== stderr ===", 1)[1].splitlines() if ln.strip()]
        text = said[-1] if said else text.split("=== stderr ===", 1)[0]
    return (" ".join(text.split()) or type(err).__name__)[:200]


# ----------------------------------------------------------------------------- resampling


def area_matrix(old: int, new: int) -> Tensor:
    """(new, old) weights of an exact area-weighted 1-D resample: overlap of each output cell
    [i*s, (i+1)*s) (s = old / new, in input pixels) with each input pixel [j, j+1), divided by s."""
    s = old / new
    start = torch.arange(new, dtype=torch.float64)[:, None] * s
    j = torch.arange(old, dtype=torch.float64)[None, :]
    overlap = (torch.minimum(start + s, j + 1) - torch.maximum(start, j)).clamp_min(0)
    return (overlap / s).float()


def area_downscale(image: Tensor, height: int, width: int) -> Tensor:
    """Area-average (H, W, C) -> (height, width, C).

    An integer factor per axis is an exact box filter (block mean). Otherwise each output pixel is
    the area-weighted mean of the input pixels its footprint overlaps (exact fractional overlaps,
    separable), which equals the box filter whenever the factor is an integer.
    """
    h, w, c = image.shape
    if (height, width) == (h, w):
        return image
    if h % height == 0 and w % width == 0:
        return image.reshape(height, h // height, width, w // width, c).mean(dim=(1, 3))
    rows = area_matrix(h, height) @ image.reshape(h, w * c)
    return torch.einsum("ow,hwc->hoc", area_matrix(w, width), rows.reshape(height, w, c))


def target_size(height: int, width: int, image_size: int | None) -> tuple[int, int]:
    """(height, width) after scaling the longer side to `image_size`; never upscales."""
    longest = max(height, width)
    if image_size is None or image_size == longest:
        return height, width
    if image_size < 1 or image_size > longest:
        raise BoostNerfError(
            f"image_size {image_size} is not in 1..{longest} (native {width}x{height}): pass a size "
            f"no larger than the native longer side, images are never upscaled"
        )
    scale = image_size / longest
    return max(1, round(height * scale)), max(1, round(width * scale))


# ----------------------------------------------------------------------------- images


# Pillow's advice to convert palette transparency to RGBA: `_read_mode` does. A filter set once, for this message
# alone: `warnings.catch_warnings` around each read is not thread-safe (`load_frames` reads in threads), and its
# exits can leave other threads' filters in place, an "ignore UserWarning" that silences the loaders' `DataWarning`s.
warnings.filterwarnings("ignore", message="Palette images with Transparency", category=UserWarning)


def _read_mode(path: Path) -> str | None:
    """The Pillow mode to read an image in so that its colours and transparency survive, or None (as stored).
    A palette image (what pngquant writes) or a colour-keyed grey or RGB PNG may carry transparency, which a
    plain read drops (its transparent pixels came back black); CMYK, YCbCr, LAB and HSV read as RGB (a CMYK
    JPEG's K came back as alpha); a 1-bit image reads as grey."""
    from PIL import Image

    with Image.open(path) as im:
        mode, transparent = im.mode, "transparency" in im.info
    if mode in ("P", "PA"):
        return "RGBA" if mode == "PA" or transparent else "RGB"
    if transparent and mode in ("L", "RGB"):
        return "LA" if mode == "L" else "RGBA"
    return {"CMYK": "RGB", "YCbCr": "RGB", "LAB": "RGB", "HSV": "RGB", "1": "L"}.get(mode)


def read_image(path: Path, out_of_range: list | None = None) -> Tensor:
    """Read an image as float32 (H, W, C) in [0, 1]: C = 1 grey, 2 grey+alpha, 3 RGB, 4 RGBA (`_read_mode`).

    8- and 16-bit integers are scaled by their type's maximum; 32-bit integers (Pillow's mode "I", which is how
    Pillow reads a 16-bit grey PNG in some releases, and how integer TIFFs come) hold 16-bit values and are scaled
    by 65535 (beyond that range they are refused); float images are taken as they are: values past [0, 1] (HDR),
    which compositing clips, add (path, min, max) to `out_of_range` when given (`load_frames` warns once)."""
    try:
        data = iio.imread(path, plugin="pillow", mode=_read_mode(path))
    except Exception as err:  # imageio/PIL raise many types for corrupt files
        raise BoostNerfError(f"cannot read image {path} (corrupt, or a kind Pillow cannot read: {one_line(err)}); "
                             "replace it, or re-export it as an 8- or 16-bit PNG or a JPEG") from None
    if data.ndim == 4:
        raise BoostNerfError(f"image {path} holds {data.shape[0]} frames (an animated image): save one still frame "
                             "per view")
    if data.ndim == 2:
        data = data[..., None]
    if data.ndim != 3 or data.shape[-1] not in (1, 2, 3, 4):
        raise BoostNerfError(f"image {path} has shape {data.shape}: expected grey, RGB or RGBA")
    scale = None
    if np.issubdtype(data.dtype, np.integer):
        scale = np.iinfo(data.dtype).max
        if data.dtype.itemsize > 2:
            lo, hi = int(data.min()), int(data.max())
            if lo < 0 or hi > 65535:
                raise BoostNerfError(f"image {path} holds {data.dtype} values in {lo}..{hi}, outside 16 bits: "
                                     "re-export it as an 8- or 16-bit PNG")
            scale = 65535
    img = torch.from_numpy(np.ascontiguousarray(data)).float()
    if scale is None and not bool(torch.isfinite(img).all()):  # NaN passes every range test and survives clamping
        raise BoostNerfError(f"image {path} holds NaN or infinite values: re-export it (tone-mapped, 8- or 16-bit)")
    if scale is not None:
        img.mul_(1.0 / scale)
    elif out_of_range is not None and data.size and (float(img.max()) > 1.0 + 1e-6 or float(img.min()) < -1e-6):
        out_of_range.append((path, float(img.min()), float(img.max())))
    return img


def orientation_note(path: Path) -> str:
    """"" or, for an image whose EXIF orientation tag turns or mirrors it (a phone's portrait shot), a note for an
    error about its size: boostnerf reads the pixels as stored, as COLMAP and nerfstudio do (so poses they computed
    match them), and does not apply the tag."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            tag = im.getexif().get(0x0112, 1)
    except (OSError, ValueError):
        return ""
    if tag in (None, 0, 1):
        return ""
    return (f"; {path.name} carries EXIF orientation {tag}, which boostnerf does not apply (it reads the pixels as "
            "stored, as COLMAP and nerfstudio do): if the cameras were computed on the turned images, turn the files "
            "themselves (e.g. mogrify -auto-orient)")


def composite(image: Tensor, background: Tensor) -> Tensor:
    """(h, w, C) premultiplied colour (+ alpha when C is 2 or 4) -> (h, w, 3) RGB on `background` (3,)."""
    colour = image[..., :3] if image.shape[-1] >= 3 else image[..., :1].expand(*image.shape[:2], 3)
    if image.shape[-1] in (2, 4):
        colour = colour + (1.0 - image[..., -1:]) * background
    return colour.clamp(0.0, 1.0)


def load_image(path: Path, size: tuple[int, int], native: tuple[int, int], background: Tensor,
               out_of_range: list | None = None) -> tuple[Tensor, Tensor | None]:
    """Read one image, area-downscale its premultiplied colour and alpha to `size` (h, w), then
    composite on `background` (3,) -> (h, w, 3) float32, and its downscaled alpha (h, w) (None when it has none).

    Raises BoostNerfError when the image's (H, W) differs from `native`.
    """
    img = read_image(path, out_of_range)
    if tuple(img.shape[:2]) != native:
        raise BoostNerfError(
            f"image {path} is {img.shape[1]}x{img.shape[0]} but the scene's images are "
            f"{native[1]}x{native[0]}: all views must have the same size"
        )
    if img.shape[-1] in (2, 4):
        img[..., :-1].mul_(img[..., -1:])  # premultiply in place
    small = area_downscale(img, *size)
    return composite(small, background), (small[..., -1].clamp(0.0, 1.0) if img.shape[-1] in (2, 4) else None)


def load_frames(frames: list[Frame], image_size: int | None,
                background: Tensor) -> tuple[Tensor, Tensor | None, tuple[int, int]]:
    """Load every frame's image, in order, with a small thread pool -> (N, h, w, 3) composited on `background`,
    alpha (N, h, w) (None when no image has an alpha channel; 1 for those without one), native (H, W).

    The first image's size is the scene's native size (every other image must match it);
    (h, w) is `target_size(H, W, image_size)`.
    """
    native = tuple(read_image(frames[0].image).shape[:2])
    size = target_size(*native, image_size)
    workers = max(1, min(8, os.cpu_count() or 1))
    out_of_range: list = []  # list.append is atomic: the threads share it
    with ThreadPoolExecutor(max_workers=workers) as pool:
        loaded = list(pool.map(lambda f: load_image(f.image, size, native, background, out_of_range), frames))
    if out_of_range:
        first, lo, hi = min(out_of_range, key=lambda t: str(t[0]))
        warnings.warn(DataWarning(
            f"{len(out_of_range)} of {len(frames)} images hold floating-point values outside 0..1 (HDR? {first}: "
            f"{lo:.3g}..{hi:.3g}): they are clipped to 0..1; tone-map the images to 8- or 16-bit first"), stacklevel=2)
    images = torch.stack([rgb for rgb, _ in loaded])
    if all(a is None for _, a in loaded):
        return images, None, native
    plain = [f.image for f, (_, a) in zip(frames, loaded) if a is None]
    if plain:
        warnings.warn(DataWarning(
            f"{len(plain)} of {len(frames)} images have no alpha channel while the others have one "
            f"({plain[0]}{', ...' if len(plain) > 1 else ''}): they are used as they are, not composited on the "
            "background colour; save them with their alpha, or composited on that colour"), stacklevel=2)
    alpha = torch.stack([torch.ones(size) if a is None else a for _, a in loaded])
    return images, alpha, native


def lossy_extra(frames) -> dict:
    """`Scene.extra` entry for frames read from lossy files (JPEG): {"lossy": True}, else {}
    (`coverage.foreground_tol`)."""
    return {"lossy": True} if any(Path(f.image).suffix.lower() in (".jpg", ".jpeg") for f in frames) else {}


# ----------------------------------------------------------------------------- transforms JSON


CAMERA_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")


def read_transforms(path: Path, may_be_empty: bool = False) -> dict:
    """The top-level object of a transforms JSON file (Blender, nerfstudio); raises unless it parses
    and has a `frames` list, which must not be empty unless `may_be_empty` (a Blender val / test split)."""
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise BoostNerfError(f"cannot parse {path}: {one_line(err)}; fix or regenerate the file") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise BoostNerfError(f"{path} has no 'frames' list: expected a transforms file with one entry per view")
    if not meta["frames"] and not may_be_empty:
        raise BoostNerfError(f"{path} has an empty 'frames' list: it needs one entry per view")
    return meta


# a transforms file's lens coefficients (nerfstudio's keys): the `cameras.Lens` fields of the same names
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
LENS_KEYS = ("camera_model", *DISTORTION_KEYS)


def lens_models() -> tuple[str, ...]:
    """The camera_model values of a transforms file boostnerf renders as they are: COLMAP's models (`cameras.MODELS`)
    whose lens the file's keys hold (FULL_OPENCV's rational terms have no nerfstudio key)."""
    return tuple(m.name for m in MODELS.values() if m.renders and set(m.fields) <= {"f", "fx", "fy", "cx", "cy",
                                                                                     *DISTORTION_KEYS})


def check_lens(entry: dict, source: str) -> None:
    """Refuse a transforms entry (the file's top level or a frame) whose camera boostnerf cannot render: a
    camera_model outside `lens_models()` (an equirectangular or omnidirectional camera), a coefficient that is no
    number, or tangential p1 / p2 on a fisheye (which has none)."""
    model = entry.get("camera_model")
    if model is not None and str(model).upper() not in lens_models():
        raise BoostNerfError(
            f"{source}: camera_model {model} is not supported; boostnerf renders {', '.join(lens_models())} cameras: "
            "undistort the images to a pinhole camera first (e.g. COLMAP image_undistorter) and write camera_model "
            "PINHOLE"
        )
    for key in DISTORTION_KEYS:
        value = entry.get(key)
        try:
            if value is not None and (isinstance(value, bool) or not math.isfinite(float(value))):
                raise ValueError
        except (TypeError, ValueError):
            raise BoostNerfError(f"{source}: distortion {key} must be a finite number, got {value!r}") from None


def frame_lens(camera: dict, source: str) -> Lens | None:
    """The lens of a frame's merged `camera` (`frame_camera`): None for a pinhole camera (no coefficient set, not a
    fisheye)."""
    fisheye = MODELS[str(camera.get("camera_model") or "OPENCV").upper()].fisheye
    coefficients = {k: float(camera[k]) for k in DISTORTION_KEYS if camera.get(k) is not None}
    if fisheye and (coefficients.get("p1") or coefficients.get("p2")):
        raise BoostNerfError(f"{source}: camera_model OPENCV_FISHEYE has no tangential distortion, but p1 / p2 are "
                             "set: remove them, or give the camera model that estimated them")
    lens = Lens(**coefficients, fisheye=fisheye)
    return lens if lens.bends else None


FOCAL_KEYS = (("fl_x", "camera_angle_x"), ("fl_y", "camera_angle_y"))  # two ways to give each axis's focal length


def frame_camera(frame: dict, meta: dict) -> dict:
    """A frame's camera values (`CAMERA_KEYS`, and the lens's `LENS_KEYS`): its own where it sets them (not null),
    else the file's. A frame that gives an axis's focal length either way (`FOCAL_KEYS`) takes none of the file's for
    that axis."""
    camera = {k: frame[k] if frame.get(k) is not None else meta.get(k) for k in (*CAMERA_KEYS, *LENS_KEYS)}
    for keys in FOCAL_KEYS:
        if any(frame.get(k) is not None for k in keys):
            camera.update({k: frame.get(k) for k in keys})
    return camera


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")  # the image files the loaders read (in either case)


def find_image(folder: Path, file_path: str) -> Path | None:
    """The image a frame's `file_path` names (as `resolve_image`), or None when no such file is there."""
    base = folder / file_path
    suffixes = (*IMAGE_SUFFIXES, *(s.upper() for s in IMAGE_SUFFIXES))
    return next((c for c in (base, *(base.with_name(base.name + s) for s in suffixes)) if c.is_file()), None)


def resolve_image(folder: Path, file_path: str, source: str) -> Path:
    """The image a frame's `file_path` names: `folder / file_path`, else the same with an image suffix added
    (`IMAGE_SUFFIXES` in lower, then upper case: the Blender release writes `./train/r_0` for `train/r_0.png`);
    raises (prefixed with `source`) when none is a file."""
    base = folder / file_path
    suffixes = (*IMAGE_SUFFIXES, *(s.upper() for s in IMAGE_SUFFIXES))
    candidates = (base, *(base.with_name(base.name + s) for s in suffixes))
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    folders = [c for c in candidates if c.is_dir()]
    if folders:
        raise BoostNerfError(f"{source}: image {file_path!r} is a folder ({folders[0]}), not an image file")
    raise BoostNerfError(f"{source}: image {file_path!r} not found (looked for {base} and {base} with "
                         f"{', '.join(suffixes)})")


def parse_pose(matrix, source: str) -> np.ndarray:
    """A frame's `transform_matrix` as a finite (4, 4) float64 array; raises (prefixed with `source`)
    otherwise."""
    try:
        pose = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        pose = np.zeros(0)
    if pose.shape == (3, 4):  # the last row 0 0 0 1 left out
        pose = np.vstack([pose, [0.0, 0.0, 0.0, 1.0]])
    if pose.shape != (4, 4):
        raise BoostNerfError(f"{source}: transform_matrix must be a 4x4 (or 3x4) matrix of numbers, "
                             f"got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise BoostNerfError(f"{source}: transform_matrix contains NaN or infinite values; fix the pose")
    det = float(np.linalg.det(pose[:3, :3]))
    if abs(det) < 1e-6:
        raise BoostNerfError(f"{source}: transform_matrix's rotation (its 3x3 block) is singular "
                             f"(determinant {det:.2g}), not a camera orientation; fix the pose")
    return pose


def camera_number(camera: dict, key: str, source: str) -> float | None:
    """`camera[key]` as a float (None when unset); raises (prefixed with `source`) unless it is a number, and for
    the image size `w` / `h` unless it is positive."""
    value = camera[key]
    if value is None:
        return None
    try:
        if isinstance(value, bool):
            raise TypeError
        number = float(value)
    except (TypeError, ValueError):
        raise BoostNerfError(f"{source}: {key} = {value!r} is not a number; fix the transforms file") from None
    if key in ("w", "h") and not 0 < number < math.inf:
        raise BoostNerfError(f"{source}: {key} = {value!r} must be a positive number (the image size in pixels the "
                             "intrinsics refer to); fix or remove it")
    return number


def frame_intrinsics(camera: dict, native: tuple[int, int], size: tuple[int, int], source: str,
                     image: Path | None = None) -> Intrinsics:
    """fx, fy, cx, cy in pixels of the stored (downscaled) image, and the lens (`frame_lens`).

    The JSON values refer to an image of `w` x `h` pixels (default, both unset: the native image size); every
    value is scaled per axis by stored / JSON size. `w` and `h` must come together and have the native image's
    aspect (`image`, when given, is named if an EXIF tag turns it).
    """
    def number(key: str) -> float | None:
        return camera_number(camera, key, source)

    w, h = number("w"), number("h")
    if (w is None) != (h is None):
        given, missing = ("w", "h") if h is None else ("h", "w")
        raise BoostNerfError(f"{source}: {given} is given without {missing}: give both (the image size in pixels the "
                             "intrinsics refer to) or neither")
    # the image may be a pixel off per axis from a downscale's rounding: 0.5% at least, more for tiny images
    tolerance = max(0.005, 1 / native[0] + 1 / native[1])
    if w is not None and not math.isclose(w / h, native[1] / native[0], rel_tol=tolerance):
        note = orientation_note(image) if image is not None else ""
        raise BoostNerfError(f"{source}: w x h = {w:g} x {h:g} does not match the image's {native[1]} x {native[0]} "
                             f"aspect; w and h are the size of the image the intrinsics refer to: fix them, or the "
                             f"image{note}")

    def focal(angle_key: str, size: float) -> float:
        angle = number(angle_key)
        if not 0 < angle < math.pi:
            raise BoostNerfError(f"{source}: {angle_key} = {angle!r}: a field of view must be in (0, pi) radians")
        return focal_for_fov(angle, size)

    h_json = h or float(native[0])
    w_json = w or float(native[1])
    fx = fy = None
    if camera["fl_x"] is not None:
        fx = number("fl_x")
    elif camera["camera_angle_x"] is not None:
        fx = focal("camera_angle_x", w_json)
    if camera["fl_y"] is not None:
        fy = number("fl_y")
    elif camera["camera_angle_y"] is not None:
        fy = focal("camera_angle_y", h_json)
    if fx is None and fy is None:
        raise BoostNerfError(f"{source}: no focal length (camera_angle_x or fl_x, camera_angle_y or fl_y); add one to "
                             "the transforms file")
    fx = fy if fx is None else fx  # one axis given: square pixels
    fy = fx if fy is None else fy
    cx = number("cx") if camera["cx"] is not None else w_json / 2
    cy = number("cy") if camera["cy"] is not None else h_json / 2
    sx, sy = size[1] / w_json, size[0] / h_json
    return Intrinsics(fx, fy, cx, cy, frame_lens(camera, source)).scaled(sx, sy)


# ----------------------------------------------------------------------------- splits


def hold_out(train: Split, every: int) -> tuple[Split, Split, str]:
    """Split `train` into (kept train, held-out test, description): views i with i % every == 0.

    Raises when `every` < 2 or when no train view would be left.
    """
    if every < 2:
        raise BoostNerfError(f"holdout_every must be 0 (off) or at least 2, got {every}")
    held = [i for i in range(len(train)) if i % every == 0]
    kept = [i for i in range(len(train)) if i % every != 0]
    if not kept:
        raise BoostNerfError(
            f"only {len(train)} train view(s): holding out every {every}th leaves none; hold none out with "
            "--holdout-every 0 (recipe key data.holdout_every: 0)"
        )
    text = f"every {every}th train view ({len(held)} of {len(train)}) held out as test"
    return train.subset(kept), train.subset(held), text


@dataclass(frozen=True)
class SceneSpace:
    """Where a scene's rays are sampled, and what they meet past it: near, far and the box (in NDC for a
    forward-facing capture, `ndc` set; `Scene`) and the background colour."""

    near: float
    far: float
    bbox: Tensor
    background: tuple[float, float, float]
    ndc: NDC | None = None


def scene_from_splits(folder: Path, splits: dict[str, Split], space: SceneSpace, format: str, holdout: str,
                      native: tuple[int, int], extra: dict | None = None) -> Scene:
    """The `Scene` a loader returns for the dataset in `folder`.

    name: the folder's own name and source: its absolute path (both after resolving links);
    background: as floats. extra: `native_size` (the images' size on disk) and `image_size` (as
    stored: the train views' size), each [height, width], then the loader's own `extra` keys.
    """
    if len(splits["train"]) == 1:
        warnings.warn(DataWarning(
            f"{folder} has 1 training view{' (after the hold-out: ' + holdout + ')' if holdout else ''}: one viewpoint "
            "shows no depth, so other views render little but background; capture the subject from several "
            "directions"), stacklevel=2)
    return Scene(
        name=folder.resolve().name,
        splits=splits,
        near=space.near,
        far=space.far,
        bbox=space.bbox,
        background=tuple(float(c) for c in space.background),
        source=str(folder.resolve()),
        format=format,
        holdout=holdout,
        extra={"native_size": list(native), "image_size": [splits["train"].height, splits["train"].width],
               **(extra or {})},
        ndc=space.ndc,
    )
