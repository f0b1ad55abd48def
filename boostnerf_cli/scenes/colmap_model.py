"""COLMAP sparse models on disk: `cameras`, `images` and `points3D` in COLMAP's binary (`.bin`) or text (`.txt`)
form, read and written without COLMAP or pycolmap (the formats of colmap/src/colmap/scene/reconstruction_io.cc).

A model is kept as plain data: `Model` holds `ModelCamera`s (id -> model name, width, height, parameters; the models,
their ids and parameters are `cameras.MODELS`),
`ModelImage`s (id -> world-to-camera rotation as a quaternion w x y z and translation, OpenCV axes: x right,
y down, z forward; camera id; file name; 2-D keypoints with the id of their 3-D point, -1 for none) and the points
(id -> xyz, rgb, reprojection error, track of (image id, keypoint index)).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from boostnerf_cli.cameras import MODEL_IDS, MODELS
from boostnerf_cli.errors import BoostNerfError


@dataclass
class ModelCamera:
    model: str
    width: int
    height: int
    params: list[float]


@dataclass
class ModelImage:
    qvec: np.ndarray  # (4,) w, x, y, z: world-to-camera rotation
    tvec: np.ndarray  # (3,) world-to-camera translation
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K, 2) keypoints in pixels
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) 3-D point of each, -1: none

    def world_from_camera(self) -> np.ndarray:
        """(4, 4) camera-to-world in COLMAP's (OpenCV) camera axes."""
        w, x, y, z = self.qvec / np.linalg.norm(self.qvec)
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        out = np.eye(4)
        out[:3, :3] = rot.T
        out[:3, 3] = -rot.T @ self.tvec
        return out


@dataclass
class Model:
    cameras: dict[int, ModelCamera]
    images: dict[int, ModelImage]
    xyz: np.ndarray  # (P, 3)
    rgb: np.ndarray  # (P, 3) uint8
    error: np.ndarray  # (P,)
    point_ids: np.ndarray  # (P,) the points' ids
    tracks: list[np.ndarray]  # P arrays (L, 2): image id, keypoint index


def quaternion(rot: np.ndarray) -> np.ndarray:
    """A rotation matrix (3, 3) -> unit quaternion w, x, y, z (w >= 0)."""
    m = rot
    t = np.trace(m)
    if t > 0:
        s = 2 * np.sqrt(t + 1)
        q = np.array([s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = np.zeros(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    return q * (1 if q[0] >= 0 else -1) / np.linalg.norm(q)


def model_files(folder: Path) -> str:
    """"bin" or "txt" when `folder` holds cameras, images and points3D in that form (bin first), else ""."""
    for ext in ("bin", "txt"):
        if all((folder / f"{name}.{ext}").is_file() for name in ("cameras", "images", "points3D")):
            return ext
    return ""


# ----------------------------------------------------------------------------- reading


class _Bytes:
    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.at + size > len(self.data):
            raise BoostNerfError(f"{self.path} ends early (a truncated or damaged COLMAP model): export the model "
                                 "again")
        out = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return out

    def array(self, dtype, count: int, cols: int) -> np.ndarray:
        size = np.dtype(dtype).itemsize * count * cols
        if self.at + size > len(self.data):
            self.take(f"<{size}x")  # raises
        out = np.frombuffer(self.data, dtype=dtype, count=count * cols, offset=self.at).reshape(count, cols)
        self.at += size
        return out

    def name(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise BoostNerfError(f"{self.path} ends early (a truncated or damaged COLMAP model): export the model "
                                 "again")
        text = self.data[self.at:end].decode("utf-8", errors="replace")
        self.at = end + 1
        return text


def _cameras_bin(path: Path) -> dict[int, ModelCamera]:
    f, cameras = _Bytes(path), {}
    for _ in range(f.take("<Q")[0]):
        cid, model_id, width, height = f.take("<iiQQ")
        if model_id not in MODEL_IDS:
            raise BoostNerfError(f"{path}: camera {cid} has an unknown camera model id {model_id}: not a COLMAP model "
                                 "this reader knows; export it as text (colmap model_converter --output_type TXT)")
        m = MODEL_IDS[model_id]
        cameras[cid] = ModelCamera(m.name, int(width), int(height), list(f.take(f"<{len(m.params)}d")))
    return cameras


def _images_bin(path: Path) -> dict[int, ModelImage]:
    f, images = _Bytes(path), {}
    for _ in range(f.take("<Q")[0]):
        iid, *pose = f.take("<I7d")
        (camera_id,) = f.take("<I")
        name = f.name()
        (n,) = f.take("<Q")
        rows = f.array(np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]), n, 1)[:, 0]
        xys = np.stack([rows["x"], rows["y"]], -1) if n else np.zeros((0, 2))
        ids = rows["id"].astype(np.int64) if n else np.zeros(0, np.int64)
        ids[ids < 0] = -1  # COLMAP's "no point" is the largest uint64: -1 here
        images[iid] = ModelImage(np.array(pose[:4]), np.array(pose[4:]), int(camera_id), name, xys, ids)
    return images


def _points_bin(path: Path) -> tuple:
    f = _Bytes(path)
    count = f.take("<Q")[0]
    ids, xyz, rgb, error, tracks = [], [], [], [], []
    for _ in range(count):
        pid, x, y, z, r, g, b, err, length = f.take("<Q3d3BdQ")
        ids.append(pid)
        xyz.append((x, y, z))
        rgb.append((r, g, b))
        error.append(err)
        tracks.append(f.array(np.dtype("<i4"), length, 2).astype(np.int64))
    return ids, xyz, rgb, error, tracks


def _lines(path: Path) -> list[list[str]]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise BoostNerfError(f"cannot read {path}: {err}; export the model again") from None
    return [line.split() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def _cameras_txt(path: Path) -> dict[int, ModelCamera]:
    cameras = {}
    for row in _lines(path):
        cameras[int(row[0])] = ModelCamera(row[1].upper(), int(row[2]), int(row[3]), [float(v) for v in row[4:]])
    return cameras


def _images_txt(path: Path) -> dict[int, ModelImage]:
    """Two lines an image, as COLMAP reads them: the image line (comments and blank lines before it skipped), then
    its keypoints on the very next line, which is blank for an image with none."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise BoostNerfError(f"cannot read {path}: {err}; export the model again") from None
    images, i = {}, 0
    while i < len(lines):
        head = lines[i].split()
        i += 1
        if not head or head[0].startswith("#"):
            continue
        vals = np.array([float(v) for v in (lines[i].split() if i < len(lines) else [])]).reshape(-1, 3)
        i += 1
        images[int(head[0])] = ModelImage(np.array([float(v) for v in head[1:5]]),
                                          np.array([float(v) for v in head[5:8]]), int(head[8]), " ".join(head[9:]),
                                          vals[:, :2], vals[:, 2].astype(np.int64))
    return images


def _points_txt(path: Path) -> tuple:
    ids, xyz, rgb, error, tracks = [], [], [], [], []
    for row in _lines(path):
        ids.append(int(row[0]))
        xyz.append(tuple(float(v) for v in row[1:4]))
        rgb.append(tuple(int(v) for v in row[4:7]))
        error.append(float(row[7]))
        tracks.append(np.array([int(v) for v in row[8:]], dtype=np.int64).reshape(-1, 2))
    return ids, xyz, rgb, error, tracks


def read_model(folder: Path) -> Model:
    """The COLMAP model in `folder` (binary first, else text); every damaged file is refused in one line."""
    ext = model_files(folder)
    if not ext:
        raise BoostNerfError(f"{folder} holds no COLMAP model: expected cameras, images and points3D (.bin or .txt)")
    try:
        if ext == "bin":
            cameras, images = _cameras_bin(folder / "cameras.bin"), _images_bin(folder / "images.bin")
            ids, xyz, rgb, error, tracks = _points_bin(folder / "points3D.bin")
        else:
            cameras, images = _cameras_txt(folder / "cameras.txt"), _images_txt(folder / "images.txt")
            ids, xyz, rgb, error, tracks = _points_txt(folder / "points3D.txt")
    except (ValueError, IndexError, struct.error) as err:
        raise BoostNerfError(f"cannot parse the COLMAP model in {folder} ({err}): export it again") from None
    for image in images.values():
        if image.camera_id not in cameras:
            raise BoostNerfError(f"{folder}: image {image.name} names camera {image.camera_id}, which is not in "
                                 f"cameras.{ext}: export the model again")
    for cid, cam in cameras.items():
        expected = len(MODELS[cam.model].params) if cam.model in MODELS else len(cam.params)
        if len(cam.params) != expected:
            raise BoostNerfError(f"{folder}: camera {cid} ({cam.model}) has {len(cam.params)} parameters, expected "
                                 f"{expected}: export the model again")
    return Model(cameras, images, np.array(xyz, dtype=np.float64).reshape(-1, 3),
                 np.array(rgb, dtype=np.uint8).reshape(-1, 3), np.array(error, dtype=np.float64),
                 np.array(ids, dtype=np.int64), tracks)


# ----------------------------------------------------------------------------- writing


def write_model(model: Model, folder: Path, ext: str = "bin") -> None:
    """Write `model` into `folder` as COLMAP's binary (`bin`) or text (`txt`) files."""
    folder.mkdir(parents=True, exist_ok=True)
    if ext == "txt":
        _write_txt(model, folder)
        return
    cams = [struct.pack("<Q", len(model.cameras))]
    for cid, cam in model.cameras.items():
        cams.append(struct.pack(f"<iiQQ{len(cam.params)}d", cid, MODELS[cam.model].colmap_id, cam.width, cam.height,
                                *cam.params))
    (folder / "cameras.bin").write_bytes(b"".join(cams))
    imgs = [struct.pack("<Q", len(model.images))]
    for iid, im in model.images.items():
        imgs.append(struct.pack("<I7dI", iid, *im.qvec, *im.tvec, im.camera_id) + im.name.encode() + b"\0")
        imgs.append(struct.pack("<Q", len(im.xys)))
        rows = np.zeros(len(im.xys), dtype=np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]))
        if len(im.xys):
            rows["x"], rows["y"], rows["id"] = im.xys[:, 0], im.xys[:, 1], im.point_ids
        imgs.append(rows.tobytes())
    (folder / "images.bin").write_bytes(b"".join(imgs))
    pts = [struct.pack("<Q", len(model.xyz))]
    for pid, p, c, e, track in zip(model.point_ids, model.xyz, model.rgb, model.error, model.tracks):
        pts.append(struct.pack("<Q3d3BdQ", int(pid), *p, *(int(v) for v in c), float(e), len(track)))
        pts.append(np.asarray(track, dtype="<i4").tobytes())
    (folder / "points3D.bin").write_bytes(b"".join(pts))


def _write_txt(model: Model, folder: Path) -> None:
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    lines += [f"{cid} {c.model} {c.width} {c.height} " + " ".join(repr(float(v)) for v in c.params)
              for cid, c in model.cameras.items()]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for iid, im in model.images.items():
        lines.append(f"{iid} " + " ".join(repr(float(v)) for v in (*im.qvec, *im.tvec)) + f" {im.camera_id} {im.name}")
        lines.append(" ".join(f"{x!r} {y!r} {int(i)}" for (x, y), i in zip(im.xys.tolist(), im.point_ids)))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for pid, p, c, e, track in zip(model.point_ids, model.xyz, model.rgb, model.error, model.tracks):
        lines.append(f"{int(pid)} " + " ".join(repr(float(v)) for v in p) + " " + " ".join(str(int(v)) for v in c)
                     + f" {float(e)!r} " + " ".join(str(int(v)) for v in np.asarray(track).ravel()))
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
