"""Warm-starting factorised and hashed experts from the shared coarse geometry.

A dense grid reproduces a density exactly by setting its vertices (`DVGOExpert.init_density`); a
VM-factorised or hash-encoded expert cannot, so it is fitted: a few Adam steps of least squares
between the expert's pre-activation density and the target's (clamped to [-10, 10] around the
activation's shift, where softplus is already ~0 or ~linear), on random points of the box.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from boostnerf_cli.adam import Adam
from boostnerf_cli.fields.dvgo import raw_from_sigma

RAW_CLAMP = 10.0


def fit_density(raw: Callable[[Tensor], Tensor], params: list[Tensor], density: Callable[[Tensor], Tensor],
                bbox: Tensor, unit: float, shift: float, steps: int = 200, batch: int = 1 << 14,
                lr: float = 0.02, seed: int = 0) -> float:
    """Fit `raw(xyz)` (pre-activation, (N,)) so that softplus(raw + shift) / unit matches `density`,
    on `batch` uniform random points of the box per step.

    -> the final mean squared error of the pre-activation.
    """
    gen = torch.Generator(device="cpu").manual_seed(seed)
    opt = Adam([{"params": params, "lr": lr}], betas=(0.9, 0.99), eps=1e-15)
    lo, size = bbox[0], bbox[1] - bbox[0]
    err = float("nan")
    for _ in range(steps):
        xyz = lo + torch.rand(batch, 3, generator=gen).to(bbox) * size
        with torch.no_grad():
            target = (raw_from_sigma(density(xyz), unit, shift) + shift).clamp(-RAW_CLAMP, RAW_CLAMP) - shift
        loss = torch.mean((raw(xyz) - target) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        err = float(loss.detach())
    for p in params:
        p.grad = None
    return err


def fit_batch(shape: tuple[int, int, int]) -> int:
    """Points per warm-start step: twice the lattice's vertex count, between 1024 and 16384."""
    return int(min(1 << 14, max(1 << 10, 2 * shape[0] * shape[1] * shape[2])))
