"""Saved views: a frame as a PNG and its camera, model and look as JSON beside it (the viewer's save button), which
`render --camera FILE` reads back and renders again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import PINHOLE, ROW_WIDTHS, WITH_LENS
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.images import write_png
from boostnerf_cli.render.renderer import Camera
from boostnerf_cli.viewpoint.camera_path import MAX_SIDE, rigid
from boostnerf_cli.viewpoint.frame import Look
from boostnerf_cli.workspace import MALFORMED, read_json, write_json


def view_dict(camera: Camera, model: str, look: Look) -> dict:
    """A saved view as JSON: the camera (pose, intrinsics: fx, fy, cx, cy and a lens's numbers,
    `cameras.Intrinsics.row`; size), the model and what it shows."""
    return {"pose": camera.pose.float().tolist(), "intrinsics": camera.intrinsics.float().tolist(),
            "height": camera.height, "width": camera.width, "model": model, "mode": look.mode, "expert": look.expert}


def save_view(folder: Path, image: np.ndarray, camera: Camera, model: str, look: Look) -> Path:
    """Write `image` as folder/view-N.png and its view as view-N.json (N: the next free number) -> the PNG."""
    folder.mkdir(parents=True, exist_ok=True)
    n = 1 + max((int(p.stem[5:]) for p in folder.glob("view-*.json") if p.stem[5:].isdigit()), default=0)
    png = folder / f"view-{n:03d}.png"
    write_png(png, image)
    write_json(png.with_suffix(".json"), view_dict(camera, model, look))
    return png


def read_view(path: Path) -> tuple[Camera, str, Look]:
    """A view `save_view` wrote -> (camera, model name, look); one line when the file is not one. Its pose must be
    rigid as a camera path's (`camera_path.rigid`; the numbers are kept as written), its size 1 to `MAX_SIDE` pixels a
    side, and a lens's fisheye flag 0 or 1."""
    data = read_json(path, "view file", "fix it, or save the view again with `boostnerf view`")
    try:
        rigid(data.get("pose"), f"{path} is not a saved view: its pose")
        pose = torch.tensor(data["pose"], dtype=torch.float32)
        intrinsics = torch.tensor(data["intrinsics"], dtype=torch.float32)
        sides = (data["height"], data["width"])
        look = Look(str(data.get("mode", "colour")), int(data.get("expert", 0)))
        model = str(data["model"])
        ok = intrinsics.ndim == 1 and len(intrinsics) in ROW_WIDTHS and bool(torch.isfinite(intrinsics).all()
                                                                            and (intrinsics[:2] > 0).all())
    except (*MALFORMED, TypeError) as e:
        raise BoostNerfError(f"{path} is not a saved view ({type(e).__name__}: {e}): save one with `boostnerf view`'s "
                             "save button") from None
    if not ok:
        raise BoostNerfError(f"{path} is not a saved view: it needs intrinsics fx, fy, cx, cy (and a lens: "
                             f"{ROW_WIDTHS[1]} numbers) with positive focal lengths")
    if not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_SIDE for v in sides):
        raise BoostNerfError(f"{path} is not a saved view: its height and width are {sides[0]!r} and {sides[1]!r}, "
                             f"whole numbers of pixels from 1 to {MAX_SIDE} are needed")
    if len(intrinsics) > PINHOLE and float(intrinsics[WITH_LENS - 1]) not in (0.0, 1.0):
        raise BoostNerfError(f"{path} is not a saved view: its lens's fisheye flag (intrinsics[{WITH_LENS - 1}]) is "
                             f"{float(intrinsics[WITH_LENS - 1]):g}, not 0 or 1")
    return Camera(pose, intrinsics, *sides), model, look
