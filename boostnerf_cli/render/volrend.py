"""Volume rendering as pure functions (no module state).

For samples i = 0..S-1 along a ray with density sigma_i >= 0 and step length delta_i:

    alpha_i = 1 - exp(-sigma_i * delta_i)            computed as -expm1(-sigma_i * delta_i)
    T_i     = prod_{j<i} (1 - alpha_j) = exp(-sum_{j<i} sigma_j * delta_j)
    w_i     = T_i * alpha_i
    C       = sum_i w_i c_i + (1 - sum_i w_i) * background

(The paper's Eq. 1 writes alpha_i = 1 - exp(sigma_i delta_i), dropping the minus sign.)
The transmittance is an exclusive cumulative sum in log space: log(1 - alpha_j) is exactly
-sigma_j * delta_j, so no log of a difference is ever taken, and densities up to 1e10 with steps up
to 1e3 stay finite in value and gradient. Weights along a ray sum to at most 1 (up to rounding).

Layout: padded (R, S) tensors, one row per ray; padding samples carry sigma = 0 (no effect).
Under CPU/CUDA autocast every step here runs in the input dtype (float32): cumsum, exp and expm1
are not downcast by autocast, and `accumulate` turns autocast off.
"""

from __future__ import annotations

import torch
from torch import Tensor

from boostnerf_cli.device import constant


def optical_depth(sigma: Tensor, delta: Tensor) -> Tensor:
    """sigma, delta (R, S) -> sigma * delta (R, S), non-negative."""
    return sigma * delta


def transmittance(tau: Tensor) -> Tensor:
    """Optical depths tau (R, S) -> T (R, S), T_i = exp(-sum_{j<i} tau_j) (exclusive cumsum)."""
    cum = torch.cumsum(tau, dim=-1)
    exclusive = torch.cat([torch.zeros_like(cum[..., :1]), cum[..., :-1]], dim=-1)
    return torch.exp(-exclusive)


def render_weights(sigma: Tensor, delta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """sigma, delta (R, S) -> weights w (R, S), alpha (R, S), transmittance T (R, S)."""
    tau = optical_depth(sigma, delta)
    alpha = -torch.expm1(-tau)
    trans = transmittance(tau)
    return trans * alpha, alpha, trans


def accumulate(weights: Tensor, values: Tensor) -> Tensor:
    """sum_i w_i v_i along the ray: weights (R, S), values (R, S, C) -> (R, C), in the weights' dtype.

    Autocast is off here: it would run this product in bfloat16/float16 (8/11-bit mantissas) and
    lose up to ~1e-2 of a pixel's colour; compositing stays in the ray dtype (docs/reliability.md)."""
    with torch.autocast(weights.device.type, enabled=False):
        return torch.einsum("rs,rsc->rc", weights, values.to(weights.dtype))


def composite(
    weights: Tensor, rgb: Tensor, t: Tensor, background: Tensor | tuple[float, float, float]
) -> tuple[Tensor, Tensor, Tensor]:
    """Colour, depth and opacity of rays.

    weights (R, S), rgb (R, S, 3), t (R, S) sample distances, background (3,)
    -> colour (R, 3) composited on the background, expected depth (R,) (sum w_i t_i, 0 where the
    ray is empty), accumulated opacity (R,).
    """
    acc = weights.sum(dim=-1)
    bg = background if isinstance(background, Tensor) else constant(tuple(background), rgb.device, rgb.dtype)
    color = accumulate(weights, rgb) + (1.0 - acc)[:, None] * bg
    depth = (weights * t).sum(dim=-1)
    return color, depth, acc


def distortion(weights: Tensor, deltas: Tensor) -> Tensor:
    """mip-NeRF 360's distortion loss per ray (R,), over intervals of lengths `deltas` laid end to end (R, S):

        sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 delta_i,   m_i the middle of interval i,

    in O(S) (the pairwise sum is 2 sum_i w_i (m_i W_{<i} - (w m)_{<i}), the intervals sorted). It pulls each ray's
    weight into one short stretch: no haze of floaters in front of the surface, no weight smeared behind it."""
    ends = torch.cumsum(deltas, dim=-1)
    mids = ends - 0.5 * deltas
    w_before = torch.cumsum(weights, dim=-1) - weights
    wm_before = torch.cumsum(weights * mids, dim=-1) - weights * mids
    pairs = 2 * (weights * (mids * w_before - wm_before)).sum(-1)
    return pairs + (weights ** 2 * deltas).sum(-1) / 3
