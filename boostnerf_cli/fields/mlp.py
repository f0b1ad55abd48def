"""ReLU MLPs (the experts' colour and density networks, the gate's network).

`MLP` is an `nn.Sequential(Linear, ReLU, ..., Linear)`: the same modules, parameter names and
checkpoints. With gradients its forward is one autograd node (`_ReluMLP`) whose backward computes,
per layer i with input a_i and output gradient g_i, dW_i = g_i^T a_i, db_i = sum g_i and
da_i = g_i W_i (masked by the ReLU of layer i-1), taking each matrix product in the orientation that is
faster for the layer's shape (docs/benchmarks.md, "Session 6": thin layers' backward); equal to
`nn.Sequential`'s gradients (tests/test_mlp.py). Without gradients, and under autocast, it is plain
`nn.Sequential`.
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
        if not torch.is_grad_enabled() or torch.is_autocast_enabled(x.device.type) or torch.compiler.is_compiling():
            return super().forward(x)  # autocast chooses each layer's precision itself; the compiler fuses its own
        return _ReluMLP.apply(x, *[p for lin in self.linears for p in (lin.weight, lin.bias)])
