"""The one scene type every loader produces and every stage consumes.

Conventions (the same for every dataset format):
- poses are camera-to-world 4x4 matrices in the OpenGL / Blender convention: the camera looks
  down its -z axis, +y is up in the image, +x is right;
- intrinsics are per view, `(fx, fy, cx, cy)` in pixels of the stored (possibly downscaled)
  images, with pixel centres at integer + 0.5; a camera with lens distortion adds its lens (the row of
  `cameras.Intrinsics.row`; read one with `Split.camera`), and its rays go through the inverse distortion;
- images are float32 RGB in [0, 1], already composited on `background` when they had alpha; a split keeps
  that alpha (`Split.alpha`) so that training can composite a pixel on another colour (`train.random_background`);
- `bbox`, `near` and `far` are where the renderer samples. For forward-facing scenes (`ndc` set,
  LLFF) they are in normalized device coordinates: every camera ray is warped by `ndc` first
  (render/rays.py `NDC`), while `poses` stay world cameras. For unbounded scenes (`contraction` set) `bbox` is the
  box of the contracted world and `far` the contraction's far bound (render/contraction.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from boostnerf_cli.cameras import ROW_WIDTHS, Intrinsics
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.contraction import Contraction
from boostnerf_cli.render.rays import NDC
from boostnerf_cli.render.renderer import COLOR_THRESHOLD, RenderSettings


@dataclass(frozen=True)
class Split:
    """One split of a scene: N views of the same size."""

    images: Tensor  # (N, H, W, 3) float32 in [0, 1]
    poses: Tensor  # (N, 4, 4) float32 camera-to-world
    # (N, 4) float32: fx, fy, cx, cy in pixels; (N, 11) with a lens, (N, 14) a rational one (cameras.Intrinsics.row)
    intrinsics: Tensor
    names: tuple[str, ...]
    alpha: Tensor | None = None  # (N, H, W) float32 in [0, 1], the images' coverage; None: every pixel opaque

    def __post_init__(self) -> None:
        n = self.images.shape[0]
        if self.images.ndim != 4 or self.images.shape[-1] != 3:
            raise BoostNerfError(f"split images must be (N, H, W, 3), got {tuple(self.images.shape)}")
        if self.poses.shape != (n, 4, 4):
            raise BoostNerfError(f"expected {n} poses of shape 4x4, got {tuple(self.poses.shape)}")
        if self.intrinsics.ndim != 2 or self.intrinsics.shape[0] != n or self.intrinsics.shape[1] not in ROW_WIDTHS:
            raise BoostNerfError(f"expected {n} intrinsics rows (cameras.Intrinsics.row: fx, fy, cx, cy, then "
                                 f"optionally the lens), got {tuple(self.intrinsics.shape)}")
        if self.alpha is not None and self.alpha.shape != self.images.shape[:3]:
            raise BoostNerfError(f"split alpha must be (N, H, W) = {tuple(self.images.shape[:3])}, "
                                 f"got {tuple(self.alpha.shape)}")
        if len(self.names) != n:
            raise BoostNerfError(f"expected {n} view names, got {len(self.names)}")
        if not torch.isfinite(self.poses).all():
            raise BoostNerfError("camera poses contain NaN or infinite values: fix the dataset's pose file")
        bad = ~torch.isfinite(self.intrinsics).all(-1) | (self.intrinsics[:, :2] <= 0).any(-1)
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            values = ", ".join(f"{float(v):g}" for v in self.intrinsics[i])
            raise BoostNerfError(f"camera intrinsics of view {self.names[i]} are fx, fy, cx, cy = {values}: "
                                 "focal lengths must be positive and every value finite; fix the dataset's camera file")

    def __len__(self) -> int:
        return self.images.shape[0]

    def camera(self, i: int) -> Intrinsics:
        """View `i`'s intrinsics and lens."""
        return Intrinsics.of(self.intrinsics[i])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def stems(self) -> tuple[str, ...]:
        """File stems for the views' outputs (renders): each name's last path part, or, where two views share it
        (one folder per camera: `cam0/0000`, `cam1/0000`), the shortest suffix of parts that tells every view
        apart, joined by `_` (`cam0_0000`). Views whose whole names repeat get `_2`, `_3`, ..."""
        parts = [tuple(p for p in n.replace("\\", "/").split("/") if p not in ("", ".")) or ("view",)
                 for n in self.names]
        for k in range(1, max(len(p) for p in parts) + 1):
            stems = ["_".join(p[-k:]) for p in parts]
            if len(set(stems)) == len(stems):
                return tuple(stems)
        seen: dict[str, int] = {}
        out = []
        for s in stems:
            seen[s] = seen.get(s, 0) + 1
            out.append(s if seen[s] == 1 else f"{s}_{seen[s]}")
        return tuple(out)

    def subset(self, index: list[int]) -> "Split":
        idx = torch.as_tensor(index, dtype=torch.long)
        return Split(self.images[idx], self.poses[idx], self.intrinsics[idx], tuple(self.names[i] for i in index),
                     None if self.alpha is None else self.alpha[idx])


@dataclass(frozen=True)
class SparsePoints:
    """The 3-D points a structure-from-motion model found (COLMAP's points3D), in the scene's world (the cameras'
    frame, never NDC), and which views see each: `visible[split]` rows (view index in that split, point index)."""

    xyz: Tensor  # (P, 3) float32
    rgb: Tensor  # (P, 3) uint8
    error: Tensor  # (P,) float32: mean reprojection error in pixels of the model's images
    visible: dict[str, Tensor]  # split name -> (M, 2) int64

    def seen_by(self, split: str, view: int) -> Tensor:
        """Indices of the points view `view` of `split` sees."""
        rows = self.visible.get(split)
        return torch.zeros(0, dtype=torch.long) if rows is None else rows[rows[:, 0] == view, 1]


@dataclass(frozen=True)
class Scene:
    """A posed image collection with the bounds a renderer needs."""

    name: str
    splits: dict[str, Split]
    near: float
    far: float
    bbox: Tensor  # (2, 3): min corner, max corner, world units
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    source: str = ""
    format: str = ""
    holdout: str = ""  # how the held-out split was made, e.g. "every 8th train view"
    extra: dict = field(default_factory=dict)
    ndc: NDC | None = None  # forward-facing scenes: rays are sampled in these NDC (bbox/near/far too)
    points: SparsePoints | None = None  # a structure-from-motion model's points (COLMAP scenes), else None
    # unbounded scenes: samples are contracted into one ball (render/contraction.py); bbox is its box, far its bound
    contraction: Contraction | None = None

    def __post_init__(self) -> None:
        if "train" not in self.splits or len(self.splits["train"]) == 0:
            raise BoostNerfError(f"scene {self.name!r} has no training views")
        if not (0 <= self.near < self.far):
            raise BoostNerfError(f"scene {self.name!r}: need 0 <= near < far, got near={self.near} far={self.far}")
        if self.bbox.shape != (2, 3) or not bool((self.bbox[1] > self.bbox[0]).all()):
            raise BoostNerfError(f"scene {self.name!r}: bounding box must be (2, 3) with max > min")

    HELD_OUT = ("test", "val")  # the split called test: the dataset's test views, else its validation views

    def held_out(self) -> Split | None:
        """The held-out views (`split("test")`), or None for a scene that holds none out (one view, holdout_every 0)."""
        return self.split("test") if any(k in self.splits for k in self.HELD_OUT) else None

    def split(self, name: str) -> Split:
        """The named split; `test` falls back to `val` when a dataset has no test split."""
        for candidate in {"test": self.HELD_OUT}.get(name, (name,)):
            if candidate in self.splits:
                return self.splits[candidate]
        raise BoostNerfError(
            f"scene {self.name!r} has no {name!r} split (it has: {', '.join(sorted(self.splits))}): give one of "
            "those with --split"
        )

    def render_settings(self, step: float, bbox: Tensor, color_threshold: float = COLOR_THRESHOLD) -> RenderSettings:
        """How to render this scene with samples `step` apart inside `bbox` (a model's box): the scene's near,
        far, background and NDC warp; colour only where a sample's weight exceeds `color_threshold`. A ray takes as
        many samples as the box's diagonal holds at `step` (DVGO's N_samples), so no ray lengthens the step of the
        rays it is rendered with (a 384^3 expert at half-voxel steps needs ~1,330)."""
        samples = math.ceil(float((bbox[1] - bbox[0]).norm()) / step) + 1
        return RenderSettings(step=step, near=self.near, far=self.far, bbox=bbox, background=self.background,
                              color_threshold=color_threshold, max_samples=samples, ndc=self.ndc,
                              contraction=self.contraction)

    def describe(self) -> dict:
        """A JSON-able summary, recorded in the workspace manifest."""
        points = {} if self.points is None else {"points": len(self.points.xyz)}
        return {
            "name": self.name,
            "source": self.source,
            "format": self.format,
            "holdout": self.holdout,
            "near": self.near,
            "far": self.far,
            "bbox": self.bbox.tolist(),
            "background": list(self.background),
            "ndc": self.ndc.to_dict() if self.ndc is not None else None,
            **({"contraction": self.contraction.to_dict()} if self.contraction is not None else {}),
            "splits": {k: {"views": len(v), "height": v.height, "width": v.width} for k, v in self.splits.items()},
            **points,
        }
