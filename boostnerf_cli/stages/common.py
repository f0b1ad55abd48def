"""What several stages share: the device to run on, the workspace's scene reloaded and checked, and training a model
with its report (pretrain's experts, finetune's mixtures and baseline)."""

from __future__ import annotations

import logging
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import count_params
from boostnerf_cli.lineage import SceneSpec, scene_digest
from boostnerf_cli.scenes import Scene, load_scene
from boostnerf_cli.train import RayData, Schedule, TrainCheckpoint, TrainResult, TrainTask, train
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
    spec = SceneSpec.recorded(data)
    scene = load_scene(path, image_size=spec.image_size, holdout_every=spec.holdout_every, format=spec.format,
                       bbox=spec.bbox, cache=ws.scene_cache,
                       kind=spec.scene)
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


def train_and_report(task: TrainTask, rays: RayData, sched: Schedule, seed: int, name: str,
                     checkpoint: TrainCheckpoint, model: torch.nn.Module,
                     data_parallel: bool = False) -> tuple[TrainResult, dict]:
    """Train `task` (`train.train`), put `model` in eval mode, and the report every trained model's begins with:
    its steps, seconds, start-up, skipped steps, parameters, last train PSNR and history. -> (result, report)."""
    result = train(task, rays, sched, seed, name, checkpoint, data_parallel=data_parallel)
    model.eval()
    final = result.history[-1] if result.history else {}
    return result, {"iterations": result.iterations, "seconds": round(result.seconds, 2),
                    "startup_seconds": result.startup_seconds, "skipped_steps": result.skipped_steps,
                    "params": count_params(model), "train_psnr": final.get("psnr"), "history": result.history}
