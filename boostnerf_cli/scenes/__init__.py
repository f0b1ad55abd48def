"""Scene loading: every dataset format becomes one `Scene` (see `scene.py` for the conventions).

To add a format, write `load_<format>(path, image_size, holdout_every) -> Scene` and a detector
`is_<format>(path) -> str` (what it found, "" when the folder is not in that format), and add one
entry to `FORMATS`. "auto" tries the detectors in order; docs/datasets.md describes every format.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Callable

import torch

from boostnerf_cli.errors import BoostNerfError, BoxWarning, DataWarning
from boostnerf_cli.scenes.blender import is_blender, load_blender
from boostnerf_cli.scenes.bounds import box_gaps, box_near_far
from boostnerf_cli.scenes.cache import cached
from boostnerf_cli.scenes.colmap import is_colmap, load_colmap
from boostnerf_cli.scenes.kind import with_kind
from boostnerf_cli.scenes.llff import is_llff, load_llff
from boostnerf_cli.scenes.nerfstudio import is_nerfstudio, load_nerfstudio
from boostnerf_cli.scenes.nsvf import is_nsvf, is_tanks, load_nsvf, load_tanks
from boostnerf_cli.scenes.procedural import LAYOUTS, make_scene
from boostnerf_cli.scenes.scene import Scene, SparsePoints, Split
from boostnerf_cli.startup import timed

# name -> (detector, loader, what the detector looks for)
FORMATS: dict[str, tuple[Callable[[Path], str], Callable[..., Scene], str]] = {
    "blender": (is_blender, load_blender, "transforms_{train,val,test}.json"),
    "nsvf": (is_nsvf, load_nsvf, "rgb/ with RGBA 0_*.png and pose/ (plus intrinsics.txt)"),
    "tanks": (is_tanks, load_tanks, "rgb/ with RGB 0_*.png and pose/ (plus intrinsics.txt)"),
    "llff": (is_llff, load_llff, "poses_bounds.npy (plus images/ or images_N/)"),
    "colmap": (is_colmap, load_colmap, "sparse/0/{cameras,images,points3D}.{bin,txt} (plus images/ or images_N/)"),
    "nerfstudio": (is_nerfstudio, load_nerfstudio, "transforms.json"),
}


def detect_format(folder: Path) -> tuple[str, str]:
    """-> (format name, what was found) for the first detector that recognises `folder`."""
    for name, (detect, _, _) in FORMATS.items():
        found = detect(folder)
        if found:
            return name, found
    wanted = "; ".join(f"{name}: {what}" for name, (_, _, what) in FORMATS.items())
    raise BoostNerfError(f"cannot tell the dataset format of {folder}: looked for {wanted}")


def _off_centre(scene: Scene) -> str:
    """A warning when a view's principal point lies more than a quarter of the image from its centre: intrinsics of
    another image size (images downscaled after the cameras were written, without `w` / `h`), or "" ."""
    for name, split in scene.splits.items():
        centre = torch.tensor([split.width, split.height], dtype=torch.float32) / 2
        off = ((split.intrinsics[:, 2:4] - centre).abs() > centre / 2).any(-1)
        if bool(off.any()):
            i = int(off.nonzero()[0])
            cx, cy = (float(v) for v in split.intrinsics[i, 2:4])
            fix = ("give w and h, that size, in the transforms file" if scene.format in ("blender", "nerfstudio")
                   else "scale them to these images")
            return (f"view {split.names[i]} ({name}) has its principal point at ({cx:g}, {cy:g}), far from the centre "
                    f"of its {split.width} x {split.height} image ({int(off.sum())} of {len(split)} views): do the "
                    f"intrinsics refer to images of another size? Then {fix}")
    return ""


def _far_from_origin(scene: Scene) -> str:
    """"" or a warning for cameras far from the world's origin compared with the scene's size (georeferenced or
    UTM coordinates): float32, which rays and grids use, keeps about 7 digits, so at 1000x the size (the larger of
    the cameras' spread and the box's longest side) a position is known to about 1e-4 of it (a twentieth of a
    384^3 voxel), and worse beyond. Cameras sharing one spot near the origin (a panorama) are no concern."""
    if scene.ndc is not None:
        return ""
    centres = scene.splits["train"].poses[:, :3, 3].double()
    spread = float((centres - centres.mean(0)).norm(dim=-1).max())
    size = max(spread, float((scene.bbox[1] - scene.bbox[0]).max()))
    reach = float(centres.abs().max())
    if size <= 0 or reach <= 1000 * size:
        return ""
    return (f"the training cameras sit up to {reach:.4g} from the world's origin, {reach / size:.0f}x the scene's "
            f"size ({size:.4g}): float32 positions there are coarse; recentre the poses (subtract their mean centre) "
            "before training")


@timed("scene")
def load_scene(path, image_size: int | None = None, holdout_every: int = 8, format: str = "auto",
               bbox: list[float] | None = None, cache: Path | None = None, kind: str = "auto") -> Scene:
    """Load the scene at `path`; `format` is "auto" or a key of `FORMATS`.

    With "auto", `scene.extra["detected"]` says which format was recognised from which files; `scene.extra["warnings"]`
    holds what the loader found doubtful (`DataWarning`, one line each). `bbox`
    ([xmin, ymin, zmin, xmax, ymax, zmax], world units) replaces the box the loader gives, for content that
    reaches past it; a forward-facing scene's box is NDC's and cannot be replaced. `cache`: a file that keeps the
    decoded scene for the next load of the same files with the same settings (scenes/cache.py). `kind` (recipe key
    data.scene): auto, bounded, unbounded or forward (scenes/kind.py); the one chosen, and why, in
    `scene.extra["kind"]`.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise BoostNerfError(f"scene folder {folder} does not exist: check the path")
    settings = {"image_size": image_size, "holdout_every": holdout_every, "format": format, "bbox": bbox,
                "scene": kind}
    return cached(lambda: _decode(folder, image_size, holdout_every, format, bbox, kind), folder, settings, cache)


def _decode(folder: Path, image_size: int | None, holdout_every: int, format: str, bbox: list[float] | None,
            kind: str = "auto") -> Scene:
    detected = ""
    if format == "auto":
        format, found = detect_format(folder)
        detected = f"{format} (found {found})"
    if format not in FORMATS:
        raise BoostNerfError(f"unknown scene format {format!r}: use auto or one of {', '.join(FORMATS)}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        scene = FORMATS[format][1](folder, image_size=image_size, holdout_every=holdout_every)
    box_doubts = []  # moot once the scene is unbounded (its space is all of it)
    for w in caught:
        if issubclass(w.category, BoxWarning) and bbox is not None:
            continue  # a doubt about the derived box or near / far: data.bbox gives both (below)
        if issubclass(w.category, DataWarning):
            scene.extra.setdefault("warnings", []).append(str(w.message))
            if issubclass(w.category, BoxWarning):
                box_doubts.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    for doubt in (_off_centre(scene), _far_from_origin(scene)):
        if doubt:
            scene.extra.setdefault("warnings", []).append(doubt)
    if detected:
        scene.extra["detected"] = detected
    if bbox is not None and kind != "unbounded":  # unbounded with a box: refused by with_kind, in one line
        if scene.ndc is not None:
            raise BoostNerfError(f"data.bbox does not apply to {folder}: a forward-facing scene is sampled in "
                                 "normalized device coordinates, whose box is fixed; remove the key")
        try:
            box = torch.tensor(bbox, dtype=torch.float32)
        except (TypeError, ValueError):
            raise BoostNerfError(f"data.bbox = {bbox!r}: "
                                 "must be six numbers, xmin, ymin, zmin, xmax, ymax, zmax") from None
        # `Scene` refuses any other shape, and a max not above its min, in one line
        scene = dataclasses.replace(scene, bbox=box.view(2, 3) if box.numel() == 6 else box,
                                    extra={**scene.extra, "bbox": "data.bbox", "box_from": "recipe key data.bbox"})
    scene = with_kind(scene, kind, folder, bbox is not None)
    if scene.contraction is not None and box_doubts:
        kept = [w for w in scene.extra["warnings"] if w not in box_doubts]
        scene.extra.pop("warnings")
        if kept:
            scene.extra["warnings"] = kept
    return _reach_box(scene) if scene.ndc is None and scene.contraction is None else scene


def _reach_box(scene: Scene) -> Scene:
    """near / far widened so that every camera's rays, of every split, reach all of the box: a far derived from the
    training cameras (test cameras farther out rendered nothing but background, with no word), from cameras inside
    the content, or one the files record, could end rays short of it, and so could a box given by data.bbox. near
    comes down to 0.9x the distance to the box of the nearest camera outside it (a camera inside the box does not
    pull it to 0)."""
    poses = torch.cat([split.poses for split in scene.splits.values()])
    _, box_far = box_near_far(poses, scene.bbox)
    gaps = box_gaps(poses, scene.bbox)
    outside = gaps[gaps > 0]
    near = min(scene.near, 0.9 * float(outside.min())) if len(outside) else scene.near
    far = max(scene.far, box_far)
    if (near, far) == (scene.near, scene.far):
        return scene
    note = (f"near / far {scene.near:.4g} / {scene.far:.4g} widened to {near:.4g} / {far:.4g}, so that every camera's "
            "rays (train and test) reach the whole scene box")
    return dataclasses.replace(scene, near=near, far=far,
                               extra={**scene.extra, "notes": [*scene.extra.get("notes", []), note]})


__all__ = ["FORMATS", "LAYOUTS", "Scene", "SparsePoints", "Split", "detect_format", "load_blender", "load_colmap",
           "load_llff", "load_nerfstudio",
           "load_nsvf", "load_scene", "load_tanks", "make_scene"]
