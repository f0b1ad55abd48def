"""One training loop for every stage that trains (pretrain, finetune, baseline).

The loop owns batching, the optimiser and its schedule, the NaN guard, progress output and
resumable checkpoints. What is trained, how rays are rendered and what the loss is are passed in
(`TrainTask`), so the loop knows nothing of experts or mixtures.
"""

from __future__ import annotations

import math
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

from boostnerf_cli import distributed as dist
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import NDC, image_rays, intersect_box
from boostnerf_cli.scenes.scene import Split
from boostnerf_cli.workspace import MALFORMED, kill_point_for_tests, malformed, save_torch


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
                   keep_alpha: bool = False) -> "RayData":
        """`keep_alpha`: keep the split's alpha (when its images had one), for a loss that composites the pixels on
        another colour than the scene's background (`train.random_background`)."""
        # Two passes over the views: which rays hit the box, then the table filled in place. Building every view's
        # rays and concatenating them held about 85 bytes per training pixel at the peak, 2.4x the 36 of the table
        # (300 views at 800 px: 16 GB); now the table and one view's rays. The split's rays are built where its
        # images are (the CPU); the box may be on the model's device.
        box = bbox.to(split.poses.device)
        hits = []
        for i in range(len(split)):
            o, d = image_rays(split.poses[i], split.intrinsics[i], split.height, split.width, ndc)
            # A ray that misses the box renders the background exactly: nothing to learn from it.
            hits.append(intersect_box(o, d, box, near, far)[2])
        n = sum(int(h.sum()) for h in hits)
        origins, dirs, rgb = (torch.empty(n, 3, dtype=split.images.dtype) for _ in range(3))
        alpha = torch.empty(n, dtype=split.images.dtype) if keep_alpha and split.alpha is not None else None
        at = 0
        for i, hit in enumerate(hits):
            o, d = image_rays(split.poses[i], split.intrinsics[i], split.height, split.width, ndc)
            k = int(hit.sum())
            origins[at : at + k], dirs[at : at + k] = o[hit], d[hit]
            rgb[at : at + k] = split.images[i].reshape(-1, 3)[hit]
            if alpha is not None:
                alpha[at : at + k] = split.alpha[i].reshape(-1)[hit]
            at += k
        return RayData(origins, dirs, rgb, alpha)

    def to(self, device: torch.device | str) -> "RayData":
        return RayData(self.origins.to(device), self.dirs.to(device), self.rgb.to(device),
                       None if self.alpha is None else self.alpha.to(device))

    def __len__(self) -> int:
        return self.origins.shape[0]


@dataclass
class Schedule:
    """Optimiser settings shared by all stages."""

    iters: int
    batch_rays: int = 4096
    lr_decay: float = 0.1  # learning rates fall exponentially to this fraction at the last step
    log_every: int = 100
    checkpoint_every: int = 500
    max_bad_steps: int = 20  # consecutive non-finite steps before the run stops


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


class PsnrTrend:
    """The mean training PSNR of each logging interval, and a warning when it falls for `intervals` intervals
    in a row by `min_drop` dB in all (a falling train PSNR means the run is losing what it had learnt)."""

    def __init__(self, intervals: int = 3, min_drop: float = 0.5):
        self.intervals, self.min_drop = intervals, min_drop
        self.total, self.count, self.means, self.warned = 0.0, 0, [], False

    def state(self) -> dict:
        """What a checkpoint keeps, so that a resumed run logs the same means and warns at the same step."""
        return {"total": self.total, "count": self.count, "means": list(self.means), "warned": self.warned}

    def load_state(self, state: dict) -> None:
        self.total, self.count = float(state["total"]), int(state["count"])
        self.means, self.warned = [float(m) for m in state["means"]], bool(state["warned"])

    def add(self, psnr: float | None) -> None:
        if psnr is not None and math.isfinite(psnr):
            self.total, self.count = self.total + psnr, self.count + 1

    def close_interval(self) -> float | None:
        mean = self.total / self.count if self.count else None
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
            return (f"warning: the train PSNR fell for {self.intervals} logging intervals in a row "
                    f"({last[0]:.2f} -> {last[-1]:.2f} dB by step {step}). Likely causes: skipping cut away structure "
                    "the training views show (compare with `pretrain --no-skip`), or learning rates too high for "
                    "this scene (lower train.lr_grid / lr_mlp)")
        return None


class Progress:
    """A rich progress bar on a terminal, plain periodic log lines otherwise; nothing when `quiet`."""

    def __init__(self, title: str, total: int, start: int, log_every: int, quiet: bool = False):
        self.title, self.total, self.log_every, self.quiet = title, total, log_every, quiet
        self.bar = None
        if sys.stderr.isatty() and not quiet:
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

    def update(self, step: int, logs: dict[str, float]) -> None:
        info = " ".join(f"{k}={v:.4g}" for k, v in logs.items())
        if self.bar is not None:
            self.bar.update(self.task, completed=step, info=info)
        elif not self.quiet and (step % self.log_every == 0 or step == self.total):
            print(f"[{self.title}] step {step}/{self.total} {info}", file=sys.stderr, flush=True)

    def warn(self, msg: str) -> None:
        if self.bar is not None:
            self.bar.console.print(f"[{self.title}] {msg}", markup=False, highlight=False)
        elif not self.quiet:
            print(f"[{self.title}] {msg}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def make_optimizer(task: TrainTask) -> torch.optim.Optimizer:
    groups = task.param_groups()
    for g in groups:
        g.setdefault("initial_lr", g["lr"])
    return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, fused=True)


def _set_lr(opt: torch.optim.Optimizer, step: int, sched: Schedule) -> None:
    factor = sched.lr_decay ** (step / max(1, sched.iters))
    for g in opt.param_groups:
        g["lr"] = g["initial_lr"] * factor


def all_finite(params: list[Tensor]) -> bool:
    """True when no gradient holds a NaN or an infinity: one sum per gradient tensor. A sum is NaN or
    +-inf when any entry is (+inf and -inf together give NaN); finite entries whose sum overflows float32
    are refused too, as a gradient that large should be. Measured on CPU over an 80^3 DVGO expert's 6.7M
    gradients, one thread: 0.9 ms, against 29 ms for a fused max-norm (`_foreach_norm(inf)`, slow on CPU)
    and ~20% of a small expert's step for an `isfinite` pass per tensor."""
    grads = [p.grad for p in params if p.grad is not None]
    return not grads or bool(torch.stack([g.sum() for g in grads]).isfinite().all())


def _non_finite_entry(obj, where: str = "") -> str | None:
    """The first floating-point tensor in a nested state holding NaN or infinity, by its path; None if none."""
    if isinstance(obj, Tensor):
        return where if obj.is_floating_point() and not bool(torch.isfinite(obj).all()) else None
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, (list, tuple)) else ()
    for k, v in items:
        found = _non_finite_entry(v, f"{where}.{k}" if where else str(k))
        if found is not None:
            return found
    return None


# how a setting of a training signature is given, for messages (others are named by their recipe key)
SETTING_NAMES = {"iters": "--iters", "seed": "--seed", "lam": "--lambda", "penalty": "--penalty",
                 "renormalize": "--renormalize", "wide_steps": "--wide-start (in steps)", "gate_noise": "--gate-noise",
                 "topk": "--topk", "train": "the recipe's train section"}


def setting_change(key: str, was, now) -> str:
    """`key: was, now now` for a message, with the flag's name and "the default" for a setting left at it. A changed
    source (`from`, the digest of moe/init or of the baseline's expert) is said as such, its digests shortened."""
    if key == "from":
        digests = f" (digest {was[:8]}..., now {now[:8]}...)" if isinstance(was, str) and isinstance(now, str) else ""
        return f"the model it is trained from was made again since{digests}"
    was, now = (("the default" if v is None else repr(v)) for v in (was, now))
    return f"{SETTING_NAMES.get(key, key)}: {was}, now {now}"


def first_difference(saved: dict, wanted: dict) -> str | None:
    """The first key (in sorted order) whose value differs between two signatures, or None when they agree."""
    return next((key for key in sorted(set(saved) | set(wanted)) if saved.get(key) != wanted.get(key)), None)


# Signature entries for the training settings that shape a model (`train`, finetune's `lam`): a checkpoint names
# them when they differ from the defaults. A checkpoint without a PSNR trend was written by an older boostnerf,
# which may not have recorded them at all: their absence there says nothing.
LATE_SETTINGS = ("train", "lam")


def unrecorded_settings(state: dict, wanted: dict | None) -> list[str]:
    """The settings of `wanted` that the checkpoint `state`, written by an earlier boostnerf, may not have recorded."""
    saved = state.get("signature")
    if saved is None or wanted is None or state.get("trend") is not None:
        return []
    return [key for key in LATE_SETTINGS if key in wanted and key not in saved]


def _difference(saved: dict | None, wanted: dict | None, unrecorded: list[str]) -> str | None:
    """The first setting in which a checkpoint's signature differs from this run's, leaving out the settings it
    could not record (`unrecorded_settings`); None when they agree or either is missing."""
    if saved is None or wanted is None:
        return None
    return first_difference({**saved, **{key: wanted[key] for key in unrecorded}}, wanted)


def batch_gradients(task: TrainTask, rays: RayData, idx: Tensor, step: int,
                    parallel: bool = False) -> tuple[bool, bool, dict[str, float]]:
    """The loss of the batch `idx` and its gradient, accumulated in the parameters' .grad.

    -> (learnable: the loss depends on the parameters (False when every sample was skipped), the loss is
    finite, logs); a non-finite loss is not backpropagated. `parallel` (data parallel): `idx` is the
    global batch and this rank takes its shard, with the random draws its rays get in the global batch
    (`distributed.rng_share`); the ranks' gradients are then combined by `distributed.average_gradients`.
    """
    if parallel:
        idx = dist.shard(idx)
    with dist.rng_share(len(idx), rays.origins.device) if parallel else nullcontext():
        alpha = None if rays.alpha is None else rays.alpha[idx]
        loss, logs = task.loss(rays.origins[idx], rays.dirs[idx], rays.rgb[idx], alpha, step)
    finite = bool(torch.isfinite(loss))
    if loss.requires_grad and finite:
        loss.backward()
    return loss.requires_grad, finite, logs


@dataclass
class Step:
    """What one optimiser step did: `learnable` (False when every sample of the batch was skipped: nothing to
    learn), `finite_loss`, `applied` (the update was taken: a finite loss and finite gradients), the logs, and the
    parameters it updates."""

    learnable: bool
    finite_loss: bool
    applied: bool
    logs: dict[str, float]
    params: list[Tensor]


def optimizer_step(task: TrainTask, rays: RayData, sched: Schedule, opt: torch.optim.Optimizer | None,
                   gen: torch.Generator, step: int, parallel: bool) -> tuple[torch.optim.Optimizer | None, Step]:
    """One training step: the optimiser (re)built when the task changed its parameters (`before_step`), the step's
    learning rates, a batch drawn from `gen`, its gradient (data parallel: averaged over the ranks), and the update
    when the loss and every gradient are finite (else the gradients are dropped). -> (the optimiser, the step)."""
    learnable, finite_loss, logs, failure = False, True, {}, None
    try:
        if task.before_step(step) or opt is None:
            opt = make_optimizer(task)
        _set_lr(opt, step, sched)
        idx = torch.randint(0, len(rays), (sched.batch_rays,), generator=gen).to(rays.origins.device)
        opt.zero_grad(set_to_none=True)
        learnable, finite_loss, logs = batch_gradients(task, rays, idx, step, parallel)
    except Exception as e:
        if not parallel:
            raise
        failure = e  # every rank stops with this rank's message (in average_gradients)
    params = [p for g in opt.param_groups for p in g["params"]] if opt is not None else []
    if parallel:
        learnable, finite_loss, logs = dist.average_gradients(params, learnable, finite_loss, logs, failure)
    applied = learnable and finite_loss and all_finite(params)
    if applied:
        opt.step()
    elif learnable:
        opt.zero_grad(set_to_none=True)
    return opt, Step(learnable, finite_loss, applied, logs, params)


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

    def guard(self, step: Step, done: int, sched: Schedule, checkpoint: Path | None, progress: Progress) -> None:
        """The NaN guard, after a learnable step: a skipped step is counted and said; the run stops when the
        parameters themselves are no longer finite (an overflowing update) or after `sched.max_bad_steps`
        consecutive skipped steps (its message says what the `checkpoint` keeps)."""
        if step.applied:
            self.bad_run = 0
            return
        self.skipped += 1
        self.bad_run += 1
        progress.warn(f"step {done}: non-finite {'gradient' if step.finite_loss else 'loss'}, "
                      f"step skipped ({self.skipped} so far)")
        # Skipping cannot help when the parameters themselves are gone (an overflowing step).
        if not all(bool(torch.isfinite(p).all()) for p in step.params):
            raise BoostNerfError(f"training diverged: the parameters became non-finite by step {done} (an "
                                 f"optimiser step overflowed); {kept(checkpoint)}: lower the learning rates in the recipe")
        if self.bad_run >= sched.max_bad_steps:
            raise BoostNerfError(f"training diverged: {self.bad_run} consecutive steps had a non-finite loss or "
                                 f"gradient (last at step {done}); {kept(checkpoint)}: lower the learning rates in the recipe "
                                 "or check the data")

    def log(self, done: int, logs: dict[str, float], seconds: float, sched: Schedule) -> str | None:
        """Add a step's PSNR to the trend; at a logging step, an entry of the history. -> a falling-PSNR warning."""
        self.trend.add(logs.get("psnr"))
        if done % sched.log_every and done != sched.iters:
            return None
        entry = {"step": done, "seconds": round(seconds, 2), **logs}
        mean = self.trend.close_interval()
        if mean is not None:
            entry["psnr_mean"] = round(mean, 3)
        self.history.append(entry)
        return self.trend.falling_warning(done)


def cuda_rng_state(device: torch.device) -> Tensor | None:
    """The random state of the CUDA device training draws on (each ray's jitter), for a checkpoint; None off CUDA.
    Only this device's: a checkpoint must resume on a machine with fewer GPUs visible."""
    return torch.cuda.get_rng_state(device) if device.type == "cuda" else None


def restore_cuda_rng(state: Tensor | list | None, device: torch.device) -> None:
    """Give `device` the state `cuda_rng_state` saved. A checkpoint of an older boostnerf holds every visible GPU's
    state (`get_rng_state_all`, which `set_rng_state_all` cannot put back with fewer GPUs): the entry of `device`'s
    index, if there is one. Nothing off CUDA."""
    if state is None or device.type != "cuda":
        return
    if isinstance(state, (list, tuple)):
        index = device.index if device.index is not None else torch.cuda.current_device()
        if index >= len(state):
            return
        state = state[index]
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
        self.unrecorded: list[str] = []  # settings an earlier boostnerf's checkpoint did not record

    def load(self) -> dict | None:
        """The state to resume from; None when there is none (no file, or --force over other settings)."""
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
        self.unrecorded = unrecorded_settings(state, self.signature)
        if self.restart_other and _difference(state.get("signature"), self.signature, self.unrecorded) is not None:
            self.unrecorded = []
            return None  # --force: a checkpoint of other settings is dropped (overwritten later)
        return state

    def _check_signature(self, saved: dict | None) -> None:
        """Refuse to resume a checkpoint written with settings that change what is being trained."""
        if (key := _difference(saved, self.signature, self.unrecorded)) is None:
            return
        change = setting_change(key, saved.get(key), self.signature.get(key))
        raise BoostNerfError(f"training checkpoint {self.path} was written with other settings ({change}): rerun "
                             "with the settings it was made with to resume, add --force to restart this model with "
                             "these, or delete it")

    def resume(self, task: TrainTask, gen: torch.Generator,
               device: torch.device) -> tuple[torch.optim.Optimizer | None, RunState]:
        """Bring `task`, a new optimiser, `gen` and torch's random states back to the saved state.
        -> (the optimiser, the run's counters); (None, a new run) when there is nothing to resume."""
        state = self.load()
        if state is None:
            return None, RunState()
        try:
            self._check_signature(state.get("signature"))
            task.load_state(state["task"])
            opt = make_optimizer(task)
            rates = [g["initial_lr"] for g in opt.param_groups]  # this run's recipe's learning rates
            opt.load_state_dict(state["optim"])
            for g, lr in zip(opt.param_groups, rates):  # the state brought back the interrupted run's; a diverged run
                g["initial_lr"] = lr  # resumed with lower rates (the advice it gives) trained on at the old ones
            run = RunState(int(state["step"]), float(state["seconds"]), int(state["skipped"]), list(state["history"]))
            if state.get("trend") is not None:  # an older boostnerf's checkpoints do not keep it
                run.trend.load_state(state["trend"])
            gen.set_state(state["gen"])
            torch.set_rng_state(state["rng"])
            restore_cuda_rng(state.get("cuda_rng"), device)
        except MALFORMED as e:
            raise BoostNerfError(f"training checkpoint {self.path} does not hold this model's training state "
                                 f"({malformed(e)}); delete it to restart this model") from None
        return opt, run

    def save(self, task: TrainTask, opt: torch.optim.Optimizer, run: RunState, gen: torch.Generator,
             device: torch.device) -> None:
        """Write the resumable state atomically; a state with NaN or infinity stops the run instead
        (the previous checkpoint stays, so nothing before it is lost)."""
        task_state, optim_state = task.state(), opt.state_dict()
        bad = _non_finite_entry(task_state) or _non_finite_entry(optim_state, "optimiser")
        if bad is not None:
            raise BoostNerfError(f"training diverged: {bad} holds non-finite values at step {run.step}, so it is not "
                                 f"checkpointed; {kept(self.path)}: lower the learning rates in the recipe or check "
                                 "the data")
        save_torch(self.path, {
            "task": task_state, "optim": optim_state, "step": run.step, "seconds": run.seconds,
            "skipped": run.skipped, "history": run.history, "gen": gen.get_state(), "rng": torch.get_rng_state(),
            "cuda_rng": cuda_rng_state(device), "signature": self.signature, "trend": run.trend.state(),
        })
        kill_point_for_tests("checkpoint")  # inert unless a resume test asks for it (workspace.TEST_KILL_ENV)


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
        progress.warn(f"resuming from {checkpoint.path} at step {run.step}/{sched.iters}")
    if checkpoint is not None and checkpoint.unrecorded:
        progress.warn(f"note: {checkpoint.path} comes from an earlier boostnerf, which did not record "
                      f"{' or '.join(SETTING_NAMES.get(k, k) for k in checkpoint.unrecorded)}; resuming with this run's")
    t0 = time.perf_counter() - run.seconds
    try:
        for step in range(run.step, sched.iters):
            # --- one step: batch, gradient, update (the rest of the loop is bookkeeping) ---
            opt, result = optimizer_step(task, rays, sched, opt, gen, step, parallel)
            run.step = step + 1
            if result.learnable:
                run.guard(result, run.step, sched, checkpoint and checkpoint.path, progress)
            # --- log and checkpoint ---
            warning = run.log(run.step, result.logs, time.perf_counter() - t0, sched)
            if warning:
                progress.warn(warning)
            progress.update(run.step, result.logs)
            if checkpoint is not None and (run.step % sched.checkpoint_every == 0 or run.step == sched.iters):
                run.seconds = time.perf_counter() - t0
                save = partial(checkpoint.save, task, opt, run, gen, device)
                if parallel:
                    dist.on_main(save)  # one file for all ranks (they hold the same state)
                else:
                    save()
    finally:
        progress.close()
    return TrainResult(sched.iters, time.perf_counter() - t0, run.skipped, run.history)
