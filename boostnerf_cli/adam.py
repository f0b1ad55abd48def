"""Adam as one fused kernel per parameter group, without torch.optim.

torch.optim's optimisers import the compiler stack (torch._dynamo) the first time one is built or stepped: 1.3 s of
every training stage's start-up on a 2-core CPU, more than the rest of it at 100 px. The update here is the kernel
`torch.optim.Adam(fused=True)` runs, `torch._fused_adam_`, with its step counts kept the same way (a float32 count on
the parameter's device, raised before the kernel and lowered again where `found_inf` skipped the update), so the
numbers are torch's, bit for bit (tests/test_train.py).

`found_inf` (a device scalar, 1 or 0) skips every update of a step on the device, without the host reading it: the
training loop sets it when a loss or gradient is not finite.
"""

from __future__ import annotations

import torch
from torch import Tensor


class Adam:
    """Adam over parameter groups {"params": [...], "lr": float, ...} (other keys are kept: the loop's initial_lr)."""

    def __init__(self, groups: list[dict], betas: tuple[float, float] = (0.9, 0.99), eps: float = 1e-15):
        self.param_groups = [{**g, "params": list(g["params"])} for g in groups]
        self.betas, self.eps = betas, eps
        self.state: dict[Tensor, dict[str, Tensor]] = {}
        self.found_inf: Tensor | None = None

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                p.grad = None

    def _state(self, p: Tensor) -> dict[str, Tensor]:
        if p not in self.state:
            self.state[p] = {"step": torch.zeros((), dtype=torch.float32, device=p.device),
                             "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                             "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
        return self.state[p]

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            states = [self._state(p) for p in params]
            steps = [s["step"] for s in states]
            torch._foreach_add_(steps, 1)
            torch._fused_adam_(params, [p.grad for p in params], [s["exp_avg"] for s in states],
                               [s["exp_avg_sq"] for s in states], [], steps, lr=group["lr"], beta1=self.betas[0],
                               beta2=self.betas[1], weight_decay=0.0, eps=self.eps, amsgrad=False, maximize=False,
                               grad_scale=None, found_inf=self.found_inf)
            if self.found_inf is not None:
                torch._foreach_sub_(steps, [self.found_inf] * len(steps))

    def state_dict(self) -> dict:
        """{"state": {index: its state}, "param_groups": [group with "params" as indices]}, indices counting the
        parameters over the groups in order (torch.optim's layout)."""
        index = {}
        groups = []
        for group in self.param_groups:
            ids = [index.setdefault(p, len(index)) for p in group["params"]]
            groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": ids})
        return {"state": {index[p]: dict(s) for p, s in self.state.items() if p in index}, "param_groups": groups}

    def load_state_dict(self, state: dict) -> None:
        """Take back a `state_dict` of an optimiser over parameters of the same shapes, in the same order."""
        params = [p for group in self.param_groups for p in group["params"]]
        if len(state["param_groups"]) != len(self.param_groups):
            raise ValueError(f"the state holds {len(state['param_groups'])} parameter groups, this optimiser "
                             f"{len(self.param_groups)}")
        for group, saved in zip(self.param_groups, state["param_groups"]):
            if len(saved["params"]) != len(group["params"]):
                raise ValueError("a parameter group of the state holds another number of parameters")
            group.update({k: v for k, v in saved.items() if k != "params"})
        self.state = {}
        for i, s in state["state"].items():
            p = params[int(i)]
            if any(s[k].shape != p.shape for k in ("exp_avg", "exp_avg_sq")):
                raise ValueError(f"the state of parameter {i} has shape {tuple(s['exp_avg'].shape)}, the parameter "
                                 f"{tuple(p.shape)}")
            self.state[p] = {k: v.to(device=p.device, dtype=torch.float32 if k == "step" else p.dtype)
                             for k, v in s.items()}
