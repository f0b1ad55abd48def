"""Saved views: a frame as a PNG and its camera, model and look as JSON beside it (the viewer's save button), which
`render --camera FILE` reads back and renders again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import ROW_WIDTHS
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.images import write_png
from boostnerf_cli.render.renderer import Camera
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
    """A view `save_view` wrote -> (camera, model name, look); one line when the file is not one."""
    data = read_json(path, "view file")
    try:
        pose = torch.tensor(data["pose"], dtype=torch.float32)
        intrinsics = torch.tensor(data["intrinsics"], dtype=torch.float32)
        height, width = int(data["height"]), int(data["width"])
        look = Look(str(data.get("mode", "colour")), int(data.get("expert", 0)))
        model = str(data["model"])
        ok = pose.shape == (4, 4) and intrinsics.ndim == 1 and len(intrinsics) in ROW_WIDTHS and height > 0
        ok = ok and width > 0 and bool(torch.isfinite(pose).all() and torch.isfinite(intrinsics).all()
                                       and (intrinsics[:2] > 0).all())
    except (*MALFORMED, TypeError) as e:
        raise BoostNerfError(f"{path} is not a saved view ({type(e).__name__}: {e}): save one with `boostnerf view`'s "
                             "save button") from None
    if not ok:
        raise BoostNerfError(f"{path} is not a saved view: it needs a finite 4x4 pose, intrinsics fx, fy, cx, cy "
                             f"(and a lens: {ROW_WIDTHS[1]} numbers) with positive focal lengths, and a positive "
                             "height and width")
    return Camera(pose, intrinsics, height, width), model, look
