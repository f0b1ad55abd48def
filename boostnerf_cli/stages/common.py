"""What several stages share: the device to run on, and the workspace's scene reloaded and checked."""

from __future__ import annotations

import logging
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import scene_digest
from boostnerf_cli.scenes import Scene, load_scene
from boostnerf_cli.workspace import Workspace

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)


def resolve_device(name: str) -> str:
    """`auto` -> cuda when available, else cpu; `cuda` without a GPU is an error."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise BoostNerfError("--device cuda was asked for but torch sees no CUDA GPU: use --device cpu or auto")
    if name not in ("cpu", "cuda"):
        raise BoostNerfError(f"unknown device {name!r}: use auto, cpu or cuda")
    return name


def workspace_scene_path(ws: Workspace, m: dict) -> Path:
    """The path of the scene the workspace `m` (its manifest) records, its content unchecked; one line saying how to
    point to where it went when it is gone."""
    recorded = ws.root / m["data"]["path"]
    if not recorded.exists():
        raise BoostNerfError(
            f"the workspace's scene {recorded} is gone: restore it, or if it moved, say where to once with `boostnerf "
            f"pretrain --workspace {ws.root} --data NEW_PLACE` (the same images and cameras: nothing is retrained)")
    return recorded


def workspace_scene(ws: Workspace) -> Scene:
    """Reload the scene a workspace was trained on, exactly as `pretrain` loaded it (refused when its images or
    cameras changed since)."""
    m = ws.require_manifest()
    data = m.get("data")
    if not data:
        raise BoostNerfError(f"{ws.manifest_path} records no scene: rerun `boostnerf pretrain --workspace {ws.root}`")
    path = workspace_scene_path(ws, m)
    scene = load_scene(path, image_size=data.get("image_size"), holdout_every=data.get("holdout_every", 8),
                       format=data.get("format", "auto"), bbox=data.get("bbox"), cache=ws.scene_cache,
                       kind=data.get("scene", "auto"))
    if m.get("scene_digest") and scene_digest(scene) != m["scene_digest"]:
        raise BoostNerfError(
            f"the workspace's scene {path} changed since pretrain (its images or cameras differ): restore it, "
            f"or retrain with `boostnerf pretrain --workspace {ws.root} --data {path} --force`"
        )
    return scene


@contextmanager
def slow_notice(message: str, after: float = 5.0) -> Iterator[None]:
    """Say `message` once if the block is still running after `after` seconds (reading a large capture takes
    minutes); a block that ends sooner, or fails at once with its one-line error, prints nothing more."""
    timer = threading.Timer(after, log, args=(message,))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
