"""Scene loading: every dataset format becomes one `Scene` (see `scene.py` for the conventions).

To add a format, write `load_<format>(path, image_size, holdout_every) -> Scene` and a detector
`is_<format>(path) -> bool`, and add one entry to `FORMATS`. "auto" tries detectors in order.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.scenes.blender import is_blender, load_blender
from boostnerf_cli.scenes.procedural import make_scene
from boostnerf_cli.scenes.scene import Scene, Split

# name -> (detector, loader, what the detector looks for)
FORMATS: dict[str, tuple[Callable[[Path], bool], Callable[..., Scene], str]] = {
    "blender": (is_blender, load_blender, "transforms_{train,val,test}.json"),
}


def load_scene(path, image_size: int | None = None, holdout_every: int = 8, format: str = "auto") -> Scene:
    """Load the scene at `path`; `format` is "auto" or a key of `FORMATS`."""
    folder = Path(path)
    if not folder.is_dir():
        raise BoostNerfError(f"scene folder {folder} does not exist: check the path")
    if format == "auto":
        format = next((name for name, (detect, _, _) in FORMATS.items() if detect(folder)), "")
        if not format:
            wanted = "; ".join(f"{name}: {what}" for name, (_, _, what) in FORMATS.items())
            raise BoostNerfError(f"cannot tell the dataset format of {folder}: looked for {wanted}")
    if format not in FORMATS:
        raise BoostNerfError(f"unknown scene format {format!r}: use auto or one of {', '.join(FORMATS)}")
    return FORMATS[format][1](folder, image_size=image_size, holdout_every=holdout_every)


__all__ = ["FORMATS", "Scene", "Split", "load_blender", "load_scene", "make_scene"]
