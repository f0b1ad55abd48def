"""Warm-starting factorised and hashed experts from the shared coarse geometry.

A dense grid reproduces a density exactly by setting its vertices (`DVGOExpert.init_density`); a
VM-factorised or hash-encoded expert cannot, so it is fitted: a few Adam steps of least squares
between the expert's pre-activation density and the target's (clamped to [-10, 10] around the
activation's shift, where softplus is already ~0 or ~linear), on random points of the box.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import torch
from torch import Tensor

from boostnerf_cli.adam import Adam
from boostnerf_cli.fields.dvgo import raw_from_sigma

RAW_CLAMP = 10.0
FIT_LR = 0.02  # Adam's learning rate for the fit
FIT_SEED = 0  # the fit's points are drawn from their own generator: the same for every expert and every run


class Fittable(Protocol):
    """An expert whose density is fitted rather than set: softplus(raw_density(xyz) + shift) / unit over its box,
    for `cfg.fit_steps` steps of `fit_batch(shape)` points."""

    bbox: Tensor
    unit: float
    shift: float
    cfg: Any
    shape: tuple[int, int, int]

    def raw_density(self, xyz: Tensor) -> Tensor: ...


def fit_density(expert: Fittable, params: list[Tensor], density: Callable[[Tensor], Tensor]) -> float:
    """Fit `params` so that the expert's density, softplus(raw_density(xyz) + shift) / unit, matches `density`,
    on `fit_batch(expert.shape)` uniform random points of its box per step, for `expert.cfg.fit_steps` steps.

    -> the final mean squared error of the pre-activation.
    """
    unit, shift, bbox, batch = expert.unit, expert.shift, expert.bbox, fit_batch(expert.shape)
    gen = torch.Generator(device="cpu").manual_seed(FIT_SEED)
    opt = Adam([{"params": params, "lr": FIT_LR}], betas=(0.9, 0.99), eps=1e-15)
    lo, size = bbox[0], bbox[1] - bbox[0]
    err = float("nan")
    for _ in range(expert.cfg.fit_steps):
        xyz = lo + torch.rand(batch, 3, generator=gen).to(bbox) * size
        with torch.no_grad():
            target = (raw_from_sigma(density(xyz), unit, shift) + shift).clamp(-RAW_CLAMP, RAW_CLAMP) - shift
        loss = torch.mean((expert.raw_density(xyz) - target) ** 2)
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
