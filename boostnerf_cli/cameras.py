"""What a camera is, once: the camera models boostnerf reads, a camera's intrinsics with its lens, the one axis flip
between the OpenGL and OpenCV conventions, the field of view, scaling, and the lens's distortion and its inverse.

- `MODELS`: COLMAP's camera models (name, COLMAP id, parameter names in COLMAP's order, fisheye or not, and the
  `Intrinsics` / `Lens` field each parameter sets). The COLMAP reader and writer, the COLMAP and transforms loaders,
  `boostnerf capture` and `make-scene` look models up here; a model whose parameters all map onto a field
  (`CameraModel.renders`) is rendered as it is, any other is refused in one line.
- `Lens`: the distortion of COLMAP's OPENCV family and nerfstudio: radial (1 + k1 r^2 + ... + k4 r^8) /
  (1 + d1 r^2 + d2 r^4 + d3 r^6) (the denominator is FULL_OPENCV's rational k4, k5, k6), tangential p1, p2, or, for a
  fisheye, the equidistant theta (1 + k1 theta^2 + ... + k4 theta^8). `distort` maps ideal (pinhole) normalized
  image coordinates to the recorded ones, `undistort` back (Newton's method with the analytic Jacobian).
- `Intrinsics`: fx, fy, cx, cy in pixels and the lens (None: a pinhole camera). A scene split keeps its views'
  intrinsics as one tensor of rows (`Intrinsics.row`, `rows`; the scene cache and the lineage digests store it):
  4 numbers for a pinhole camera, `WITH_LENS` with a lens, `WITH_RATIONAL` with FULL_OPENCV's rational terms;
  `Intrinsics.of` reads a row back, and only this module knows the row's layout past fx, fy, cx, cy.
- `GL_TO_CV`: poses are OpenGL camera-to-world matrices (the camera looks down -z, +y up; scenes/scene.py); COLMAP,
  OpenCV and a browser viewer's cameras look down +z with +y down. `flip_axes` turns one into the other (either way).
- `DataFrame`: the similarity between the frame of the data as the user gave it (a capture's COLMAP world, a
  transforms.json's own) and the scene's world, where boostnerf renders (the identity but for a forward-facing
  capture, which is rescaled and recentred on its average camera: `scene.extra["world_from_data"]`). Camera paths
  and exports cross it, so what goes out lines up with the user's files.

Pixel (u, v) has its centre at (u + 0.5, v + 0.5); v grows downwards; normalized image coordinates are OpenCV's
(x right, y down, z = 1).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError

# OpenGL (looks down -z, +y up) <-> OpenCV (looks down +z, +y down) camera axes: x stays, y and z flip (an involution)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def flip_axes(pose):
    """A camera-to-world pose (4, 4) (numpy or torch) in one convention -> the other: `pose @ GL_TO_CV`, in the
    pose's own type, dtype and device."""
    if isinstance(pose, Tensor):
        return pose @ torch.as_tensor(GL_TO_CV, dtype=pose.dtype, device=pose.device)
    return np.asarray(pose) @ GL_TO_CV


@dataclass(frozen=True)
class DataFrame:
    """`world_from_data`: the 4x4 similarity (a uniform scale, a rotation, a shift) from the data's own frame to the
    scene's world. Poses are OpenGL camera-to-world matrices in both frames, with orthonormal rotations."""

    world_from_data: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.world_from_data, dtype=np.float64)
        if t.shape != (4, 4) or not np.isfinite(t).all() or not np.allclose(t[3], [0, 0, 0, 1]):
            raise BoostNerfError(f"world_from_data must be a finite 4x4 similarity, got {t.tolist()}")
        object.__setattr__(self, "world_from_data", t)

    @classmethod
    def of(cls, extra: dict) -> "DataFrame":
        """The frame a scene records in its `extra` (the identity when it records none)."""
        return cls(np.asarray(extra.get("world_from_data", np.eye(4)), dtype=np.float64))

    @property
    def scale(self) -> float:
        """World units per data unit."""
        return float(abs(np.linalg.det(self.world_from_data[:3, :3])) ** (1 / 3))

    @property
    def identity(self) -> bool:
        return bool(np.allclose(self.world_from_data, np.eye(4), rtol=0, atol=1e-12))

    @staticmethod
    def _apply(t: np.ndarray, values, poses: bool):
        """`t` (4, 4) applied to points (..., 3) or, with `poses`, to camera-to-world poses (..., 4, 4), whose rotation
        stays orthonormal (divided by the scale); numpy or torch in, the same type and dtype out."""
        if isinstance(values, Tensor):
            out = DataFrame._apply(t, values.detach().cpu().double().numpy(), poses)
            return torch.from_numpy(out).to(values.device, values.dtype)
        x = np.asarray(values, dtype=np.float64)
        r, shift = t[:3, :3], t[:3, 3]
        if not poses:
            return x @ r.T + shift
        out = x.copy()
        out[..., :3, :3] = r @ x[..., :3, :3] / abs(np.linalg.det(r)) ** (1 / 3)
        out[..., :3, 3] = x[..., :3, 3] @ r.T + shift
        return out

    def points_to_world(self, xyz):
        """Points (..., 3) of the data's frame -> the scene's world (numpy or torch, in the input's dtype)."""
        return self._apply(self.world_from_data, xyz, False)

    def points_to_data(self, xyz):
        """Points (..., 3) of the scene's world -> the data's frame."""
        return self._apply(np.linalg.inv(self.world_from_data), xyz, False)

    def poses_to_world(self, poses):
        """Camera-to-world poses (..., 4, 4) of the data's frame -> the scene's world."""
        return self._apply(self.world_from_data, poses, True)

    def poses_to_data(self, poses):
        """Camera-to-world poses (..., 4, 4) of the scene's world -> the data's frame."""
        return self._apply(np.linalg.inv(self.world_from_data), poses, True)


# ----------------------------------------------------------------------------- the lens


@dataclass(frozen=True)
class Lens:
    """A lens's distortion (module docstring): radial k1..k4 over d1..d3, tangential p1, p2; or a fisheye's k1..k4
    (equidistant, no tangential terms)."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    d1: float = 0.0
    d2: float = 0.0
    d3: float = 0.0
    fisheye: bool = False

    def __post_init__(self) -> None:
        for f in COEFFICIENTS:
            object.__setattr__(self, f, float(getattr(self, f)))
        object.__setattr__(self, "fisheye", bool(self.fisheye))

    @property
    def bends(self) -> bool:
        """Whether the lens bends rays: a coefficient set, or a fisheye (whose angle mapping bends even without)."""
        return self.fisheye or any(getattr(self, f) for f in COEFFICIENTS)

    def coefficients(self) -> dict[str, float]:
        """The coefficients that are set, by name."""
        return {f: getattr(self, f) for f in COEFFICIENTS if getattr(self, f)}

    def distort(self, xy: Tensor) -> Tensor:
        """Ideal normalized image coordinates (..., 2) -> the distorted ones the camera records (COLMAP's
        `Distortion`, nerfstudio's)."""
        x, y = xy.unbind(-1)
        r2 = x * x + y * y
        if self.fisheye:
            r = r2.sqrt()
            theta = torch.atan(r)
            scale = torch.where(r > 1e-12, self._theta_d(theta) / r.clamp_min(1e-12), torch.ones_like(r))
            return xy * scale[..., None]
        radial = self._radial(r2)
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return torch.stack([xd, yd], dim=-1)

    def undistort(self, xy_d: Tensor, iterations: int = 40) -> Tensor:
        """The inverse of `distort`: distorted normalized coordinates (..., 2) -> ideal ones, in float64, by Newton's
        method on distort(xy) - xy_d with the analytic Jacobian, started at the distorted point (a fisheye solves its
        angle in one dimension). Converges to ~1e-12 within a few steps for the lenses of phones and action cameras;
        convergence is read every `CHECK_EVERY` steps, not every step (each read waits for the device)."""
        target = xy_d.double()
        if self.fisheye:
            theta_d = target.norm(dim=-1)
            theta = theta_d.clone()
            for _ in range(iterations):
                df = self._theta_d_derivative(theta)
                f = self._theta_d(theta) - theta_d
                theta = (theta - f / torch.where(df.abs() > 1e-12, df, torch.full_like(df, 1e-12))).clamp(0, 1.55)
            scale = torch.where(theta_d > 1e-12, torch.tan(theta) / theta_d.clamp_min(1e-12), torch.ones_like(theta))
            return target * scale[..., None]
        xy = target.clone()
        for i in range(iterations):
            f = self.distort(xy) - target
            (a, b), (c, d) = self.jacobian(xy)  # [[dxd/dx, dxd/dy], [dyd/dx, dyd/dy]]
            det = a * d - b * c
            det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
            xy = xy - torch.stack([(d * f[..., 0] - b * f[..., 1]) / det, (a * f[..., 1] - c * f[..., 0]) / det], -1)
            if (i + 1) % CHECK_EVERY == 0 and float(f.abs().max()) < 1e-12:
                break
        return xy

    def jacobian(self, xy: Tensor) -> tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor]]:
        """d distort / d xy of a (non-fisheye) lens at xy (..., 2): ((dxd/dx, dxd/dy), (dyd/dx, dyd/dy))."""
        x, y = xy.unbind(-1)
        r2 = x * x + y * y
        radial = self._radial(r2)
        num = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))
        den = 1 + r2 * (self.d1 + r2 * (self.d2 + r2 * self.d3))
        dnum = self.k1 + r2 * (2 * self.k2 + r2 * (3 * self.k3 + r2 * 4 * self.k4))
        dden = self.d1 + r2 * (2 * self.d2 + r2 * 3 * self.d3)
        dradial = (dnum * den - num * dden) / (den * den)  # d radial / d r^2
        xy2 = 2 * x * y * dradial
        return ((radial + 2 * x * x * dradial + 2 * self.p1 * y + 6 * self.p2 * x,
                 xy2 + 2 * self.p1 * x + 2 * self.p2 * y),
                (xy2 + 2 * self.p1 * x + 2 * self.p2 * y,
                 radial + 2 * y * y * dradial + 6 * self.p1 * y + 2 * self.p2 * x))

    def _radial(self, r2: Tensor) -> Tensor:
        num = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))
        if not (self.d1 or self.d2 or self.d3):
            return num
        return num / (1 + r2 * (self.d1 + r2 * (self.d2 + r2 * self.d3)))

    def _theta_d(self, theta: Tensor) -> Tensor:
        t2 = theta * theta
        return theta * (1 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def _theta_d_derivative(self, theta: Tensor) -> Tensor:
        t2 = theta * theta
        return 1 + t2 * (3 * self.k1 + t2 * (5 * self.k2 + t2 * (7 * self.k3 + t2 * 9 * self.k4)))


COEFFICIENTS = ("k1", "k2", "k3", "k4", "p1", "p2", "d1", "d2", "d3")  # a `Lens`'s numbers
RATIONAL = ("d1", "d2", "d3")  # FULL_OPENCV's denominator: a row holds them only when a camera of its split has one
CHECK_EVERY = 8  # Newton steps of `Lens.undistort` between two reads of its residual


# ----------------------------------------------------------------------------- intrinsics

# A split's row of intrinsics: fx, fy, cx, cy (`PINHOLE`); with a lens then k1 k2 k3 k4 p1 p2 and 1 for a fisheye, else
# 0 (`WITH_LENS`, the layout of the scene caches and workspace digests made before FULL_OPENCV was read); with a
# rational lens then d1 d2 d3 (`WITH_RATIONAL`)
PINHOLE = 4
WITH_LENS = PINHOLE + len(COEFFICIENTS) - len(RATIONAL) + 1
WITH_RATIONAL = WITH_LENS + len(RATIONAL)


@dataclass(frozen=True)
class Intrinsics:
    """A camera's focal lengths and principal point in pixels, and its lens (None: a pinhole camera)."""

    fx: float
    fy: float
    cx: float
    cy: float
    lens: Lens | None = None

    def __post_init__(self) -> None:
        for f in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, f, float(getattr(self, f)))
        if self.lens is not None and not self.lens.bends:
            object.__setattr__(self, "lens", None)

    @classmethod
    def of(cls, value: "Intrinsics | Tensor | Sequence[float]") -> "Intrinsics":
        """Intrinsics from a row (`row`: `PINHOLE`, `WITH_LENS` or `WITH_RATIONAL` numbers), or the intrinsics
        themselves."""
        if isinstance(value, Intrinsics):
            return value
        values = [float(v) for v in (value.tolist() if isinstance(value, Tensor) else value)]
        if len(values) == PINHOLE:
            return cls(*values)
        if len(values) not in (WITH_LENS, WITH_RATIONAL):
            raise BoostNerfError(f"an intrinsics row has {PINHOLE} numbers (fx, fy, cx, cy), {WITH_LENS} (then k1 k2 "
                                 f"k3 k4 p1 p2 fisheye) or {WITH_RATIONAL} (then d1 d2 d3), not {len(values)}")
        polynomial = values[PINHOLE : WITH_LENS - 1]
        lens = Lens(*polynomial, *values[WITH_LENS:], fisheye=values[WITH_LENS - 1] != 0)
        return cls(*values[:PINHOLE], lens)

    def row(self, width: int | None = None) -> list[float]:
        """The row a split keeps (`PINHOLE`, `WITH_LENS` or `WITH_RATIONAL` numbers, see there): the shortest that
        holds this camera, or `width` (a split's: its pinhole cameras' lens part zero)."""
        lens = self.lens or Lens()
        width = width or (PINHOLE if self.lens is None else WITH_RATIONAL if self.rational else WITH_LENS)
        row = [self.fx, self.fy, self.cx, self.cy]
        row += [*(getattr(lens, f) for f in COEFFICIENTS if f not in RATIONAL), 1.0 if lens.fisheye else 0.0]
        row += [getattr(lens, f) for f in RATIONAL]
        if any(row[width:]):
            raise BoostNerfError(f"a row of {width} numbers cannot hold this camera's lens")
        return row[:width]

    @property
    def rational(self) -> bool:
        return self.lens is not None and any(getattr(self.lens, f) for f in RATIONAL)

    def scaled(self, sx: float, sy: float | None = None) -> "Intrinsics":
        """The same camera for an image scaled by sx across and sy down (default sx): the focal lengths and principal
        point scale; the lens acts on normalized coordinates, the same at any size."""
        sy = sx if sy is None else sy
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy)

    def resized(self, height: int, width: int, new_height: int, new_width: int) -> "Intrinsics":
        """The same camera rendering new_height x new_width pixels instead of height x width (a width rounded to keep
        the aspect): the focal lengths scale with the height, so pixels stay square, the principal point with each
        side."""
        s = new_height / height
        return replace(self, fx=self.fx * s, fy=self.fy * s, cx=self.cx * (new_width / width), cy=self.cy * s)

    def fov_y(self, height: int) -> float:
        """The vertical field of view in radians of an image `height` pixels high (the pinhole's: a lens's bend at
        the border is left out)."""
        return 2.0 * math.atan(0.5 * height / self.fy)

    @classmethod
    def from_fov(cls, fov_y: float, height: int, width: int) -> "Intrinsics":
        """A pinhole camera with square pixels, vertical field of view `fov_y` (radians), principal point at the
        image's centre."""
        focal = focal_for_fov(fov_y, height)
        return cls(focal, focal, width / 2.0, height / 2.0)

    def normalized(self, uv: Tensor) -> Tensor:
        """Pixel positions (..., 2) (u, v) -> ideal normalized image coordinates (..., 2) (through the lens's inverse
        when it has one), float64."""
        uv = uv.double()
        xy = torch.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], dim=-1)
        return xy if self.lens is None else self.lens.undistort(xy)

    def pixels(self, xy: Tensor) -> Tensor:
        """Ideal normalized image coordinates (..., 2) -> pixel positions (..., 2), through the lens when it has one
        (computed in float64, returned in xy's dtype)."""
        if self.lens is not None:
            xy = self.lens.distort(xy.double()).to(xy.dtype)
        return torch.stack([self.fx * xy[..., 0] + self.cx, self.fy * xy[..., 1] + self.cy], dim=-1)

    # --- COLMAP's parameters
    @classmethod
    def from_colmap(cls, model: str, params: Sequence[float], source: str) -> "Intrinsics":
        """The intrinsics of a COLMAP camera (`MODELS[model]`, `params` in its order); one line for a model boostnerf
        does not render."""
        m = camera_model(model, source)
        if not m.renders:
            raise BoostNerfError(f"{source}: camera model {m.name} is not supported; boostnerf reads "
                                 f"{', '.join(rendered_models())}: undistort the images (colmap image_undistorter) and "
                                 "load the undistorted model")
        values: dict[str, float] = {}
        for name, value in zip(m.fields, params):
            for f in ("fx", "fy") if name == "f" else (name,):
                values[f] = float(value)
        lens = Lens(**{f: values[f] for f in COEFFICIENTS if f in values}, fisheye=m.fisheye)
        return cls(values["fx"], values["fy"], values["cx"], values["cy"], lens)

    def colmap(self, model: str) -> list[float]:
        """These intrinsics as the parameters of COLMAP's `model`, in its order; one line when the model cannot hold
        them (another lens, fx != fy for a single focal length)."""
        m = camera_model(model, "intrinsics")
        lens = self.lens or Lens(fisheye=m.fisheye)
        values = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "f": self.fx,
                  **{f: getattr(lens, f) for f in COEFFICIENTS}}
        held = set(m.fields) | ({"fx", "fy"} if "f" in m.fields else set())
        lost = [f for f in ("fy", *COEFFICIENTS) if f not in held and values[f] != (self.fx if f == "fy" else 0.0)]
        if not m.renders or lost or lens.fisheye != m.fisheye:
            raise BoostNerfError(f"COLMAP's {m.name} cannot hold these intrinsics ({', '.join(lost) or 'the lens'})")
        return [values[f] for f in m.fields]


def focal_for_fov(fov: float, size: float) -> float:
    """The focal length in pixels that sees `fov` radians across `size` pixels."""
    return 0.5 * size / math.tan(0.5 * fov)


def rows(cameras: Sequence[Intrinsics]) -> Tensor:
    """The split's intrinsics tensor, float32: (N, `PINHOLE`) when no camera has a lens, else (N, `WITH_LENS`), or
    (N, `WITH_RATIONAL`) when one has FULL_OPENCV's rational terms (the numbers a camera has not: zero)."""
    width = max(len(c.row()) for c in cameras)
    return torch.tensor([c.row(width) for c in cameras], dtype=torch.float32)


ROW_WIDTHS = (PINHOLE, WITH_LENS, WITH_RATIONAL)


# ----------------------------------------------------------------------------- camera models


@dataclass(frozen=True)
class CameraModel:
    """One of COLMAP's camera models: its name, its id in COLMAP's binary files, its parameters' names in COLMAP's
    order, whether it is a fisheye, and the `Intrinsics` / `Lens` field each parameter sets (None: no field holds
    it; "f": fx and fy)."""

    name: str
    colmap_id: int
    params: tuple[str, ...]
    fisheye: bool
    fields: tuple[str | None, ...]

    @property
    def renders(self) -> bool:
        """Whether boostnerf renders the model as it is: every parameter has a field."""
        return None not in self.fields


def _model(name: str, colmap_id: int, params: str, fisheye: bool = False, **renamed: str | None) -> CameraModel:
    names = tuple(params.split())
    return CameraModel(name, colmap_id, names, fisheye, tuple(renamed.get(n, n) for n in names))


# COLMAP's camera models (colmap/src/colmap/sensor/models.h), by id; SIMPLE_RADIAL's k is k1, FULL_OPENCV's rational
# k4 k5 k6 are the lens's denominator d1 d2 d3
MODELS = {m.name: m for m in (
    _model("SIMPLE_PINHOLE", 0, "f cx cy"),
    _model("PINHOLE", 1, "fx fy cx cy"),
    _model("SIMPLE_RADIAL", 2, "f cx cy k", k="k1"),
    _model("RADIAL", 3, "f cx cy k1 k2"),
    _model("OPENCV", 4, "fx fy cx cy k1 k2 p1 p2"),
    _model("OPENCV_FISHEYE", 5, "fx fy cx cy k1 k2 k3 k4", True),
    _model("FULL_OPENCV", 6, "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6", k4="d1", k5="d2", k6="d3"),
    _model("FOV", 7, "fx fy cx cy omega", omega=None),
    _model("SIMPLE_RADIAL_FISHEYE", 8, "f cx cy k", True, k="k1"),
    _model("RADIAL_FISHEYE", 9, "f cx cy k1 k2", True),
    _model("THIN_PRISM_FISHEYE", 10, "fx fy cx cy k1 k2 p1 p2 k3 k4 sx1 sy1", True, p1=None, p2=None, sx1=None,
           sy1=None),
    _model("RAD_TAN_THIN_PRISM_FISHEYE", 11, "fx fy cx cy k0 k1 k2 k3 k4 k5 p0 p1 s0 s1 s2 s3", True,
           **{n: None for n in "k0 k1 k2 k3 k4 k5 p0 p1 s0 s1 s2 s3".split()}),
)}
MODEL_IDS = {m.colmap_id: m for m in MODELS.values()}


def camera_model(name: str, source: str) -> CameraModel:
    """The model called `name` (any case); one line naming `source` for a name COLMAP does not know."""
    m = MODELS.get(str(name).upper())
    if m is None:
        raise BoostNerfError(f"{source}: unknown camera model {name}: COLMAP's are {', '.join(MODELS)}")
    return m


def rendered_models() -> tuple[str, ...]:
    """The names of the models boostnerf renders as they are, in COLMAP's order."""
    return tuple(m.name for m in MODELS.values() if m.renders)


# ----------------------------------------------------------------------------- pixels and rays


class _Grids:
    """Undistorted pixel grids, by camera and size, within a byte budget (least recently used out first): a split
    whose every image has its own camera keeps all of them while they fit, instead of recomputing each grid's Newton
    steps on every pass over the views."""

    def __init__(self, budget: int) -> None:
        self.budget = budget
        self.grids: OrderedDict[tuple, Tensor] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, height: int, width: int, camera: Intrinsics) -> Tensor:
        key = (height, width, camera)
        with self.lock:
            if key in self.grids:
                self.grids.move_to_end(key)
                return self.grids[key]
        v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                              torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
        grid = camera.normalized(torch.stack([u, v], dim=-1)).float()
        with self.lock:
            self.grids[key] = grid
            while sum(g.numel() * g.element_size() for g in self.grids.values()) > self.budget and len(self.grids) > 1:
                self.grids.popitem(last=False)
        return grid


GRIDS = _Grids(1 << 30)  # 1 GiB: e.g. 300 cameras of 1,000 x 750 pixels


def ideal_grid(height: int, width: int, camera: Intrinsics) -> Tensor:
    """(H, W, 2) float32 ideal normalized coordinates of every pixel centre of `camera` (through its lens's inverse):
    computed once per camera and size (`GRIDS`), then reused."""
    return GRIDS.get(height, width, camera)
