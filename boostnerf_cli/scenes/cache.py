"""A scene decoded once: its images as training sees them, kept in one file that later stages read back.

Decoding a capture's PNG or JPEG files and scaling them down is most of a stage's start-up (100 lego views at
800 px: about 2 s on two cores, for every stage that reads the scene). `load_scene(..., cache=PATH)` keeps the loaded
scene in one safetensors file at PATH (the workspace's `cache/scene.safetensors`), keyed by the loader's settings and
every file of the scene folder by name, size and modification time: a later stage on the same files and settings
reads the tensors back instead (when their digest, written with them, still matches), and any change to them decodes
the files again and rewrites the cache. The cache
holds float32 images (12 bytes a pixel and view, e.g. 192 MB for 100 views at 400 px); deleting it costs only the
decoding.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.contraction import Contraction
from boostnerf_cli.render.rays import NDC
from boostnerf_cli.scenes.scene import Scene, SparsePoints, Split
from boostnerf_cli.workspace import atomic_path, tensors_digest

KEY = "boostnerf-scene"


def source_key(folder: Path, settings: dict) -> str:
    """What a cached scene must match: the loader's `settings` and every file under `folder` (name, size, time)."""
    files = []
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            st = p.stat()
            files.append((p.relative_to(folder).as_posix(), st.st_size, st.st_mtime_ns))
    text = json.dumps({"settings": settings, "folder": str(folder.resolve()), "files": files}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def read(path: Path, key: str) -> Scene | None:
    """The scene cached at `path` for `key`, or None (no cache, another key, or a file that does not read)."""
    if not path.is_file():
        return None
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            meta = json.loads((f.metadata() or {}).get(KEY, "{}"))
        if meta.get("key") != key:
            return None
        tensors = load_file(str(path))
        if meta.get("digest") != tensors_digest(tensors):  # its bytes changed since it was written: decode again
            return None
        splits = {name: Split(tensors[f"{name}.images"], tensors[f"{name}.poses"], tensors[f"{name}.intrinsics"],
                              tuple(names), tensors.get(f"{name}.alpha"))
                  for name, names in meta["splits"].items()}
        points = None
        if "points.xyz" in tensors:
            points = SparsePoints(tensors["points.xyz"], tensors["points.rgb"], tensors["points.error"],
                                  {name: tensors[f"points.{name}.visible"] for name in meta["splits"]
                                   if f"points.{name}.visible" in tensors})
        return Scene(meta["name"], splits, meta["near"], meta["far"], tensors["bbox"], tuple(meta["background"]),
                     meta["source"], meta["format"], meta["holdout"], meta["extra"],
                     NDC(**meta["ndc"]) if meta["ndc"] is not None else None, points,
                     Contraction.from_dict(meta["contraction"]) if meta.get("contraction") else None)
    except (SafetensorError, OSError, ValueError, KeyError, TypeError, BoostNerfError):  # damaged, foreign or of
        # another layout: decode again
        return None


def write(path: Path, key: str, scene: Scene) -> None:
    """Keep `scene` at `path` for `key` (atomically); a scene whose notes are not plain JSON is not kept."""
    meta = {"key": key, "name": scene.name, "near": scene.near, "far": scene.far, "background": list(scene.background),
            "source": scene.source, "format": scene.format, "holdout": scene.holdout, "extra": scene.extra,
            "ndc": scene.ndc.to_dict() if scene.ndc is not None else None,
            "contraction": scene.contraction.to_dict() if scene.contraction is not None else None,
            "splits": {name: list(s.names) for name, s in scene.splits.items()}}
    try:
        json.dumps(meta)
    except (TypeError, ValueError):
        return
    tensors = {"bbox": scene.bbox}
    for name, s in scene.splits.items():
        tensors.update({f"{name}.images": s.images, f"{name}.poses": s.poses, f"{name}.intrinsics": s.intrinsics})
        if s.alpha is not None:
            tensors[f"{name}.alpha"] = s.alpha
    if scene.points is not None:
        tensors.update({"points.xyz": scene.points.xyz, "points.rgb": scene.points.rgb,
                        "points.error": scene.points.error})
        tensors.update({f"points.{name}.visible": rows for name, rows in scene.points.visible.items()})
    clean = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        save_file(clean, str(tmp), metadata={KEY: json.dumps({**meta, "digest": tensors_digest(clean)})})


def cached(load, folder: Path, settings: dict, path: Path | None) -> Scene:
    """`load()` (which reads the scene at `folder` with `settings`), through the cache at `path` (None: no cache)."""
    if path is None:
        return load()
    key = source_key(folder, settings)
    scene = read(path, key)
    if scene is None:
        scene = load()
        try:
            write(path, key, scene)
        except OSError:  # a full disk or a read-only workspace: the scene is read, the next stage decodes again
            pass
    return scene
