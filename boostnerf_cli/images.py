"""Pictures on disk: a heat colour map, labelled panel grids, and videos (MP4 or GIF).

Pure numpy + Pillow + imageio + imageio-ffmpeg (all core dependencies; MP4 is written with the ffmpeg
binary that imageio-ffmpeg ships). A .mp4 asked for when that backend is missing is refused, not
written as GIF.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.workspace import atomic_path


def to_uint8(img: torch.Tensor | np.ndarray) -> np.ndarray:
    """Colours in [0, 1] (clipped) -> uint8, rounded to nearest."""
    a = img.numpy() if isinstance(img, torch.Tensor) else img
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def depth_to_uint16(depth: torch.Tensor, far: float, radius: float | None = None) -> np.ndarray:
    """Depth in world units -> 16-bit PNG values (docs/reports.md): 65535 = `far`. With `radius` (an unbounded scene:
    its far bound is a thousand radii of the sphere it keeps linear, which would leave the subject black and coarse)
    the depth contracted as the scene is: u = t / (2 radius) up to the radius, 1 - radius / (2 t) past it, so 32768 is
    one radius away and 65535 infinitely far; t = 2 radius u, or radius / (2 (1 - u)) past one half."""
    if radius is None:
        return (depth.clamp(0, far) / far * 65535.0 + 0.5).numpy().astype(np.uint16)
    t = depth.double().clamp_min(0)
    u = torch.where(t <= radius, t / (2 * radius), 1 - radius / (2 * t.clamp_min(radius)))
    return (u * 65535.0 + 0.5).numpy().astype(np.uint16)


def write_png(path: Path, array: np.ndarray) -> None:
    """`array` (uint8 or uint16) as a PNG at `path`, atomically."""
    import imageio.v3 as iio

    with atomic_path(path) as tmp:
        iio.imwrite(tmp, array, extension=".png")


# Heat map: black -> purple -> red -> orange -> yellow -> white (monotonic in brightness, so it
# also reads in greyscale print). Anchors at evenly spaced values in [0, 1].
_HEAT = np.array([
    [0, 0, 0], [40, 10, 90], [120, 20, 130], [200, 40, 70], [245, 110, 20], [250, 200, 40], [255, 255, 230],
], dtype=np.float64) / 255.0


def heat(values: np.ndarray, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """Values (...,) -> uint8 RGB (..., 3) on the heat map, `lo` black, `hi` near-white, clipped."""
    span = hi - lo if hi > lo else 1.0
    x = np.clip((np.asarray(values, dtype=np.float64) - lo) / span, 0.0, 1.0) * (len(_HEAT) - 1)
    i = np.minimum(np.floor(x).astype(int), len(_HEAT) - 2)
    f = (x - i)[..., None]
    rgb = _HEAT[i] * (1.0 - f) + _HEAT[i + 1] * f
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def colorize_depth(depth: np.ndarray, acc: np.ndarray, lo: float, hi: float, background=(0, 0, 0)) -> np.ndarray:
    """Depth (H, W) -> uint8 RGB: near bright, far dark on the heat map; pixels with opacity < 0.5 get `background`."""
    rgb = heat(hi - np.asarray(depth), 0.0, hi - lo)
    rgb[np.asarray(acc) < 0.5] = np.asarray(background, dtype=np.uint8)
    return rgb


def upscale(img: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement (keeps every rendered pixel visible as a block)."""
    return img if factor <= 1 else np.repeat(np.repeat(img, factor, axis=0), factor, axis=1)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: fixed bitmap font
        return ImageFont.load_default()


def wrap_text(text: str, font, width: int) -> list[str]:
    """`text` broken into lines no wider than `width` px in `font`: at spaces, and inside a word only where the word
    alone is wider than that. Nothing is dropped: the lines joined back (with a space where they broke at one) give
    `text` again."""
    lines: list[str] = []
    for word in text.split(" "):
        trial = f"{lines[-1]} {word}" if lines else word
        if lines and font.getlength(trial) <= width:
            lines[-1] = trial
            continue
        lines.append("")
        for ch in word:  # a new line for the word; cut it where it alone does not fit
            if lines[-1] and font.getlength(lines[-1] + ch) > width:
                lines.append("")
            lines[-1] += ch
    return lines or [""]


LINE_H = 15  # pixels per line of text at font size 13


def panel_grid(rows: list[list[tuple[str, np.ndarray | None]]], min_width: int = 192, caption: str = "") -> np.ndarray:
    """Labelled panels in a grid -> uint8 RGB image.

    rows: lists of (label, uint8 RGB (H, W, 3) image or None for an empty cell); every image has
    the same size. Panels are enlarged by an integer factor to be at least `min_width` wide, each
    gets its label above it, and `caption` (optional) goes under the grid. A label wider than its panel is
    wrapped onto more lines (`wrap_text`), and its row's label band grows to hold them, so that no text runs into
    the next panel's; the caption wraps at the grid's width.
    """
    from PIL import Image, ImageDraw

    images = [img for row in rows for _, img in row if img is not None]
    if not images:
        raise BoostNerfError("nothing to draw")
    h, w = images[0].shape[:2]
    k = max(1, -(-min_width // w))
    ph, pw, pad = h * k, w * k, 4
    ncols = max(len(r) for r in rows)
    width = ncols * (pw + pad) + pad
    font = _font(13)
    labels = [[wrap_text(label, font, pw - 4) for label, _ in row] for row in rows]
    label_h = [3 + LINE_H * max(len(lines) for lines in row) for row in labels]  # one line: 18 px
    cap_lines = wrap_text(caption, font, width - 2 * pad - 4) if caption else []
    cap_h = 5 + LINE_H * len(cap_lines) if caption else 0  # one line: 20 px
    canvas = Image.new("RGB", (width, sum(label_h) + len(rows) * (ph + pad) + pad + cap_h), "white")
    draw = ImageDraw.Draw(canvas)
    y = pad
    for r, row in enumerate(rows):
        for c, (_, img) in enumerate(row):
            x = pad + c * (pw + pad)
            for j, line in enumerate(labels[r][c]):
                draw.text((x + 2, y + 2 + LINE_H * j), line, fill=(0, 0, 0), font=font)
            if img is not None:
                canvas.paste(Image.fromarray(upscale(np.ascontiguousarray(img), k)), (x, y + label_h[r]))
        y += label_h[r] + ph + pad
    for j, line in enumerate(cap_lines):
        draw.text((pad + 2, y + 3 + LINE_H * j), line, fill=(0, 0, 0), font=font)
    return np.asarray(canvas)


def colorbar(height: int, width: int, lo: float, hi: float) -> np.ndarray:
    """A vertical heat-map legend (top = hi, bottom = lo) of the given size, uint8 RGB; the caller labels it."""
    values = np.linspace(hi, lo, height)[:, None].repeat(max(1, width // 4), axis=1)
    bar = np.full((height, width, 3), 255, dtype=np.uint8)
    bar[:, : values.shape[1]] = heat(values, lo, hi)
    return bar


# --- videos ---------------------------------------------------------------------------------------
def ffmpeg_available() -> bool:
    """True when imageio-ffmpeg (a core dependency) imports and finds its ffmpeg binary."""
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return False
    return True


def video_target(path: Path) -> tuple[Path, str]:
    """The format of the video asked for at `path`, from its suffix: "mp4" or "gif". A .mp4 without a
    working ffmpeg backend is refused (before anything is rendered or written), never changed to GIF."""
    path = Path(path)
    if path.suffix.lower() == ".gif":
        return path, "gif"
    if path.suffix.lower() != ".mp4":
        raise BoostNerfError(f"--video {path}: name an .mp4 or .gif file")
    if not ffmpeg_available():
        raise BoostNerfError(f"cannot write {path.name}: the MP4 writer imageio-ffmpeg (a boostnerf dependency) is "
                             "not installed or has no ffmpeg binary; reinstall it (pip install imageio-ffmpeg) "
                             "or ask for --video NAME.gif")
    return path, "mp4"


def write_videos(videos: list[tuple[Path, list[np.ndarray]]], fps: float, fmt: str) -> None:
    """Videos (path, frames: uint8 RGB of one size) as MP4 or GIF (`encode_video`), as one set: each encoded to a
    temporary file next to it, and only once every one is, all renamed into place; one that fails to encode leaves
    none of them written (the previous versions unchanged). The callers check the paths first (`check_writable`)."""
    with contextlib.ExitStack() as stack:
        temporary = [stack.enter_context(atomic_path(path, keep_suffix=True)) for path, _ in videos]  # ffmpeg: suffix
        for tmp, (path, frames) in zip(temporary, videos):
            try:
                encode_video(tmp, frames, fps, fmt)
            except OSError as e:  # said of its own file here: left to the stack, the last one entered would name its
                raise BoostNerfError(f"could not write {path} ({e.strerror or e}); no video of the set was written: "
                                     "free disk space or fix the folder's permissions and rerun the same command"
                                     ) from None


def encode_video(path: Path, frames: list[np.ndarray], fps: float, fmt: str) -> None:
    """Frames (uint8 RGB, same size) -> `path` as MP4 (H.264, yuv420p) or looping GIF (written in place)."""
    if not frames:
        raise BoostNerfError("no frames to write")
    if fmt == "mp4":
        import imageio.v2 as iio2

        h, w = frames[0].shape[:2]
        pad = ((0, h % 2), (0, w % 2), (0, 0))  # yuv420p needs even sides
        with iio2.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
                             macro_block_size=1, quality=8) as writer:
            for f in frames:
                writer.append_data(np.pad(f, pad, mode="edge"))
    elif fmt == "gif":
        import imageio.v3 as iio

        iio.imwrite(path, np.stack(frames), extension=".gif", duration=round(1000 / fps), loop=0)
    else:
        raise BoostNerfError(f"unknown video format {fmt!r}")
