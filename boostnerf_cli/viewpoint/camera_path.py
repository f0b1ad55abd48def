"""Camera paths a user draws: keyframes (a pose and a vertical field of view), the smooth path sampled through them,
and the path as a JSON file in nerfstudio's camera-path layout (its viewer's, read by `ns-render camera-path`), so
that paths move between the tools. `boostnerf view`'s camera path panel edits a `CameraPath`; `render --camera-path`
renders a file's frames (`read_camera_path`, `path_cameras`).

- `CameraPath`: the keyframes in order (`Keyframe`: an OpenGL camera-to-world pose in the scene's world, a vertical
  field of view in degrees), the list operations the panel offers (`CameraPath.add`, `CameraPath.move`,
  `CameraPath.delete`, `CameraPath.set_fov`), and the path through them: `CameraPath.at` (the pose and field of view
  at a time), `CameraPath.frames` (the frames of a video, `CameraPath.fps` a second over `CameraPath.seconds`).
  The keyframes are evenly spaced in time (one after the other; with `CameraPath.cycle` the last leads back to the
  first). Positions and the field of view follow a Kochanek-Bartels spline of tension 1 - `CameraPath.smoothness`
  (1: Catmull-Rom, smooth; 0: straight lines from keyframe to keyframe, easing into each); rotations follow the
  matching spherical Bezier curve of unit quaternions (De Casteljau's construction with `slerp`): great arcs between
  the keyframes' rotations at smoothness 0, tangent to the arcs' neighbours at 1. The path passes through every
  keyframe at its time.
- The file (`path_json`, `write_camera_path`, `read_camera_path`): "camera_path", the frames to render, each
  {"camera_to_world": 16 numbers, a 4x4 OpenGL camera-to-world matrix row by row, "fov": vertical, degrees,
  "aspect": width / height}; "render_width", "render_height" (every frame's size in pixels); "camera_type"
  ("perspective", the only one boostnerf renders); "keyframes" ({"matrix", "fov", "aspect"} each), "fps", "seconds",
  "is_cycle", "smoothness_value" (nerfstudio's spline tension: 0 smooth, 1 straight; 1 - `CameraPath.smoothness`),
  "default_fov", "default_transition_sec". A file with keyframes and no "camera_path" frames is sampled from its
  keyframes. Every frame is rendered at render_width x render_height with square pixels (as ns-render does), so an
  "aspect" other than render_width / render_height is refused, as are a "crop", another camera type and any
  "version" (nerfstudio writes none); nerfstudio's "render_time" (a dynamic scene's time) is ignored.
- Frames: the poses in a file are in the frame of the data as the user gave it (a capture's COLMAP world, a
  transforms.json's own), not the scene's world where boostnerf renders: `cameras.DataFrame` crosses between the two
  (the identity but for forward-facing captures), so a path through a capture's own camera poses, written by any tool,
  renders that capture's photos. A matrix must be rigid: an orthonormal rotation, bottom row 0 0 0 1; a uniform scale
  of the rotation (a scaled camera object in Blender) is divided out, as nerfstudio's rays normalise it away.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import DataFrame, Intrinsics
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.renderer import Camera
from boostnerf_cli.workspace import read_json, write_json

CAMERA_TYPES = ("perspective",)  # nerfstudio's "fisheye" and "equirectangular" are not rendered
RIGID = 1e-3  # the largest |R^T R / s^2 - I| of a pose's rotation R (s: its uniform scale)
ASPECT = 0.01  # a frame's aspect may differ from render_width / render_height by this fraction (rounding)
MAX_SIDE = 16384  # render_width and render_height at most
HAND_FIX = "fix it (UTF-8 JSON, one object), or save the path again from `boostnerf view`"  # a user's file
MAX_FRAMES = 100_000  # frames a path sampled from its keyframes has at most (fps x seconds)
DEFAULT_SECONDS = 4.0  # a new path's duration
NAME = re.compile(r"^[\w][\w.-]*$")  # a camera path's file name (before .json): letters, digits, _ . -


# --- unit quaternions (w, x, y, z), float64 -------------------------------------------------------------------------
def quat_of(r: np.ndarray) -> np.ndarray:
    """A rotation matrix (3, 3) -> its unit quaternion, w >= 0."""
    m = np.asarray(r, dtype=np.float64)
    k = np.array([  # Bar-Itzhack's symmetric matrix: its top eigenvector is the quaternion (x, y, z, w)
        [m[0, 0] - m[1, 1] - m[2, 2], m[1, 0] + m[0, 1], m[2, 0] + m[0, 2], m[2, 1] - m[1, 2]],
        [m[1, 0] + m[0, 1], m[1, 1] - m[0, 0] - m[2, 2], m[2, 1] + m[1, 2], m[0, 2] - m[2, 0]],
        [m[2, 0] + m[0, 2], m[2, 1] + m[1, 2], m[2, 2] - m[0, 0] - m[1, 1], m[1, 0] - m[0, 1]],
        [m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], m[0, 0] + m[1, 1] + m[2, 2]]]) / 3.0
    x, y, z, w = np.linalg.eigh(k)[1][:, -1]
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def matrix_of(q: np.ndarray) -> np.ndarray:
    """A unit quaternion -> its rotation matrix (3, 3)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, av, bw, bv = a[0], a[1:], b[0], b[1:]
    return np.concatenate([[aw * bw - av @ bv], aw * bv + bw * av + np.cross(av, bv)])


def qinv(q: np.ndarray) -> np.ndarray:
    return np.concatenate([q[:1], -q[1:]])


def qlog(q: np.ndarray) -> np.ndarray:
    """A unit quaternion -> half its rotation angle times its axis (3,), of the shorter way round."""
    q = q if q[0] >= 0 else -q
    s = np.linalg.norm(q[1:])
    return q[1:] * (math.atan2(s, q[0]) / s if s > 1e-12 else 1.0)


def qexp(v: np.ndarray) -> np.ndarray:
    """The inverse of `qlog`."""
    a = float(np.linalg.norm(v))
    return np.concatenate([[math.cos(a)], v * (math.sin(a) / a if a > 1e-12 else 1.0)])


def slerp(a: np.ndarray, b: np.ndarray, u: float) -> np.ndarray:
    """The rotation a fraction `u` of the shorter way from `a` to `b`."""
    return qmul(a, qexp(u * qlog(qmul(qinv(a), b))))


# --- the path ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Keyframe:
    """A camera the path passes: `pose` (4, 4) float64, OpenGL camera-to-world in the scene's world; `fov` vertical,
    in degrees."""

    pose: np.ndarray
    fov: float

    @classmethod
    def of_camera(cls, camera: Camera) -> "Keyframe":
        """The keyframe of a camera (a page's view): its pose and vertical field of view."""
        fov = math.degrees(Intrinsics.of(camera.intrinsics).fov_y(camera.height))
        return cls(camera.pose.double().cpu().numpy(), fov)


@dataclass(frozen=True)
class PathFrame:
    """One frame of a video along a path: its pose (as `Keyframe.pose`) and vertical field of view in degrees."""

    pose: np.ndarray
    fov: float


def hermite(p0, p1, m0, m1, u: float):
    """The cubic Hermite curve from p0 (tangent m0) to p1 (tangent m1) at u in [0, 1]."""
    u2, u3 = u * u, u * u * u
    return (2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * m0 + (3 * u2 - 2 * u3) * p1 + (u3 - u2) * m1


@dataclass
class CameraPath:
    """Keyframes in order and how the path runs through them (module docstring): its duration, frames per second,
    smoothness (0 straight .. 1 smooth), whether it closes on itself, and the size of its frames in pixels."""

    keyframes: list[Keyframe] = field(default_factory=list)
    seconds: float = DEFAULT_SECONDS
    fps: float = 24.0
    smoothness: float = 1.0
    cycle: bool = False
    width: int = 256
    height: int = 256

    # --- the panel's operations ---------------------------------------------------------------------------------------
    def check(self, i: int) -> int:
        """`i`, refused in one line unless the path has keyframe `i`."""
        if not 0 <= i < len(self.keyframes):
            have = f"keyframes 0 to {len(self.keyframes) - 1}" if self.keyframes else "no keyframes yet"
            raise BoostNerfError(f"there is no keyframe {i}: the path has {have}")
        return i

    def add(self, keyframe: Keyframe, at: int | None = None) -> int:
        """Insert `keyframe` before keyframe `at` (default: at the end) -> its index."""
        at = len(self.keyframes) if at is None else min(max(0, at), len(self.keyframes))
        self.keyframes.insert(at, keyframe)
        return at

    def move(self, i: int, step: int) -> int:
        """Move keyframe `i` `step` places later (earlier when negative), within the list -> its new index."""
        to = min(max(0, self.check(i) + step), len(self.keyframes) - 1)
        self.keyframes.insert(to, self.keyframes.pop(i))
        return to

    def delete(self, i: int) -> None:
        self.keyframes.pop(self.check(i))

    def set_fov(self, i: int, fov: float) -> None:
        """Give keyframe `i` vertical field of view `fov` (degrees)."""
        self.keyframes[self.check(i)] = Keyframe(self.keyframes[i].pose, check_fov(fov, f"keyframe {i}'s fov"))

    def configure(self, seconds: float, fps: float, smoothness: float, cycle: bool, width: int, height: int) -> None:
        """Set how the path runs (module docstring) and its frames' size; one line for a value out of range."""
        seconds, fps = number(seconds, "the duration (seconds)"), number(fps, "the frames per second", 0.0, 1000.0)
        check_frames(seconds, fps)
        self.seconds, self.fps = seconds, fps
        if not 0.0 <= float(smoothness) <= 1.0:
            raise BoostNerfError(f"the smoothness is {smoothness!r}: from 0 (straight) to 1 (smooth)")
        self.smoothness, self.cycle = float(smoothness), bool(cycle)
        if not (1 <= int(width) <= MAX_SIDE and 1 <= int(height) <= MAX_SIDE):
            raise BoostNerfError(f"the frame size is {width} x {height}: 1 to {MAX_SIDE} pixels a side")
        self.width, self.height = int(width), int(height)

    def summary(self) -> str:
        """The path in one line: its keyframes (field of view, time) and frames."""
        n = len(self.keyframes)
        if not n:
            return "no keyframes yet: add one from the page's view"
        keys = ", ".join(f"{i}: {k.fov:.1f} deg at {t:.2f} s" for i, (k, t) in enumerate(zip(self.keyframes,
                                                                                         self.key_times())))
        return (f"{n} keyframe{'s' if n != 1 else ''} ({keys}); {len(self.frame_times())} frames of "
                f"{self.width}x{self.height} px at {self.fps:g} fps" + (", looping" if self.cycle else ""))

    # --- the path through the keyframes -------------------------------------------------------------------------------
    @property
    def segments(self) -> int:
        """The stretches between keyframes: one fewer than the keyframes, as many with `cycle`."""
        n = len(self.keyframes)
        return n if self.cycle and n > 1 else max(0, n - 1)

    def key_times(self) -> np.ndarray:
        """The time (seconds) the path passes each keyframe."""
        return np.arange(len(self.keyframes)) * (self.seconds / max(1, self.segments))

    def frame_times(self) -> np.ndarray:
        """The times of a video's frames, one every 1 / fps seconds (the step rounded so that `seconds` holds a whole
        number of them, n = round(fps x seconds), 1 at least): n + 1 frames from 0 to `seconds`, both ends, or with
        `cycle` n, stopping one short of the end, where the path starts again. A keyframe whose time is a multiple of
        the step is a frame."""
        count = max(1, round(self.fps * self.seconds))
        return np.arange(count if self.cycle else count + 1) * (self.seconds / count)

    def at(self, t: float) -> PathFrame:
        """The pose and field of view at time `t` (seconds, clipped to the path's)."""
        n = len(self.keyframes)
        if n == 0:
            raise BoostNerfError("the camera path has no keyframes: add one")
        if n == 1:
            return PathFrame(self.keyframes[0].pose.copy(), self.keyframes[0].fov)
        x = min(max(t / self.seconds, 0.0), 1.0) * self.segments
        k = min(int(math.floor(x)), self.segments - 1)
        u, a, b = x - k, k, (k + 1) % n
        positions = [kf.pose[:3, 3] for kf in self.keyframes]
        fovs = [kf.fov for kf in self.keyframes]
        position = hermite(positions[a], positions[b], self.tangent(positions, a), self.tangent(positions, b), u)
        fov = hermite(fovs[a], fovs[b], self.tangent(fovs, a), self.tangent(fovs, b), u)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = matrix_of(self.rotation(a, b, u)), position
        return PathFrame(pose, float(np.clip(fov, min(fovs), max(fovs))))

    def frames(self) -> list[PathFrame]:
        """The video's frames (`frame_times`)."""
        return [self.at(float(t)) for t in self.frame_times()]

    def neighbours(self, values: list, i: int) -> tuple:
        """The values before and after keyframe i's: around the loop with `cycle`, else mirrored at the ends."""
        n = len(values)
        if self.cycle:
            return values[(i - 1) % n], values[(i + 1) % n]
        before = values[i - 1] if i > 0 else 2 * values[0] - values[1]
        after = values[i + 1] if i < n - 1 else 2 * values[n - 1] - values[n - 2]
        return before, after

    def tangent(self, values: list, i: int):
        """The Kochanek-Bartels tangent (tension 1 - smoothness, no bias or continuity) at keyframe i of `values`."""
        before, after = self.neighbours(values, i)
        return 0.5 * self.smoothness * (after - before)

    def rotation_tangent(self, i: int) -> np.ndarray:
        """The rotations' tangent at keyframe i, in its own frame (half-angle axis units): `tangent` of the logs of
        the rotations to its neighbours (mirrored at the ends of a path that does not close)."""
        q = [quat_of(kf.pose[:3, :3]) for kf in self.keyframes]
        n = len(q)
        back = qlog(qmul(qinv(q[i]), q[(i - 1) % n])) if self.cycle or i > 0 else None
        ahead = qlog(qmul(qinv(q[i]), q[(i + 1) % n])) if self.cycle or i < n - 1 else None
        back = -ahead if back is None else back
        ahead = -back if ahead is None else ahead
        return 0.5 * self.smoothness * (ahead - back)

    def rotation(self, a: int, b: int, u: float) -> np.ndarray:
        """The rotation a fraction u from keyframe a to keyframe b: the spherical Bezier curve whose inner control
        points lie a third of each end's tangent along it."""
        qa, qb = quat_of(self.keyframes[a].pose[:3, :3]), quat_of(self.keyframes[b].pose[:3, :3])
        qb = qb if qa @ qb >= 0 else -qb
        controls = [qa, qmul(qa, qexp(self.rotation_tangent(a) / 3)), qmul(qb, qexp(-self.rotation_tangent(b) / 3)), qb]
        while len(controls) > 1:
            controls = [slerp(p, r, u) for p, r in zip(controls, controls[1:])]
        return controls[0]


def check_frames(seconds: float, fps: float) -> None:
    """One line when `seconds` at `fps` are more than `MAX_FRAMES` frames."""
    if round(fps * seconds) > MAX_FRAMES:
        raise BoostNerfError(f"{seconds:g} seconds at {fps:g} frames per second are {round(fps * seconds):,} frames: "
                             f"at most {MAX_FRAMES:,}; shorten the path or lower the frames per second")


def check_fov(fov: float, what: str) -> float:
    """A vertical field of view in degrees, refused in one line unless finite and strictly between 0 and 180."""
    if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not 0.0 < float(fov) < 180.0:
        raise BoostNerfError(f"{what} is {fov!r}: a vertical field of view in degrees, between 0 and 180")
    return float(fov)


def path_cameras(frames: list[PathFrame], height: int, width: int) -> list[Camera]:
    """The frames as cameras `height` x `width` pixels: pinhole, square pixels, the principal point at the centre,
    the focal length that gives each its vertical field of view (nerfstudio's)."""
    return [Camera(torch.tensor(f.pose, dtype=torch.float32),
                   torch.tensor(Intrinsics.from_fov(math.radians(f.fov), height, width).row(), dtype=torch.float32),
                   height, width) for f in frames]


def through_views(poses: torch.Tensor, intrinsics: torch.Tensor, height: int, width: int,
                  views: list[int]) -> CameraPath:
    """A path with a keyframe at each of `views` of a split (its `poses`, `intrinsics`, image size), in that order: the
    user's own photos' viewpoints, each with its field of view; frames of the split's size."""
    if not views:
        raise BoostNerfError("a camera path through views needs at least one view: give --views, e.g. 0,4,8")
    path = CameraPath(width=width, height=height)
    for i in views:
        if not 0 <= i < len(poses):
            raise BoostNerfError(f"there is no view {i}: the split has views 0 to {len(poses) - 1}")
        cam = Camera(poses[i], intrinsics[i], height, width)
        path.add(Keyframe.of_camera(cam))
    return path


# --- the file ---------------------------------------------------------------------------------------------------------
def flat(matrix: np.ndarray) -> list[float]:
    """A 4x4 matrix as nerfstudio writes one: 16 numbers, row by row."""
    return [float(v) for v in np.asarray(matrix, dtype=np.float64).reshape(16)]


def path_json(path: CameraPath, frame: DataFrame) -> dict:
    """`path` as a nerfstudio camera-path file: its keyframes and its sampled frames (`CameraPath.frames`), the poses
    taken from the scene's world to the data's frame (`cameras.DataFrame.poses_to_data`)."""
    if not path.keyframes:
        raise BoostNerfError("the camera path has no keyframes: add one (the panel's \"add keyframe\") first")
    aspect = path.width / path.height

    def data(pose: np.ndarray) -> list[float]:
        return flat(frame.poses_to_data(pose))

    keyframes = [{"matrix": data(k.pose), "fov": k.fov, "aspect": aspect, "override_transition_enabled": False,
                  "override_transition_sec": None} for k in path.keyframes]
    frames = [{"camera_to_world": data(f.pose), "fov": f.fov, "aspect": aspect} for f in path.frames()]
    return {"keyframes": keyframes, "camera_type": "perspective", "render_height": path.height,
            "render_width": path.width, "camera_path": frames, "fps": path.fps, "seconds": path.seconds,
            "smoothness_value": 1.0 - path.smoothness, "is_cycle": path.cycle, "default_fov": path.keyframes[0].fov,
            "default_transition_sec": path.seconds / max(1, path.segments)}


def write_camera_path(file: Path, path: CameraPath, frame: DataFrame) -> Path:
    """Write `path` to `file` (`path_json`), atomically -> `file`."""
    write_json(file, path_json(path, frame))
    return file


@dataclass
class PathFile:
    """A camera-path file read: its keyframes and settings (`path`, in the scene's world) and the frames to render
    (its "camera_path" entries, or `path`'s frames when it has none)."""

    path: CameraPath
    frames: list[PathFrame]


def number(value, what: str, low: float = 0.0, high: float = math.inf) -> float:
    """A JSON number strictly between `low` and `high`, else one line."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low < float(value) < high:
        bound = f"between {low:g} and {high:g}" if math.isfinite(high) else f"a finite number above {low:g}"
        raise BoostNerfError(f"{what} is {value!r}: it must be {bound}")
    return float(value)


def rigid(value, what: str) -> np.ndarray:
    """A 4x4 camera-to-world matrix from 16 numbers (row by row, or 4 rows of 4) -> float64 (4, 4), its rotation's
    uniform scale divided out; one line for anything else (module docstring)."""
    rows = value if isinstance(value, list) and value and all(isinstance(r, list) for r in value) else [value]
    numbers = [v for r in rows if isinstance(r, list) for v in r]
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers) or len(numbers) != 16:
        raise BoostNerfError(f"{what} must be 16 numbers (a 4x4 matrix row by row), not {str(value)[:80]}")
    m = np.array(numbers, dtype=np.float64).reshape(4, 4)
    if not np.isfinite(m).all():
        raise BoostNerfError(f"{what} has a NaN or infinite value: fix or remove the entry")
    if not np.allclose(m[3], [0, 0, 0, 1], rtol=0, atol=1e-6):
        raise BoostNerfError(f"{what}'s bottom row is {' '.join(f'{v:g}' for v in m[3])}, not 0 0 0 1 (a camera-to-"
                             "world pose, not a projection): fix or remove the entry")
    r = m[:3, :3]
    s2 = float(np.trace(r.T @ r)) / 3.0
    off = float(np.abs(r.T @ r / s2 - np.eye(3)).max()) if s2 > 1e-12 else math.inf
    if off > RIGID or np.linalg.det(r) <= 0:
        why = "a reflection" if off <= RIGID else f"|R^T R / s^2 - I| = {off:.2g} > {RIGID:g}"
        raise BoostNerfError(f"{what} is not a rigid camera pose: its rotation is not orthonormal ({why}; a uniform "
                             "scale is allowed, a shear or a scale per axis is not): fix or remove the entry")
    m[:3, :3] = r / math.sqrt(s2)
    return m


def entries(data: dict, key: str) -> list:
    value = data.get(key, [])
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(e, dict) for e in value):
        raise BoostNerfError(f'"{key}" must be a list of objects, not {str(value)[:80]}')
    if len(value) > MAX_FRAMES:  # frames, as a path sampled from keyframes has at most (keyframes: fewer still)
        raise BoostNerfError(f'"{key}" has {len(value):,} entries: at most {MAX_FRAMES:,}; shorten the path')
    return value


def side(data: dict, key: str) -> int:
    """render_width or render_height: a whole number of pixels, 1 to `MAX_SIDE`."""
    if key not in data:
        raise BoostNerfError(f'it has no "{key}": give the frames\' size in pixels (render_width and render_height)')
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 1 <= value <= MAX_SIDE \
            or value != int(value):
        raise BoostNerfError(f'"{key}" is {value!r}: a whole number of pixels from 1 to {MAX_SIDE}')
    return int(value)


def settings(data: dict) -> CameraPath:
    """A file's top-level values: its size, camera type, duration, frames per second, loop and smoothness."""
    if "version" in data:
        raise BoostNerfError(f'it has "version" {data["version"]!r}: boostnerf reads nerfstudio\'s camera paths, '
                             "which have no version; remove the key if the file is one")
    kind = data.get("camera_type", "perspective")
    if str(kind).lower() not in CAMERA_TYPES:
        raise BoostNerfError(f'"camera_type" is {kind!r}: boostnerf renders {", ".join(CAMERA_TYPES)} cameras only')
    if data.get("crop") not in (None, {}):
        raise BoostNerfError('it has a "crop": boostnerf renders the whole scene; remove "crop" to render the path')
    width, height = side(data, "render_width"), side(data, "render_height")
    cycle = data.get("is_cycle", False)
    if not isinstance(cycle, bool):
        raise BoostNerfError(f'"is_cycle" is {cycle!r}: true or false')
    tension = data.get("smoothness_value")
    if tension is not None and (isinstance(tension, bool) or not isinstance(tension, (int, float))
                                or not 0.0 <= tension <= 1.0):
        raise BoostNerfError(f'"smoothness_value" is {tension!r}: a number from 0 (smooth) to 1 (straight)')
    seconds = number(data["seconds"], '"seconds"') if data.get("seconds") is not None else DEFAULT_SECONDS
    fps = number(data["fps"], '"fps"') if data.get("fps") is not None else None
    if fps is None:
        n = len(entries(data, "camera_path"))
        fps = n / seconds if n and data.get("seconds") is not None else 24.0  # ns-render's: frames over seconds
    return CameraPath([], seconds, fps, 1.0 - float(tension or 0.0), cycle, width, height)


def pose_and_fov(entry: dict, key: str, what: str, path: CameraPath, frame: DataFrame) -> tuple[np.ndarray, float]:
    """An entry's pose (key `key`, taken to the scene's world) and field of view; its aspect, when it gives one, must
    be the frames' (render_width / render_height)."""
    if key not in entry or "fov" not in entry:
        raise BoostNerfError(f'{what} needs "{key}" (16 numbers) and "fov" (vertical, degrees)')
    pose = frame.poses_to_world(rigid(entry[key], f"{what}.{key}"))
    fov = check_fov(entry["fov"], f"{what}.fov")
    if entry.get("aspect") is not None:
        aspect, frames = number(entry["aspect"], f"{what}.aspect"), path.width / path.height
        if abs(aspect / frames - 1.0) > ASPECT:
            raise BoostNerfError(f"{what}.aspect is {aspect:g}, not render_width / render_height = {frames:g}: "
                                 "boostnerf renders every frame at render_width x render_height with square pixels")
    return pose, fov


def read_camera_path(file: Path, frame: DataFrame) -> PathFile:
    """A camera-path file (nerfstudio's layout, written by any tool), its poses taken to the scene's world; one line
    naming the file and the entry for anything boostnerf cannot render as the file means it."""
    data = read_json(Path(file), "camera path", HAND_FIX)
    try:
        path = settings(data)
        for i, entry in enumerate(entries(data, "keyframes")):
            path.keyframes.append(Keyframe(*pose_and_fov(entry, "matrix", f"keyframes[{i}]", path, frame)))
        frames = [PathFrame(*pose_and_fov(entry, "camera_to_world", f"camera_path[{i}]", path, frame))
                  for i, entry in enumerate(entries(data, "camera_path"))]
        if not frames and not path.keyframes:
            raise BoostNerfError('it has no "camera_path" frames and no "keyframes": save a path from `boostnerf '
                                 "view`'s camera path panel (or nerfstudio's viewer)")
        if path.keyframes:
            check_frames(path.seconds, path.fps)  # the frames sampled from the keyframes (here or in the viewer)
    except BoostNerfError as e:  # what is wrong with one value: said with the file's name
        raise BoostNerfError(f"camera path {file}: {e}") from None
    return PathFile(path, frames or path.frames())


def camera_path_file(folder: Path, name: str) -> Path:
    """The file of the camera path called `name` in `folder` (name.json); one line for a name that is no plain
    file name."""
    stem = name.strip().removesuffix(".json")
    if not NAME.match(stem):
        raise BoostNerfError(f"{name!r} is no camera path name: use letters, digits, '-', '_' and '.'")
    return Path(folder) / f"{stem}.json"


def saved_paths(folder: Path) -> list[str]:
    """The names of the camera paths saved in `folder`, sorted."""
    return sorted(p.stem for p in Path(folder).glob("*.json")) if Path(folder).is_dir() else []
