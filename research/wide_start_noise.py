"""Two finetuning switches kept out of the product: a wide start and noisy top-k gating.

Neither is in the paper nor in the official code, and neither showed a gain (docs/results.md: on lego at 100 px a
0.3 wide start gave Top-1 +0.16 dB once, within what a finetuning seed moves, and nothing on the 2 x 128 MLP
experts; gate noise 0.3 changed nothing and 1.0 cost 0.79 dB). This module patches them into `boostnerf finetune`:

    python research/wide_start_noise.py finetune -w WS --topk 1 --wide-start 0.3 [--gate-noise 0.3] [options]

--wide-start F   the first floor(F * moe.iters) joint steps route to k + 1 experts (renormalised), then to k: the
                 gate compares experts before the partition sets
--gate-noise S   training chooses experts by the top-k of log p + S * N(0, 1) and weights them by their noiseless
                 probabilities (Shazeer et al. 2017), so a Top-1 gate sees other experts too; rendering never adds it

Both act only on a trained gate that leaves experts out (not the ensemble, not k = M). A model finetuned with them
records them in its signature, so a plain `boostnerf finetune` refuses to skip it as its own.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import torch
from torch import Tensor

from boostnerf_cli import lineage
from boostnerf_cli.moe import mixture as mixture_module
from boostnerf_cli.stages import finetune as finetune_stage
from boostnerf_cli.tasks import MixtureTask

SWITCHES = {"--wide-start": ("wide_start", 0.0, 1.0), "--gate-noise": ("gate_noise", 0.0, 10.0)}  # [lo, hi)


@dataclass(frozen=True)
class Switches:
    wide_start: float = 0.0
    gate_noise: float = 0.0


def noisy_top_k(probs: Tensor, k: int, renormalize: bool, noise: float) -> tuple[Tensor, Tensor]:
    """`router.top_k` with the choice made on log p + noise * N(0, 1) (torch's global generator); the weights are the
    chosen experts' noiseless probabilities, renormalised as `router.top_k` does."""
    scores = probs.detach().clamp_min(1e-30).log() + noise * torch.randn_like(probs)
    idx = scores.argmax(dim=-1, keepdim=True) if k == 1 else torch.topk(scores, k, dim=-1).indices
    vals = probs.gather(-1, idx)
    if renormalize:
        vals = vals - vals.detach() + 1.0 if k == 1 else vals / vals.sum(-1, keepdim=True).clamp_min(1e-12)
    return vals, idx


@contextmanager
def noisy_routing(noise: float) -> Iterator[None]:
    """Mixtures choose their experts with `noisy_top_k` inside the block."""
    plain = mixture_module.top_k
    mixture_module.top_k = lambda probs, k, renormalize: noisy_top_k(probs, k, renormalize, noise)
    try:
        yield
    finally:
        mixture_module.top_k = plain


class SwitchedTask(MixtureTask):
    """`tasks.MixtureTask` with the switches: the routing is a function of the step alone (a resumed run routes as
    an uninterrupted one), the last step is always narrow, and the training renders alone are noisy."""

    switches = Switches()

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        sparse = self.mix.gate.cfg.gate_type != "uniform" and self.mix.cfg.topk < self.mix.m
        self.final = {"topk": self.mix.cfg.topk, "renormalize": self.mix.cfg.renormalize}
        self.wide_steps = int(self.switches.wide_start * self.rec.iters) if sparse else 0
        self.gate_noise = self.switches.gate_noise if sparse else 0.0

    def before_step(self, step: int) -> bool:
        routing = self.final if step >= self.wide_steps else {"topk": self.final["topk"] + 1, "renormalize": True}
        if any(getattr(self.mix.cfg, k) != v for k, v in routing.items()):
            self.mix.configure(**routing)
        return super().before_step(step)

    def loss(self, origins: Tensor, dirs: Tensor, rgb: Tensor, alpha: Tensor | None, step: int):
        if not self.gate_noise:
            return super().loss(origins, dirs, rgb, alpha, step)
        with noisy_routing(self.gate_noise):
            return super().loss(origins, dirs, rgb, alpha, step)


def take_switches(args: list[str]) -> tuple[Switches, list[str]]:
    """The switches given in `args` (`--wide-start F`, `--gate-noise=S`), and the other arguments."""
    values, rest, i = {}, [], 0
    while i < len(args):
        flag, _, inline = args[i].partition("=")
        if flag not in SWITCHES:
            rest.append(args[i])
            i += 1
            continue
        text = inline if inline else (args[i + 1] if i + 1 < len(args) else "")
        i += 1 if inline else 2
        name, lo, hi = SWITCHES[flag]
        try:
            value = float(text)
        except ValueError:
            raise SystemExit(f"error: {flag} needs a number, got {text!r}") from None
        if not lo <= value < hi:
            raise SystemExit(f"error: {flag} = {value:g}: must be in [{lo:g}, {hi:g})")
        values[name] = value
    return Switches(**values), rest


def patch(switches: Switches) -> None:
    """Finetune with `SwitchedTask`, and record the switches in the finetuned models' signatures."""
    SwitchedTask.switches = switches
    finetune_stage.MixtureTask = SwitchedTask
    plain = lineage.FinetuneSpec.signature
    extra = {k: v for k, v in vars(switches).items() if v}

    def signature(self) -> dict:
        return {**plain(self), **({"research": extra} if extra else {})}

    lineage.FinetuneSpec.signature = signature


def main(argv: list[str]) -> None:
    switches, rest = take_switches(argv)
    if rest[:1] != ["finetune"]:
        raise SystemExit("error: usage: python research/wide_start_noise.py finetune [--wide-start F] "
                         "[--gate-noise S] [boostnerf finetune options]")
    patch(switches)
    from boostnerf_cli.cli import main as cli_main

    sys.argv = ["boostnerf", *rest]
    cli_main()


if __name__ == "__main__":
    main(sys.argv[1:])
