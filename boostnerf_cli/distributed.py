"""Several processes for `pretrain` and `finetune` (torchrun); one process is unchanged.

Launched by `torchrun` (WORLD_SIZE > 1 in the environment), `session` joins the process group from
torchrun's variables (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT) with the backend of the
device: NCCL on CUDA (rank r uses cuda:LOCAL_RANK), gloo on CPU. Without torchrun nothing here
creates a process group and every helper is the one-process identity, so numbers stay as they are.

Failures: every place where ranks meet goes through `check`, a collective in which each rank says
whether its part failed. When one did, the failing rank raises its own error and every other rank a
`BoostNerfError` naming it ("rank 1 of 2 failed: ..."), so all ranks stop with its message and a
non-zero exit. Data collectives (`all_sum`, `average_gradients`) are preceded by such a check, so a
rank that fails anywhere in a step still meets the others (docs/distributed.md).
"""

from __future__ import annotations

import logging
import os
from contextlib import ExitStack, contextmanager
from datetime import timedelta
from typing import Callable, Iterator, TypeVar

import torch
import torch.distributed as dist
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.metrics import mse_to_psnr

T = TypeVar("T")

# How long a rank waits for the others at a meeting point. Pretraining ranks wait for the slowest
# rank's experts, which can take hours; a rank that dies is noticed by torchrun, which stops the rest.
TIMEOUT = timedelta(days=7)

_device = torch.device("cpu")  # where collectives' tensors live: cpu for gloo, this rank's GPU for NCCL


def launched() -> bool:
    """True in a process started by torchrun with more than one process."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def world_size() -> int:
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def rank() -> int:
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def is_main() -> bool:
    return rank() == 0


@contextmanager
def session(device: str) -> Iterator[str]:
    """Join torchrun's process group for the block (nothing without torchrun); -> the device this rank uses."""
    global _device
    if not launched():
        yield device
        return
    if device == "cuda":
        device = f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
        torch.cuda.set_device(device)
    try:
        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo", timeout=TIMEOUT)
    except (RuntimeError, ValueError) as e:
        raise BoostNerfError(f"could not join torchrun's process group ({e}); see docs/distributed.md") from None
    _device = torch.device(device)
    try:
        yield device
        # every rank reaches teardown before any leaves (on success only: a failed rank's peers are stopped by
        # torchrun). Without it a rank that destroyed its gloo group while its peer still finished the last
        # collective aborted now and then under load ("terminate called without an active exception")
        dist.barrier()
    finally:
        _device = torch.device("cpu")
        dist.destroy_process_group()


@contextmanager
def others_quiet() -> Iterator[None]:
    """The block's messages (the `boostnerf_cli` log) said by rank 0 alone, for messages every rank would repeat."""
    logger = logging.getLogger("boostnerf_cli")
    level = logger.level
    if not is_main():
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


# --- meeting points ------------------------------------------------------------------------------
def _describe(error: BaseException) -> str:
    if isinstance(error, BoostNerfError):
        return str(error)
    return f"{type(error).__name__}: {error} (its traceback is printed by that rank)"


def check(error: BaseException | None = None) -> None:
    """Collective: if `error` is set on any rank, every rank raises (see the module docstring).
    One process: raises `error` if given."""
    if world_size() == 1:
        if error is not None:
            raise error
        return
    flag = torch.tensor([float(error is not None)], device=_device)
    dist.all_reduce(flag)
    if float(flag) == 0:
        return
    messages: list[str | None] = [None] * world_size()
    dist.all_gather_object(messages, None if error is None else _describe(error))
    if error is not None:
        raise error
    failed, message = next((r, m) for r, m in enumerate(messages) if m is not None)
    raise BoostNerfError(f"rank {failed} of {world_size()} failed: {message}")


@contextmanager
def together() -> Iterator[None]:
    """Run the block on every rank, then meet: if it raised on any rank, it raises on every rank."""
    error = None
    try:
        yield
    except Exception as e:  # interrupts (BaseException) are not caught: torchrun stops every rank
        error = e
    check(error)


def on_main(fn: Callable[[], T]) -> T | None:
    """Rank 0 runs `fn` while the others wait; -> its result on rank 0, None elsewhere."""
    with together():
        if is_main():
            return fn()
    return None


def main_first(fn: Callable[[], T]) -> T:
    """Rank 0 runs `fn` (it may write), then the other ranks (they read what it wrote); -> fn's result."""
    result = on_main(fn)
    with together():
        if not is_main():
            result = fn()
    return result  # type: ignore[return-value]


@contextmanager
def writer_lock(ws) -> Iterator[None]:
    """The workspace's writer lock (`Workspace.lock`) for all ranks: rank 0 takes it, the others start once
    it has it, and it is released once every rank has finished the block. A second command is refused."""
    if world_size() == 1:
        with ws.lock():
            yield
        return
    with ExitStack() as held:
        with together():
            if is_main():
                held.enter_context(ws.lock())
        yield
        check()  # every rank is done before rank 0 releases the lock


# --- data parallel -------------------------------------------------------------------------------
def shard(batch: Tensor) -> Tensor:
    """This rank's contiguous share of a global batch (its length divisible by the number of ranks)."""
    return batch.chunk(world_size())[rank()]


@contextmanager
def rng_share(per_rank: int, device: str | torch.device) -> Iterator[None]:
    """Make a block that draws one uniform value per ray of this rank's shard (the renderer's jitter) draw
    the values those rays get in the global batch, and leave torch's RNG where one process leaves it.

    torch's CPU generator draws uniform floats one after the other, so skipping the values of the ranks
    before this one, and after the block those of the ranks after it, is exact on CPU. On CUDA (Philox,
    drawn per launch) the shard's values are other independent draws: equal in distribution only.
    """
    before, after = rank() * per_rank, (world_size() - rank() - 1) * per_rank
    if before:
        torch.rand(before, device=device)
    yield
    if after:
        torch.rand(after, device=device)


def all_sum(t: Tensor) -> Tensor:
    """Collective: the sum over the ranks of `t` (a new tensor, no gradient)."""
    check()
    total = t.detach().clone()
    dist.all_reduce(total)
    return total


def _as_mean(key: str, value: float) -> float:
    """Logs are averaged over the ranks; a PSNR is averaged as the mean squared error it comes from."""
    return 10.0 ** (-value / 10.0) if key == "psnr" else value


def _from_mean(key: str, value: float) -> float:
    return mse_to_psnr(value) if key == "psnr" else value


def average_gradients(params: list[Tensor], learnable: bool, finite: bool, logs: dict[str, float],
                      error: Exception | None = None) -> tuple[bool, bool, dict[str, float]]:
    """Data parallel, after every rank's backward of the mean loss of its shard: each parameter's .grad becomes
    the mean over the ranks (zeros for a rank without one), which for equal shards is the gradient of the
    mean loss of the union. A parameter no rank has a gradient for keeps None, so Adam skips it as it
    would in one process. -> the whole batch's (learnable: some rank's loss depends on the parameters,
    finite: every rank's loss is finite, logs averaged over the ranks). `error`: this rank's step failed.
    """
    check(error)
    world, n = world_size(), len(params)
    head = torch.tensor([float(learnable), float(not finite), *(float(p.grad is not None) for p in params),
                         *(_as_mean(k, v) for k, v in logs.items())], dtype=torch.float64, device=_device)
    dist.all_reduce(head)
    grads = [(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params]
    flat = torch.cat(grads) if grads else torch.zeros(0, device=_device)
    dist.all_reduce(flat)
    flat /= world
    for p, has, g in zip(params, head[2 : 2 + n].tolist(), flat.split([p.numel() for p in params])):
        p.grad = g.view_as(p) if has > 0 else None
    means = (head[2 + n :] / world).tolist()
    return bool(head[0] > 0), bool(head[1] == 0), {k: _from_mean(k, v) for k, v in zip(logs, means)}
