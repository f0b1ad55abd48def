"""What several stages share: the device to run on, a notice for slow reads, and training a model with its report
(pretrain's experts, finetune's mixtures and baseline). What a workspace holds is `lineage.Survey`'s to say."""

from __future__ import annotations

import logging
import threading
from contextlib import contextmanager
from typing import Iterator

import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import count_params
from boostnerf_cli.train import RayData, Schedule, TrainCheckpoint, TrainResult, TrainTask, train

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
