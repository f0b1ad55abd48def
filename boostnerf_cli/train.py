"""One training loop for every stage that trains (pretrain, finetune, baseline).

The loop owns batching, the optimiser and its schedule, the NaN guard, progress output and
resumable checkpoints. What is trained, how rays are rendered and what the loss is are passed in
(`TrainTask`), so the loop knows nothing of experts or mixtures.
"""

from __future__ import annotations

import logging
import math
import sys
import time
import zlib
from collections import deque
from contextlib import nullcontext
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Callable, Iterator, Protocol

import torch
from torch import Tensor

from boostnerf_cli import distributed as dist
from boostnerf_cli.adam import Adam
from boostnerf_cli.device import from_host
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import MAKE, Found, decide
from boostnerf_cli.recipe import TrainRecipe
from boostnerf_cli.render.rays import NDC, image_rays, intersect_box
from boostnerf_cli.scenes.scene import Split
from boostnerf_cli.startup import CLOCK
from boostnerf_cli.workspace import FORMAT_VERSION, MALFORMED, malformed, save_torch

_log = logging.getLogger(__name__)  # a run's messages and warnings (cli.py says them on stderr)


@dataclass
class RayData:
    """All training rays of a split that hit the box: origins, dirs, rgb, each (N, 3), and the pixels' alpha (N,)
    (None: opaque images, or not asked for), on the split's device (the CPU) until `.to(device)`."""

    origins: Tensor
    dirs: Tensor
    rgb: Tensor
    alpha: Tensor | None = None

    @staticmethod
    def from_split(split: Split, bbox: Tensor, near: float, far: float, ndc: NDC | None = None,
                   keep_alpha: bool = False, device: torch.device | str = "cpu") -> "RayData":
        """The rays of `split` that hit `bbox`, built on `device` in one pass over the views: each view's rays that
        hit are written into a table sized for every pixel, then cut to those written (36 bytes a pixel at most:
        300 views at 800 px, 6.9 GB). A ray that misses the box renders the background exactly: nothing to learn
        from it. `keep_alpha`: keep the split's alpha (when its images had one), for a loss that composites the
        pixels on another colour than the scene's background (`train.random_background`)."""
        device = torch.device(device)
        box, dtype, pixels = bbox.to(device), split.images.dtype, split.height * split.width
        origins, dirs, rgb = (torch.empty(len(split) * pixels, 3, dtype=dtype, device=device) for _ in range(3))
        alpha = None
        if keep_alpha and split.alpha is not None:
            alpha = torch.empty(len(split) * pixels, dtype=dtype, device=device)
        at = 0
        for i in range(len(split)):
            o, d = image_rays(split.poses[i].to(device), split.intrinsics[i], split.height, split.width, ndc)
            hit = intersect_box(o, d, box, near, far)[2]
            k = int(hit.sum())
            origins[at : at + k], dirs[at : at + k] = o[hit], d[hit]
            rgb[at : at + k] = split.images[i].to(device).reshape(-1, 3)[hit]
            if alpha is not None:
                alpha[at : at + k] = split.alpha[i].to(device).reshape(-1)[hit]
            at += k
        return RayData(origins[:at], dirs[:at], rgb[:at], None if alpha is None else alpha[:at])

    def to(self, device: torch.device | str) -> "RayData":
        return RayData(self.origins.to(device), self.dirs.to(device), self.rgb.to(device),
                       None if self.alpha is None else self.alpha.to(device))

    def __len__(self) -> int:
        return self.origins.shape[0]


_TRAIN = TrainRecipe()  # the training section's defaults, Schedule's too


@dataclass
class Schedule:
    """How long the loop trains, with how many rays a step, how its learning rates fall and when it logs and
    checkpoints: `Schedule.of` takes them from a recipe's training section (the one place that does)."""

    iters: int
    batch_rays: int = _TRAIN.batch_rays
    lr_decay: float = _TRAIN.lr_decay  # learning rates fall exponentially to this fraction at the last step
    log_every: int = _TRAIN.log_every
    checkpoint_every: int = _TRAIN.checkpoint_every
    max_bad_steps: int = 20  # consecutive non-finite steps before the run stops

    @staticmethod
    def of(iters: int, tcfg: TrainRecipe) -> "Schedule":
        """`iters` steps with the training settings `tcfg` (a recipe's `train` section)."""
        return Schedule(iters, tcfg.batch_rays, tcfg.lr_decay, tcfg.log_every, tcfg.checkpoint_every)


class TrainTask(Protocol):
    """What one stage trains: its parameters, how a batch of rays becomes a loss, its growth events."""

    def param_groups(self) -> list[dict]: ...

    def loss(self, origins: Tensor, dirs: Tensor, rgb: Tensor, alpha: Tensor | None,
             step: int) -> tuple[Tensor, dict[str, float]]: ...

    def before_step(self, step: int) -> bool:
        """Called before each step; True when the parameters changed (the optimiser is rebuilt)."""
        ...

    def state(self) -> dict: ...

    def load_state(self, state: dict) -> None: ...


@dataclass
class TrainResult:
    iterations: int
    seconds: float
    skipped_steps: int
    history: list[dict] = field(default_factory=list)
    startup_seconds: float = 0.0  # from the command's start (or the model before) to this model's first step


class PsnrTrend:
    """The mean training PSNR of each logging interval, and a warning when it falls for `intervals` intervals
    in a row by `min_drop` dB in all (a falling train PSNR means the run is losing what it had learnt)."""

    def __init__(self, intervals: int = 3, min_drop: float = 0.5):
        self.intervals, self.min_drop = intervals, min_drop
        self.total, self.count, self.means, self.warned = 0.0, 0, [], False

    def state(self) -> dict:
        """What a checkpoint keeps, so that a resumed run logs the same means and warns at the same step."""
        return {"total": float(self.total), "count": int(self.count), "means": list(self.means), "warned": self.warned}

    def load_state(self, state: dict) -> None:
        self.total, self.count = float(state["total"]), int(state["count"])
        self.means, self.warned = [float(m) for m in state["means"]], bool(state["warned"])

    def add(self, psnr: float | Tensor | None) -> None:
        """Add a step's PSNR (a device value is summed on the device: nothing waits for it)."""
        if isinstance(psnr, Tensor):
            finite = torch.isfinite(psnr)
            self.total = self.total + torch.where(finite, psnr, 0.0)
            self.count = self.count + finite.to(torch.int64)
        elif psnr is not None and math.isfinite(psnr):
            self.total, self.count = self.total + psnr, self.count + 1

    def close_interval(self) -> float | None:
        total, count = float(self.total), int(self.count)
        mean = total / count if count else None
        if mean is not None:
            self.means.append(mean)
        self.total, self.count = 0.0, 0
        return mean

    def falling_warning(self, step: int) -> str | None:
        last = self.means[-(self.intervals + 1):]
        if self.warned or len(last) <= self.intervals:
            return None
        if all(b < a for a, b in zip(last, last[1:])) and last[0] - last[-1] >= self.min_drop:
            self.warned = True
            return (f"the train PSNR fell for {self.intervals} logging intervals in a row "
                    f"({last[0]:.2f} -> {last[-1]:.2f} dB by step {step}). Likely causes: skipping cut away structure "
                    "the training views show (compare with `pretrain --no-skip`), or learning rates too high for "
                    "this scene (lower train.lr_grid / lr_mlp)")
        return None


class Progress:
    """A rich progress bar on a terminal, plain periodic log lines otherwise; nothing when `quiet`."""

    def __init__(self, title: str, total: int, start: int, log_every: int, quiet: bool = False):
        self.title, self.total, self.log_every, self.quiet = title, total, log_every, quiet
        self.bar = None
        chatty = not quiet and _log.isEnabledFor(logging.INFO)  # -q: no progress
        if sys.stderr.isatty() and chatty:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn
            from rich.progress import Progress as RichProgress
            from rich.table import Column

            # on stderr, where the plain log lines go (stdout is for results), and laid out so that the title, step
            # and time always show: the logged values take what is left, cut at its end (at 80 columns they took
            # the whole line and the bar, the step and the time were gone)
            self.bar = RichProgress(TextColumn("{task.description}", table_column=Column(no_wrap=True)),
                                    BarColumn(bar_width=16), MofNCompleteColumn(), TimeElapsedColumn(),
                                    TextColumn("{task.fields[info]}",
                                               table_column=Column(no_wrap=True, overflow="ellipsis", ratio=1)),
                                    console=Console(stderr=True), expand=True, transient=False)
            self.bar.start()
            self.task = self.bar.add_task(title, total=total, completed=start, info="")

    def update(self, step: int, logs: dict[str, float] | None) -> None:
        """The step count; with `logs` (a logging step's values), also them."""
        if self.bar is not None:
            self.bar.update(self.task, completed=step, **({} if logs is None else {"info": _info(logs)}))
        elif not self.quiet and logs is not None and (step % self.log_every == 0 or step == self.total) \
                and _log.isEnabledFor(logging.INFO):
            print(f"[{self.title}] step {step}/{self.total} {_info(logs)}", file=sys.stderr, flush=True)

    def say(self, msg: str, level: int = logging.INFO) -> None:
        """A message of this run, `[title] msg`, through the log (above the bar, which redirects stderr)."""
        if not self.quiet:
            _log.log(level, f"[{self.title}] {msg}")

    def warn(self, msg: str) -> None:
        self.say(msg, logging.WARNING)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _info(logs: dict[str, float]) -> str:
    return " ".join(f"{k}={v:.4g}" for k, v in logs.items())


def make_optimizer(task: TrainTask) -> Adam:
    groups = task.param_groups()
    for g in groups:
        g.setdefault("initial_lr", g["lr"])
    return Adam(groups, betas=(0.9, 0.99), eps=1e-15)


def _set_lr(opt: Adam, step: int, sched: Schedule) -> None:
    factor = sched.lr_decay ** (step / max(1, sched.iters))
    for g in opt.param_groups:
        g["lr"] = g["initial_lr"] * factor


def grads_finite(params: list[Tensor], device: torch.device | str = "cpu") -> Tensor:
    """Whether no gradient holds a NaN or an infinity, as a device bool (nothing waits for it): one sum per gradient
    tensor. A sum is NaN or +-inf when any entry is (+inf and -inf together give NaN); finite entries whose sum
    overflows float32 are refused too, as a gradient that large should be. Measured on CPU over an 80^3 DVGO
    expert's 6.7M gradients, one thread: 0.9 ms, against 29 ms for a fused max-norm (`_foreach_norm(inf)`, slow on
    CPU) and ~20% of a small expert's step for an `isfinite` pass per tensor."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.ones((), dtype=torch.bool, device=device)
    return torch.stack([g.sum() for g in grads]).isfinite().all()


def state_checksum(obj) -> int:
    """CRC-32 of every tensor of a nested state (`_state_tensors`: path, dtype, shape and bytes, in path order): what a
    checkpoint keeps to tell it was damaged after writing. A CRC, not `tensors_digest`'s hash, for speed: 0.06 s for
    216 MB against 0.28 s, one thread (a paper-sized mixture's state is several GB, checkpointed every few thousand
    steps on a GPU)."""
    crc = 0
    for name, t in sorted(_state_tensors(obj).items()):
        t = t.detach().contiguous().cpu()
        crc = zlib.crc32(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode(), crc)
        if t.numel():
            crc = zlib.crc32(t.reshape(-1).view(torch.uint8).numpy(), crc)
    return crc


def _state_tensors(obj, where: str = "") -> dict[str, Tensor]:
    """Every tensor of a nested state (dicts, lists, tuples), by its path: what a checkpoint's checksum is made of."""
    if isinstance(obj, Tensor):
        return {where: obj}
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, (list, tuple)) else ()
    found: dict[str, Tensor] = {}
    for k, v in items:
        found.update(_state_tensors(v, f"{where}.{k}" if where else str(k)))
    return found


def _non_finite_entry(obj, where: str = "") -> str | None:
    """The first floating-point tensor in a nested state holding NaN or infinity, by its path; None if none."""
    return next((path for path, t in _state_tensors(obj, where).items()
                 if t.is_floating_point() and not bool(torch.isfinite(t).all())), None)


def batch_gradients(task: TrainTask, rays: RayData, idx: Tensor, step: int,
                    parallel: bool = False) -> tuple[bool, Tensor, dict]:
    """The loss of the batch `idx` and its gradient, accumulated in the parameters' .grad.

    -> (learnable: the loss depends on the parameters (False when every sample was skipped), whether the loss is
    non-finite (a device bool: the update is then skipped, `optimizer_step`), logs). `parallel` (data parallel):
    `idx` is the global batch and this rank takes its shard, with the random draws its rays get in the global batch
    (`distributed.rng_share`); the ranks' gradients are then combined by `distributed.average_gradients`.
    """
    if parallel:
        idx = dist.shard(idx)
    with dist.rng_share(len(idx), rays.origins.device) if parallel else nullcontext():
        alpha = None if rays.alpha is None else rays.alpha[idx]
        loss, logs = task.loss(rays.origins[idx], rays.dirs[idx], rays.rgb[idx], alpha, step)
    if loss.requires_grad:
        loss.backward()  # a non-finite loss gives non-finite gradients; the update is skipped either way
    return loss.requires_grad, ~torch.isfinite(loss.detach()), logs


def compiles(mode: str, device: torch.device | str) -> bool:
    """Whether a training step compiles (recipe key train.compile): "on", "off", or "auto": on a GPU."""
    return mode == "on" or (mode == "auto" and torch.device(device).type == "cuda")


def compiled(fn: Callable) -> Callable:
    """`fn` (a task's loss) through torch.compile: its operators and their gradients fused into few kernels. Random
    draws (the samples' jitter) stay torch's own, so a compiled run draws what an eager one does and resumes alike."""
    import torch._inductor.config as inductor

    inductor.fallback_random = True
    fast, calls = torch.compile(fn), 0

    def step(*args, **kwargs):
        # The first call runs eagerly: it sizes the sample budgets, each with its one wait for the device, which the
        # compiler cannot trace (it would split the step there, for good); the later calls find their sizes set.
        nonlocal calls
        calls += 1
        return (fn if calls == 1 else fast)(*args, **kwargs)

    return step


def draw_batch(gen: torch.Generator, n: int, size: int, device: torch.device) -> Tensor:
    """`size` ray indices below `n` from the host generator `gen` (so every device draws the same rays), on `device`
    (copied without waiting)."""
    return from_host(torch.randint(0, n, (size,), generator=gen), device)


@dataclass
class Step:
    """What one optimiser step did: `learnable` (False when every sample of the batch was skipped: nothing to
    learn), `flags` (None, or a device vector (non-finite loss, non-finite gradient, a sample budget overflowed): the
    update was skipped when any is set), the logs (device values), and the parameters it updates."""

    learnable: bool
    flags: Tensor | None
    logs: dict
    params: list[Tensor]


def optimizer_step(task: TrainTask, rays: RayData, sched: Schedule, opt: Adam | None,
                   gen: torch.Generator, step: int, parallel: bool) -> tuple[Adam | None, Step]:
    """One training step: the optimiser (re)built when the task changed its parameters (`before_step`), the step's
    learning rates, a batch drawn from `gen`, its gradient (data parallel: averaged over the ranks), and the update,
    skipped on the device (fused Adam's `found_inf`) unless the loss and every gradient are finite and every sample
    fitted its budget. Nothing here waits for the device (but data parallel). -> (the optimiser, the step)."""
    learnable, loss_bad, logs, failure = False, None, {}, None
    packer = getattr(task, "packer", None)
    try:
        if task.before_step(step) or opt is None:
            opt = make_optimizer(task)
        _set_lr(opt, step, sched)
        idx = draw_batch(gen, len(rays), sched.batch_rays, rays.origins.device)
        opt.zero_grad(set_to_none=True)
        if packer is not None:
            packer.begin()
        learnable, loss_bad, logs = batch_gradients(task, rays, idx, step, parallel)
    except Exception as e:
        if not parallel:
            raise
        failure = e  # every rank stops with this rank's message (in average_gradients)
    params = [p for g in opt.param_groups for p in g["params"]] if opt is not None else []
    if parallel:
        finite = failure is not None or not bool(loss_bad)
        learnable, finite, logs = dist.average_gradients(params, learnable, finite, _floats(logs), failure)
        loss_bad = torch.tensor(not finite, device=rays.origins.device)
    if not learnable:
        return opt, Step(False, None, logs, params)
    over = packer.overflowed() if packer is not None else None
    flags = torch.stack([loss_bad, ~grads_finite(params, loss_bad.device),
                         over if over is not None else torch.zeros_like(loss_bad)]).float()
    opt.found_inf = flags.amax()  # the update leaves every parameter and its state as they were when set
    opt.step()
    return opt, Step(True, flags, logs, params)


def _floats(logs: dict) -> dict[str, float]:
    return {k: float(v) for k, v in logs.items()}


class Outcomes:
    """Each step's flags (`Step.flags`), read back on the host without stopping the device: a copy queued after the
    step, read once it has arrived (at once off a GPU), and all of them on a logging or checkpoint step, when the
    task's sample budgets (`packer`) are settled too."""

    def __init__(self, device: torch.device, packer=None):
        self.cuda, self.packer = device.type == "cuda", packer
        self.queue: deque = deque()

    def push(self, done: int, step: Step) -> None:
        if not step.learnable:
            return
        host = step.flags.to("cpu", non_blocking=True)
        event = None
        if self.cuda:
            event = torch.cuda.Event()
            event.record()
        self.queue.append((done, host, event))

    def ready(self, wait: bool) -> Iterator[tuple[int, list[float]]]:
        """(step, its flags) of the steps whose flags have arrived, in order; `wait`: of every step pushed."""
        if wait and self.packer is not None:
            self.packer.settle()
        while self.queue:
            done, host, event = self.queue[0]
            if event is not None:
                if not wait and not event.query():
                    return
                event.synchronize()
            self.queue.popleft()
            yield done, host.tolist()


@dataclass
class RunState:
    """How far a run is: steps done, seconds trained, non-finite steps skipped, the logged history and the PSNR
    trend (what a checkpoint keeps besides the model, the optimiser and the random states), and the current run
    of consecutive non-finite steps."""

    step: int = 0
    seconds: float = 0.0
    skipped: int = 0
    history: list[dict] = field(default_factory=list)
    trend: PsnrTrend = field(default_factory=PsnrTrend)
    bad_run: int = 0

    def guard(self, done: int, flags: list[float], sched: Schedule, checkpoint: Path | None, progress: Progress,
              params: list[Tensor], packer=None) -> None:
        """The NaN guard, on a learnable step's flags (`Step.flags`): a skipped step is counted and said; the run stops
        when the parameters themselves are no longer finite (an overflowing update) or after `sched.max_bad_steps`
        consecutive steps with a non-finite loss or gradient (its message says what the `checkpoint` keeps). A step
        whose samples overflowed their budget is skipped too, and the budgets grow at once (`packer.settle`)."""
        loss_bad, grad_bad, overflow = (bool(f) for f in flags)
        if not (loss_bad or grad_bad or overflow):
            self.bad_run = 0
            return
        self.skipped += 1
        if not (loss_bad or grad_bad):
            packer.settle()
            progress.warn(f"step {done}: more samples than the sample budget held, step skipped ({self.skipped} so "
                          "far); the budget grows")
            return
        self.bad_run += 1
        progress.warn(f"step {done}: non-finite {'loss' if loss_bad else 'gradient'}, "
                      f"step skipped ({self.skipped} so far)")
        # Skipping cannot help when the parameters themselves are gone (an overflowing step).
        if not all(bool(torch.isfinite(p).all()) for p in params):
            raise BoostNerfError(f"training diverged: the parameters became non-finite by step {done} (an "
                                 f"optimiser step overflowed); {kept(checkpoint)}: lower the learning rates in the "
                                 "recipe")
        if self.bad_run >= sched.max_bad_steps:
            raise BoostNerfError(f"training diverged: {self.bad_run} consecutive steps had a non-finite loss or "
                                 f"gradient (last at step {done}); {kept(checkpoint)}: lower the learning rates in the "
                                 "recipe or check the data")

    def log(self, done: int, logs: dict, seconds: float, sched: Schedule) -> dict[str, float] | None:
        """Add a step's PSNR to the trend; at a logging step, an entry of the history (the one time a step's logs are
        read from the device). -> that step's logs, as numbers (None off a logging step)."""
        self.trend.add(logs.get("psnr"))
        if done % sched.log_every and done != sched.iters:
            return None
        logs = _floats(logs)
        entry = {"step": done, "seconds": round(seconds, 2), **logs}
        mean = self.trend.close_interval()
        if mean is not None:
            entry["psnr_mean"] = round(mean, 3)
        self.history.append(entry)
        return logs


def cuda_rng_state(device: torch.device) -> Tensor | None:
    """The random state of the CUDA device training draws on (each ray's jitter), for a checkpoint; None off CUDA.
    Only this device's: a checkpoint must resume on a machine with fewer GPUs visible."""
    return torch.cuda.get_rng_state(device) if device.type == "cuda" else None


def restore_cuda_rng(state: Tensor | None, device: torch.device) -> None:
    """Give `device` the state `cuda_rng_state` saved; nothing off CUDA."""
    if state is not None and device.type == "cuda":
        torch.cuda.set_rng_state(state, device)


def kept(path: Path | None) -> str:
    """What a stopped run keeps, for its error message."""
    if path is None:
        return "this short stage keeps no checkpoint"
    if path.exists():
        return f"the last good checkpoint {path} is kept (rerunning resumes from it)"
    return "no checkpoint had been written yet"


class TrainCheckpoint:
    """A run's resumable state in one file, written atomically: the task's state, the optimiser's, the run's
    counters (`RunState`), the batch generator's, torch's and the CUDA device's random states (a resumed run draws
    what an uninterrupted one does), and `signature`, the settings that define what is trained.

    A checkpoint of another signature is refused, or with `restart_other` (pretrain's and finetune's --force)
    dropped: the model trains from its first step. A checkpoint of the same settings is resumed either way (an
    interrupted --force run goes on when rerun). A state with non-finite values is never written.
    """

    def __init__(self, path: Path, signature: dict | None = None, restart_other: bool = False):
        self.path, self.signature, self.restart_other = path, signature, restart_other

    def load(self) -> dict | None:
        """The saved state, None when there is no file; one line for a damaged one."""
        if not self.path.exists():
            return None
        try:
            state = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception as e:  # a damaged checkpoint: say so, do not train from a wrong state
            raise BoostNerfError(f"training checkpoint {self.path} is damaged ({type(e).__name__}); delete it to "
                                 "restart this model") from None
        if not isinstance(state, dict):
            raise BoostNerfError(f"training checkpoint {self.path} is not a boostnerf training state; "
                                 "delete it to restart this model")
        if state.get("format_version") != FORMAT_VERSION:
            raise BoostNerfError(f"training checkpoint {self.path} has file format {state.get('format_version')!r}, "
                                 f"and this boostnerf reads format {FORMAT_VERSION!r}: delete it to restart this model")
        checksum = state.pop("checksum", None)
        if checksum is not None and state_checksum(state) != checksum:
            raise BoostNerfError(f"training checkpoint {self.path} is damaged: its numbers are not those written with "
                                 "it (their checksum differs); delete it to restart this model")
        return state

    def resume(self, task: TrainTask, gen: torch.Generator,
               device: torch.device) -> tuple[Adam | None, RunState]:
        """Bring `task`, a new optimiser, `gen` and torch's random states back to the saved state, when
        `lineage.decide` resumes it. -> (the optimiser, the run's counters); (None, a new run) when there is
        nothing to resume (no checkpoint, or --force over one of other settings, which is overwritten later)."""
        state = self.load()
        if state is None:
            return None, RunState()
        try:
            found = Found(str(self.path), state.get("signature"), checkpoint=True)
            if decide(found, self.signature, self.restart_other).check().action == MAKE:
                return None, RunState()
            task.load_state(state["task"])
            opt = make_optimizer(task)
            rates = [g["initial_lr"] for g in opt.param_groups]  # this run's recipe's learning rates
            opt.load_state_dict(state["optim"])
            for g, lr in zip(opt.param_groups, rates):  # the state brought back the interrupted run's; a diverged run
                g["initial_lr"] = lr  # resumed with lower rates (the advice it gives) trained on at the old ones
            run = RunState(int(state["step"]), float(state["seconds"]), int(state["skipped"]), list(state["history"]))
            run.trend.load_state(state["trend"])
            gen.set_state(state["gen"])
            torch.set_rng_state(state["rng"])
            restore_cuda_rng(state.get("cuda_rng"), device)
        except MALFORMED as e:
            raise BoostNerfError(f"training checkpoint {self.path} does not hold this model's training state "
                                 f"({malformed(e)}); delete it to restart this model") from None
        return opt, run

    def save(self, task: TrainTask, opt: Adam, run: RunState, gen: torch.Generator,
             device: torch.device) -> None:
        """Write the resumable state atomically; a state with NaN or infinity stops the run instead
        (the previous checkpoint stays, so nothing before it is lost)."""
        task_state, optim_state = task.state(), opt.state_dict()
        bad = _non_finite_entry(task_state) or _non_finite_entry(optim_state, "optimiser")
        if bad is not None:
            raise BoostNerfError(f"training diverged: {bad} holds non-finite values at step {run.step}, so it is not "
                                 f"checkpointed; {kept(self.path)}: lower the learning rates in the recipe or check "
                                 "the data")
        state = {
            "task": task_state, "optim": optim_state, "step": run.step, "seconds": run.seconds,
            "skipped": run.skipped, "history": run.history, "gen": gen.get_state(), "rng": torch.get_rng_state(),
            "cuda_rng": cuda_rng_state(device), "signature": self.signature, "trend": run.trend.state(),
            "format_version": FORMAT_VERSION,
        }
        save_torch(self.path, {**state, "checksum": state_checksum(state)})  # checked by `load`


def _check_rays(rays: RayData, sched: Schedule, title: str, parallel: bool) -> None:
    if len(rays) == 0:  # torch.randint over no rays raised "random_ expects 'from' to be less than 'to'"
        raise BoostNerfError(f"{title}: no training ray crosses the box this model is trained in: if the recipe sets "
                             "data.bbox, it must hold what the cameras see")
    if parallel and sched.batch_rays % dist.world_size():
        raise BoostNerfError(f"train.batch_rays ({sched.batch_rays}) must be divisible by the number of processes "
                             f"({dist.world_size()}) to split every batch evenly: change one of them")


def train(task: TrainTask, rays: RayData, sched: Schedule, seed: int, title: str,
          checkpoint: TrainCheckpoint | None = None, data_parallel: bool = False) -> TrainResult:
    """Run `sched.iters` steps of `task` on random batches of `rays`, resuming from `checkpoint` (written every
    `sched.checkpoint_every` steps and after the last). A non-finite loss or gradient skips the step (`RunState.guard`).

    `data_parallel` under torchrun: every rank draws the same global batch, trains on its shard, and the gradients
    are averaged (`batch_gradients`), so a step is the one-process step on the whole batch; every rank keeps the
    same state, rank 0 alone prints and writes the checkpoint, which does not depend on the number of ranks.
    """
    parallel = data_parallel and dist.world_size() > 1
    _check_rays(rays, sched, title, parallel)
    device = rays.origins.device
    gen = torch.Generator(device="cpu").manual_seed(seed)
    torch.manual_seed(seed)
    opt, run = checkpoint.resume(task, gen, device) if checkpoint is not None else (None, RunState())
    progress = Progress(title, sched.iters, run.step, sched.log_every, quiet=parallel and not dist.is_main())
    if run.step > 0:
        progress.say(f"resuming from {checkpoint.path} at step {run.step}/{sched.iters}")
    startup = CLOCK.ready(title)
    t0 = time.perf_counter() - run.seconds
    outcomes = Outcomes(device, getattr(task, "packer", None))
    try:
        for step in range(run.step, sched.iters):
            # --- one step: batch, gradient, update (the rest of the loop is bookkeeping) ---
            opt, result = optimizer_step(task, rays, sched, opt, gen, step, parallel)
            run.step = step + 1
            saving = checkpoint is not None and (run.step % sched.checkpoint_every == 0 or run.step == sched.iters)
            logging_step = run.step % sched.log_every == 0 or run.step == sched.iters
            # --- the steps' outcomes as they arrive (every one on a logging or checkpoint step), log, checkpoint ---
            outcomes.push(run.step, result)
            for done, flags in outcomes.ready(wait=logging_step or saving):
                run.guard(done, flags, sched, checkpoint and checkpoint.path, progress, result.params, outcomes.packer)
            logs = run.log(run.step, result.logs, time.perf_counter() - t0, sched)
            if logs is not None and (warning := run.trend.falling_warning(run.step)):
                progress.warn(warning)
            progress.update(run.step, logs)
            if saving:
                run.seconds = time.perf_counter() - t0
                save = partial(checkpoint.save, task, opt, run, gen, device)
                if parallel:
                    dist.on_main(save)  # one file for all ranks (they hold the same state)
                else:
                    save()
    finally:
        progress.close()
    return TrainResult(sched.iters, time.perf_counter() - t0, run.skipped, run.history, round(startup, 2))
