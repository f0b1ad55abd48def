"""Top-k routing, sparse dispatch and the resolution-weighted auxiliary loss (pure functions).

Shapes: N samples, M experts, k chosen experts per sample.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.limits import MAX_LOSS_WEIGHT, OneOfOrNumbers, Range, comma_numbers
from boostnerf_cli.render.packing import DYNAMIC, Packer
from boostnerf_cli.render.timing import part

PENALTIES = ("geometric", "linear", "quadratic", "none")
# moe.penalty: a named scheme, or explicit weights "w_0, w_1, ..." (`penalty_weights`)
PENALTY_RULE = OneOfOrNumbers(PENALTIES, Range(0, MAX_LOSS_WEIGHT, lo_open=True))


def explicit_weights(kind: str) -> list[float] | None:
    """The weights a penalty of the form "1, 1.5, 2.23" lists (one per expert, smallest first), or None for a
    named scheme (or text that is not numbers)."""
    return None if kind in PENALTIES else comma_numbers(kind)


def check_penalty(kind: str, m: int) -> None:
    """A penalty is a named scheme or one positive, finite weight per expert (of the mixture's `m`)."""
    if not PENALTY_RULE.allows(kind):
        raise BoostNerfError(f"moe.penalty = {kind!r}: must be {PENALTY_RULE}, one per expert, e.g. \"1, 1.5, 2.23\"")
    weights = explicit_weights(kind)
    if weights is not None and len(weights) != m:
        raise BoostNerfError(f"moe.penalty = {kind!r} lists {len(weights)} weights but the mixture has {m} experts: "
                             f"give one weight per expert, smallest expert first")


def penalty_weights(m: int, kind: str, device=None) -> Tensor:
    """Per-expert weights w_i, i = 0..M-1 (experts ordered by size, smallest first).

    geometric: w_i = exp(ln M / (M - 1))^i = M^(i/(M-1))   (paper, default; w_0 = 1, w_{M-1} = M)
    linear:    w_{i+1} = w_i + 1, w_0 = 1
    quadratic: w_{i+1} = 2 w_i,   w_0 = 1   (the supplementary's name for a doubling progression)
    none:      w_i = 1
    "w_0, w_1, ...": these weights, one per expert (the official code's list is [1, 1.5, 2.23, 3, ...], its
    first M entries: "1, 1.5, 2.23" for M = 3; docs/paper-map.md)
    With M = 1 every named scheme gives w = [1].
    """
    check_penalty(kind, m)
    explicit = explicit_weights(kind)
    if explicit is not None:
        return torch.tensor(explicit, dtype=torch.float32, device=device)
    i = torch.arange(m, dtype=torch.float32, device=device)
    if m == 1 or kind == "none":
        return torch.ones(m, device=device)
    if kind == "geometric":
        return torch.exp(i * math.log(m) / (m - 1))
    if kind == "linear":
        return 1.0 + i
    return 2.0**i


def check_topk(k: int, experts: list[str], key: str) -> None:
    """The one check of k: 1 <= k <= M; `key` names where k came from (moe.topk, --topk) in the error."""
    if not 1 <= k <= len(experts):
        raise BoostNerfError(f"{key} = {k} but the mixture has {len(experts)} experts ({', '.join(experts)}): "
                             f"set {key} between 1 and {len(experts)}")


def top_k(probs: Tensor, k: int, renormalize: bool) -> tuple[Tensor, Tensor]:
    """probs (N, M) -> weights (N, k), expert indices (N, k); weights sum to 1 when renormalised.

    Renormalising one weight would make it the constant 1 and cut the gate off from the photometric
    loss, so for k = 1 the renormalised weight is a straight-through 1: its value is 1 (the chosen
    expert's output is used as is, not dimmed by a probability below 1) and its gradient is that of
    the raw probability, d w / d p = 1 (the paper's Algorithm 1 multiplies by the raw p).
    """
    if k == 1:  # the same choice and gradient as topk, without its sort (~1.7x faster on CPU)
        vals, idx = probs.max(dim=-1, keepdim=True)
    else:
        vals, idx = torch.topk(probs, k, dim=-1)
    return (renormalized(vals) if renormalize else vals), idx


def renormalized(vals: Tensor) -> Tensor:
    """The chosen probabilities (N, k) renormalised as `top_k` does: summing to 1; the straight-through 1 for k = 1."""
    if vals.shape[1] == 1:
        return vals - vals.detach() + 1.0
    return vals / vals.sum(-1, keepdim=True).clamp_min(1e-12)


def expert_counts(idx: Tensor, m: int, weight: Tensor | None = None) -> Tensor:
    """c_i: how many samples are dispatched to each expert, (M,) float32 (no gradient). `weight` (N,): each sample's
    share (0 for a pad of a static packing); a sum on the device, so nothing waits to learn the counts' length."""
    ones = torch.ones_like(idx, dtype=torch.float32) if weight is None else weight.to(torch.float32)[:, None].expand(
        idx.shape)
    return torch.zeros(m, device=idx.device).index_add_(0, idx.reshape(-1), ones.reshape(-1))


AUX_NORMS = ("batch", "counts")
AUX_SAMPLES = ("all", "visible")


def aux_loss(probs: Tensor, idx: Tensor, weights: Tensor, norm: str = "batch", sel: Tensor | None = None) -> Tensor:
    """L_rw-aux = M / Z^2 * sum_i c_i m_i w_i, m_i = sum over the batch of G(x)_i.

    probs (N, M) gate probabilities, idx (N, k) chosen experts, weights (M,), `sel` (N,) bool: the samples that form
    the batch (None: all; a static packing's pads, and samples the caller leaves out, are not in it). An empty batch
    gives 0.
    norm "batch":  Z = |B| = N, the paper's Eq. (the project's default);
    norm "counts": Z = sum_i c_i = k N, the official code's (EIDOSLAB/boost-your-nerf, instant-ngp/moe_main.py,
                   train_moe: `num_experts / sum(c_s)**2`), k^2 times smaller than "batch" for Top-k.
    Which samples form the batch (every routed sample, or the visible ones) is the caller's choice.
    """
    m = probs.shape[1]
    if sel is None:
        n = probs.shape[0]
        if n == 0:
            return probs.sum() * 0.0
        c = expert_counts(idx, m).to(probs.device)
        return m / aux_denominator(n, idx.shape[1], norm) ** 2 * (c * probs.sum(dim=0) * weights.to(probs)).sum()
    c = expert_counts(idx, m, sel).to(probs.device)
    mass = torch.where(sel[:, None], probs, probs.new_zeros(())).sum(dim=0)
    z = aux_denominator(sel.sum().to(probs.dtype), idx.shape[1], norm)
    return torch.where(z > 0, m / z.clamp_min(1) ** 2, 0.0) * (c * mass * weights.to(probs)).sum()


def aux_denominator(n, k: int, norm: str):
    """Z of the auxiliary loss for n routed samples (a number or a device count), k experts each: n ("batch") or
    sum_i c_i = k n ("counts")."""
    if norm not in AUX_NORMS:
        raise ValueError(f"unknown auxiliary-loss normalisation {norm!r}")
    return (float(n) if isinstance(n, int) else n) * (k if norm == "counts" else 1)


class Routes(NamedTuple):
    """Where each of N samples goes: weights (N, k) and indices (N, k) of its k experts out of m (`top_k`'s choice);
    `unit`: every weight is exactly 1 with no gradient (rendering's renormalised Top-1), so outputs are not scaled;
    `every`: idx is every expert for every sample, in order (the ensemble's uniform gate), so nothing is sorted."""

    vals: Tensor
    idx: Tensor
    m: int
    unit: bool = False
    every: bool = False


def take(x: Tensor, rows: Tensor | None) -> Tensor:
    """x's rows `rows` (`ExpertRows`' lists), or x itself for None (every sample, in order)."""
    return x if rows is None else x.index_select(0, rows)


class ExpertRows(NamedTuple):
    """The samples routed to each expert, listed once per density pass (the dynamic packing's path): for expert e,
    `rows[e]` (n_e,) the indices of its samples in order (None: every sample, `Routes.every`), `weights[e]` (n_e,)
    their routing weights (None: `unit`)."""

    rows: list[Tensor | None]
    weights: list[Tensor | None]

    @staticmethod
    def of(routes: Routes, min_weight: float = 0.0) -> "ExpertRows":
        """Each expert's samples and weights, from one sort of the N x k choices by expert (no per-sample blend of the
        k weights: a choice's weight is read where it was made). `min_weight` > 0, for two weights per sample that sum
        to 1: a choice weighing less is left out and the other one weighs 1 (`MixtureConfig.render_min_weight`)."""
        vals, idx, m, unit, every = routes
        if every:  # every sample to every expert: the lists are the samples themselves, their weights a column each
            return ExpertRows([None] * m, [None] * m if unit else list(vals.unbind(1)))
        k = idx.shape[1]
        flat, w = idx.reshape(-1), vals.reshape(-1)
        buckets = m  # the experts; a left-out choice goes to one more, after them, and is dropped after the sort
        if min_weight > 0 and not unit:
            flat = torch.where(w >= min_weight, flat, m)
            w = torch.where(w > 1 - min_weight, 1.0, w)
            buckets = m + 1
        if buckets <= 256:  # a stable sort of bytes: 3x faster than M comparisons and lists on a CPU (int64: 6x slower)
            flat = flat.to(torch.uint8)
        order = torch.argsort(flat, stable=True)  # each expert's choices together, in sample order
        counts = torch.bincount(flat, minlength=buckets).tolist()[:m]
        if buckets > m:
            order = order[: sum(counts)]
        # a choice's sample: its index over k (a shift for k a power of two: 4x faster than a division on the CPU)
        shift = k.bit_length() - 1
        samples = order if k == 1 else order >> shift if k == 1 << shift else torch.div(order, k, rounding_mode="floor")
        rows = list(samples.split(counts))
        weights = [None] * m if unit else list(w.index_select(0, order).split(counts))
        return ExpertRows(rows, weights)

    def run(self, run: Callable[[int, Tensor, Tensor], Tensor], out: Tensor, slots: Tensor | None = None) -> Tensor:
        """out (n, C) += each expert's weighted outputs: `run(e, rows, dest)` -> (len(rows), C) on its samples `rows`,
        whose outputs land at `out[dest]`. `slots` (N,) long, -1 where a sample is left out: only the others run, and
        sample `row` lands at `out[slots[row]]` (a colour pass over some of the density pass's samples); without it at
        `out[row]`. A list of None (every sample) passes `run` None for both without slots (all samples, in order),
        else the samples `slots` keeps. The same sums, in the same order, as `dispatch`."""
        with part("dispatch"):
            kept_all = None  # every sample's list, with slots: the samples they keep and where they land, made once
            for e, (rows, w) in enumerate(zip(self.rows, self.weights)):
                dest = rows
                if slots is not None and rows is None:
                    if kept_all is None:
                        kept = (slots >= 0).nonzero().squeeze(-1)
                        kept_all = (kept, slots.index_select(0, kept))
                    rows, dest = kept_all
                    w = None if w is None else w.index_select(0, rows)
                elif slots is not None:
                    at = slots.index_select(0, rows)
                    kept = (at >= 0).nonzero().squeeze(-1)
                    rows, dest = rows.index_select(0, kept), at.index_select(0, kept)
                    w = None if w is None else w.index_select(0, kept)
                if len(out if rows is None else rows) == 0:
                    continue
                with part(f"expert {e}"):
                    y = run(e, rows, dest)
                if w is not None:
                    y = y * w[:, None]
                if dest is None and y.dtype == out.dtype:  # every sample, in order: out[i] += y[i], as the index_add
                    out.add_(y)
                elif dest is None:  # another dtype: refused as the index_add refuses it, not rounded into out
                    out.index_add_(0, torch.arange(len(y), device=y.device), y)
                else:
                    out.index_add_(0, dest, y)
        return out


def dispatch(
    routes: Routes,
    run: Callable[[int, Tensor], Tensor],
    out_dim: int,
    like: Tensor,
    packer: Packer = DYNAMIC,
    live: Tensor | None = None,
    name: str = "expert",
    listed: ExpertRows | None = None,
) -> Tensor:
    """Sparse mixture: out[s] = sum_j vals[s, j] * run(idx[s, j], rows)[s], each expert run once.

    `run(e, rows)` evaluates expert e on sample rows `rows` (1-D LongTensor) -> (len(rows), out_dim). The samples
    routed to expert e (by any of their k choices; of the `live` ones, when given) are packed by `packer`
    (render/packing.py: dynamic, exactly them, in order; static, a fixed budget per expert and pass `name`), so every
    expert sees only the samples routed to it, and the outputs are weighted and added back. `like`: a tensor of the
    output's dtype and device. `listed`: the routes' `ExpertRows`, when the caller made them already. The dynamic
    packing lists each expert's samples once (`ExpertRows`). -> out (N, out_dim).
    """
    vals, idx, m, unit, _ = routes
    n, k = idx.shape
    if listed is not None or (not packer.static and live is None):
        listed = ExpertRows.of(routes) if listed is None else listed
        return listed.run(lambda e, r, _: run(e, r).reshape(n if r is None else len(r), out_dim),
                          like.new_zeros(n, out_dim))
    one = idx[:, 0] if k == 1 else None  # one expert a sample: its index is the choice, its weight the only one
    with part("dispatch"):
        out = like.new_zeros(n, out_dim)
        for e in range(m):
            hit = (one == e) if one is not None else idx == e
            chosen = hit if one is not None else hit.any(-1)
            rows = packer.pack(f"{name}{e}", chosen if live is None else chosen & live)
            if not packer.static and len(rows) == 0:
                continue
            with part(f"expert {e}"):
                y = run(e, rows.rows).reshape(len(rows), out_dim)
            if not unit:
                w = vals[:, 0] if one is not None else torch.where(hit, vals, vals.new_zeros(())).sum(-1)
                y = y * w[rows.rows][:, None]
            out = rows.add(out, y)
    return out
