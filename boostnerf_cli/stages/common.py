"""What several stages share: the device to run on, and the workspace's scene reloaded and checked."""

from __future__ import annotations

import hashlib
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.scenes import Scene, load_scene
from boostnerf_cli.workspace import Workspace


def resolve_device(name: str) -> str:
    """`auto` -> cuda when available, else cpu; `cuda` without a GPU is an error."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise BoostNerfError("--device cuda was asked for but torch sees no CUDA GPU: use --device cpu or auto")
    if name not in ("cpu", "cuda"):
        raise BoostNerfError(f"unknown device {name!r}: use auto, cpu or cuda")
    return name


def _load_recorded(path, data: dict) -> Scene:
    return load_scene(path, image_size=data.get("image_size"), holdout_every=data.get("holdout_every", 8),
                      format=data.get("format", "auto"), bbox=data.get("bbox"))


def _locate_scene(ws: Workspace, m: dict) -> tuple[Path, Scene | None]:
    """Where a workspace's scene is: its own `scene` folder (the generated one) when the recorded path is elsewhere
    and that folder holds the recorded images and cameras (a workspace made by an older boostnerf recorded its generated
    scene absolute: a renamed or copied one must read its own scene, not what now sits at the old place); else the
    recorded path, and when that is gone, one line saying how to point to where it went (a leftover `scene` folder
    of another scene is not blamed). -> (path, the scene when already loaded to tell)."""
    data = m["data"]
    recorded, own = ws.root / data["path"], ws.root / "scene"
    if not own.is_dir() or own.resolve() == recorded.resolve():
        own = None
    own_scene = None
    if own is not None and m.get("scene_digest"):
        try:
            own_scene = _load_recorded(own, data)
        except BoostNerfError:
            pass
        if own_scene is not None and scene_digest(own_scene) == m["scene_digest"]:
            return own, own_scene
    if not recorded.exists() and own is not None and not m.get("scene_digest"):
        return own, None  # no digest to tell by (a very old manifest): the workspace's own scene, as before
    if not recorded.exists():  # a `scene` folder left from another scene is not it (the recorded one moved)
        raise BoostNerfError(
            f"the workspace's scene {recorded} is gone: restore it, or if it moved, say where to once with `boostnerf "
            f"pretrain --workspace {ws.root} --data NEW_PLACE` (the same images and cameras: nothing is retrained)")
    return recorded, None


def workspace_scene_path(ws: Workspace, m: dict) -> Path:
    """The path of the scene the workspace `m` (its manifest) records (`_locate_scene`); its content unchecked."""
    return _locate_scene(ws, m)[0]


def workspace_scene(ws: Workspace, log: Callable[[str], None] | None = None) -> Scene:
    """Reload the scene a workspace was trained on, exactly as `pretrain` loaded it; `log` says when this boostnerf
    renders it with other near / far bounds than the workspace's pretrain recorded (a later release widened them:
    figures can then differ from the workspace's reports)."""
    m = ws.require_manifest()
    data = m.get("data")
    if not data:
        raise BoostNerfError(f"{ws.manifest_path} records no scene: rerun `boostnerf pretrain --workspace {ws.root}`")
    path, scene = _locate_scene(ws, m)
    if scene is None:
        scene = _load_recorded(path, data)
    if m.get("scene_digest") and scene_digest(scene) != m["scene_digest"]:
        raise BoostNerfError(
            f"the workspace's scene {path} changed since pretrain (its images or cameras differ): restore it, "
            f"or retrain with `boostnerf pretrain --workspace {ws.root} --data {path} --force`"
        )
    was = m.get("scene") or {}
    if log is not None and scene.ndc is None and was.get("near") is not None and (
            abs(was["near"] - scene.near) > 1e-6 * max(1.0, abs(scene.near)) or
            abs(was["far"] - scene.far) > 1e-6 * max(1.0, abs(scene.far))):
        log(f"note: rays run over near / far {scene.near:.4g} / {scene.far:.4g} here, {was['near']:.4g} / "
            f"{was['far']:.4g} when this workspace was pretrained (an earlier boostnerf): its reports' figures may "
            "differ from these; rerun `boostnerf pretrain` on it to record the new bounds (nothing is retrained)")
    return scene


def scene_digest(scene: Scene) -> str:
    """Fingerprint of what training sees: every split's images, poses and intrinsics (recorded by pretrain)."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(scene.splits):
        s = scene.splits[name]
        h.update(name.encode())
        for t in (s.images, s.poses, s.intrinsics):
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


@contextmanager
def slow_notice(log: Callable[[str], None], message: str, after: float = 5.0) -> Iterator[None]:
    """Say `message` once if the block is still running after `after` seconds (reading a large capture takes
    minutes); a block that ends sooner, or fails at once with its one-line error, prints nothing more."""
    timer = threading.Timer(after, log, args=(message,))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
