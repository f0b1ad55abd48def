"""ReLU MLPs (the experts' colour and density networks, the gate's network) with a CPU-friendly backward.

`MLP` is an `nn.Sequential(Linear, ReLU, ..., Linear)`: the same modules, parameter names and
checkpoints. Its training pass is one autograd node (`_ReluMLP`) instead of one per layer, for one
reason: the orientation of the backward's matrix products. Autograd computes a layer's gradients as
`g.T @ a` (weight) and `g @ W` (input) whatever the layer's shape; for a thin layer (few inputs, many
outputs: the gate's 8 -> 64, a colour MLP's 39 -> 64) that product runs 2-5x slower on a CPU than
the same product transposed, `(a.T @ g).T` and `(W.T @ g.T).T` (13k rows, one thread, MKL: 1.15
against 0.21 ms and 0.91 against 0.23 ms for 8 -> 64). The backward here picks the orientation from
the layer's shape (transposed when it has fewer inputs than outputs, measured faster for every shape
used here). The input's gradient of such a layer then arrives channels-first (a transposed view),
which is the layout the grid lookups' backward wants anyway (fields/grid.py). Without autograd (no
gradient needed) and under autocast the forward is plain `nn.Sequential`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class _ReluMLP(torch.autograd.Function):
    """x, W_0, b_0, ..., W_{n-1}, b_{n-1} -> y: n Linear layers with ReLU between them."""

    @staticmethod
    def forward(ctx, x: Tensor, *params: Tensor) -> Tensor:  # type: ignore[override]
        n = len(params) // 2
        acts = [x]  # the input of each layer (for layers > 0: the ReLU output, which its mask needs)
        h = x
        for i in range(n):
            h = torch.addmm(params[2 * i + 1], h, params[2 * i].t())
            if i < n - 1:
                h = h.clamp_min_(0)
                acts.append(h)
        ctx.save_for_backward(*acts, *params[0::2])
        return h

    @staticmethod
    def backward(ctx, g: Tensor):  # type: ignore[override]
        saved = ctx.saved_tensors
        n = len(saved) // 2
        acts, weights = saved[:n], saved[n:]
        needs = ctx.needs_input_grad
        grads: list[Tensor | None] = [None] * (2 * n)
        for i in reversed(range(n)):
            a, w = acts[i], weights[i]
            thin = w.shape[1] < w.shape[0]  # fewer inputs than outputs
            if needs[1 + 2 * i]:
                grads[2 * i] = ((a.t() @ g).t() if thin else g.t() @ a).contiguous()
            if needs[2 + 2 * i]:
                grads[2 * i + 1] = g.sum(0)
            if i == 0 and not needs[0]:
                break
            g = (w.t() @ g.t()).t() if thin else g @ w
            if i > 0:
                g = torch.ops.aten.threshold_backward(g, a, 0)
        return (g if needs[0] else None, *grads)


class MLP(nn.Sequential):
    """Linear layers of widths `dims` (input, hidden..., output) with ReLU between them."""

    def __init__(self, dims: list[int]):
        if len(dims) < 2:
            raise ValueError(f"an MLP needs an input and an output width, got {dims}")
        mods: list[nn.Module] = []
        for i in range(len(dims) - 1):
            mods.append(nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                mods.append(nn.ReLU(inplace=True))
        super().__init__(*mods)

    @property
    def linears(self) -> list[nn.Linear]:
        return [m for m in self if isinstance(m, nn.Linear)]

    def forward(self, x: Tensor) -> Tensor:  # type: ignore[override]
        if not torch.is_grad_enabled() or torch.is_autocast_enabled(x.device.type):
            return super().forward(x)  # autocast chooses each layer's precision itself
        return _ReluMLP.apply(x, *[p for lin in self.linears for p in (lin.weight, lin.bias)])
