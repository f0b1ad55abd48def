"""The mixture of experts is itself a Field (the paper's Sec. 3 and Algorithm 1).

    skip(x)   = alpha_D(x) > T      V_D: a density volume initialised from the smallest expert (vd_source:
                                    smallest), or the largest expert's own density (largest, the official code)
    G(x)      = gate probabilities over the M experts
    K         = top-k(G(x))
    sigma_f   = sum_{i in K} g_i sigma_i(x),   c_f = sum_{i in K} g_i c_i(x, d)     (mix: density, the paper)

with g = G(x)_K, renormalised over K when `renormalize` (then the k weights sum to 1). Experts
are black boxes behind the Field protocol; each runs only on the samples routed to it.

mix: alpha (the official code, EIDOSLAB/boost-your-nerf dvgo/moe.py, DVGOMoE.forward) mixes opacities
instead: alpha_f = sum_{i in K} g_i alpha_i, alpha_i = 1 - exp(-sigma_i delta) over one render step
delta = `step`. The renderer is unchanged: the mixture returns the density that has opacity alpha_f
over that step (`alpha_mix_density`), so a step of `step` composites alpha_f exactly (a longer step,
when a ray needs more than the renderer's max_samples, composites 1 - (1 - alpha_f)^(step'/step)).

vd_filter: visible (the official code) also drops, before the gate, the samples whose rendering weight under
V_D alone (V_D composited along the ray over the samples that pass T) is at most the renderer's colour
threshold: samples hidden behind V_D's surfaces reach neither the gate nor the experts (`MixtureSkip.filter`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from boostnerf_cli import flops
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.limits import MAX_GRID_RES, OneOf, Range, at_least, limit
from boostnerf_cli.moe import cells as C
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig, softmax
from boostnerf_cli.moe.router import (
    AUX_NORMS,
    AUX_SAMPLES,
    PENALTY_RULE,
    ExpertRows,
    Routes,
    aux_loss,
    check_penalty,
    check_topk,
    dispatch,
    expert_counts,
    penalty_weights,
    renormalized,
    take,
    top_k,
)
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.packing import DYNAMIC, Packer
from boostnerf_cli.render.timing import part
from boostnerf_cli.render.volrend import render_weights

MIX_MODES = ("density", "alpha")
# V_D: the frozen density volume fitted to the smallest expert | the largest's density
VD_SOURCES = ("smallest", "largest")
VD_FILTERS = ("opacity", "visible")  # V_D drops samples by its opacity over one step | and by its weight along the ray
# Smallest one-step transmittance of a mixed sample (alpha_f <= 1 - 1e-30, optical depth <= 69): keeps the
# optical depth and its gradient finite when every chosen expert is opaque.
MIN_TRANSMITTANCE = 1e-30


@dataclass
class Routing:
    """How a mixture routes, mixes and is penalised: keys of the recipe's `moe` section, declared here once
    (`recipe.MoERecipe` extends this class). build-moe sets them on moe/init, each finetune again on its model."""

    # the untrained mixture's k (moe/init; bench's untrained rows): build-moe fits
    # it to the number of experts, with a note; finetune --topk K sets each model's
    topk: int = limit(2, at_least(1))
    # top-k weights sum to 1 (k = 1: straight-through 1); False: raw probabilities (docs/results.md)
    renormalize: bool = True
    # geometric | linear | quadratic | none | weights "1, 1.5, 2.23" (one per expert)
    penalty: str = limit("geometric", PENALTY_RULE)
    # auxiliary loss over |B|^2 (paper) | counts: over (sum_i c_i)^2 = k^2 |B|^2 (official code)
    aux_norm: str = limit("batch", OneOf(AUX_NORMS))
    # auxiliary loss over every routed sample | visible: those whose V_D opacity
    # and V_D rendering weight pass moe.train.color_threshold (official code)
    aux_samples: str = limit("all", OneOf(AUX_SAMPLES))
    # V_D: fitted to the smallest expert, frozen | largest: the
    # largest expert's own density as it trains (official code)
    vd_source: str = limit("smallest", OneOf(VD_SOURCES))
    # V_D drops samples by its opacity over one step | visible: also those its rendering
    # weight along the ray puts at or below the colour threshold (official code)
    vd_filter: str = limit("opacity", OneOf(VD_FILTERS))
    # the routing weights mix density (paper's equation) | alpha:
    # each expert's opacity over one render step (official code)
    mix: str = limit("density", OneOf(MIX_MODES))
    # rendering samples the trained gate's logits on a bake_res^3 lattice, and routes
    # a Top-1 or Top-2 by their half-cells (0: run the gate MLP on every sample)
    bake_res: int = limit(128, Range(0, MAX_GRID_RES))
    # rendering a renormalised Top-2 leaves out a choice weighing less than this
    # and gives its share to the other one, in both passes (0: never)
    render_min_weight: float = limit(0.01, Range(0, 0.5, hi_open=True))


def routing_of(source: Routing) -> dict:
    """The `Routing` keys of `source` (a recipe's moe section, or a mixture's config), by name."""
    return {f.name: getattr(source, f.name) for f in dataclasses.fields(Routing)}


# T: V_D's opacity over one render step at or below which a sample is filtered (recipe key moe.density_threshold)
DENSITY_THRESHOLD = 1e-3


@dataclass
class MixtureConfig(Routing):
    """A mixture's config: its routing, and what build-moe fixed for it."""

    density_threshold: float = DENSITY_THRESHOLD  # T, as build-moe read it from moe.density_threshold
    vd_res: int = 64  # density volume: vd_res^3 voxels
    step: float = 0.01  # render step (world units)
    expert_names: list[str] = field(default_factory=list)

    @staticmethod
    def saved(config: dict) -> "MixtureConfig":
        """The config a mixture file records (its `threshold`, in files written before it was `density_threshold`; its
        `color_min_weight`, before it was `render_min_weight`; `route_cells`, a rendering switch since removed)."""
        config = dict(config)
        for old, new in (("threshold", "density_threshold"), ("color_min_weight", "render_min_weight")):
            if old in config:
                config[new] = config.pop(old)
        config.pop("route_cells", None)
        return MixtureConfig(**config)


def check_config(cfg: MixtureConfig, m: int) -> None:
    """A mixture of `m` experts can use `cfg`: known mixing and V_D options, 1 <= k <= m, a penalty for m experts."""
    for name, value, choices in (("mixing", cfg.mix, MIX_MODES), ("V_D source", cfg.vd_source, VD_SOURCES),
                                 ("V_D filter", cfg.vd_filter, VD_FILTERS)):
        if value not in choices:
            raise BoostNerfError(f"unknown {name} {value!r}: one of {', '.join(choices)}")
    check_penalty(cfg.penalty, m)
    names = cfg.expert_names if len(cfg.expert_names) == m else [f"expert {i}" for i in range(m)]
    check_topk(cfg.topk, names, "moe.topk")


def alpha_mix_density(alpha: Tensor, trans: Tensor, wsum: Tensor, step: float) -> Tensor:
    """The density whose opacity over one `step` is alpha_f = sum_i w_i alpha_i.

    alpha (N,) = sum_i w_i alpha_i with alpha_i = -expm1(-sigma_i step) (exact for alpha_i -> 0),
    trans (N,) = sum_i w_i exp(-sigma_i step) (exact for alpha_i -> 1), wsum (N,) = sum_i w_i.
    The density is -log(1 - alpha_f) / step, taken as -log1p(-alpha_f) / step below alpha_f = 1/2 and as
    -log((1 - wsum) + trans) / step above it (the same value, without cancellation in either range), the
    transmittance floored at MIN_TRANSMITTANCE: finite, with finite gradients, for opaque experts and any step > 0.
    """
    low = -torch.log1p(-alpha.clamp(0.0, 0.5))
    high = -torch.log(((1.0 - wsum) + trans).clamp(MIN_TRANSMITTANCE, 1.0))
    return torch.where(alpha < 0.5, low, high) / step


def _alpha_and_trans(sigma: Tensor, step: float) -> Tensor:
    """sigma (N,) -> (N, 2): one step's opacity -expm1(-sigma step) and transmittance exp(-sigma step)."""
    tau = sigma * step
    return torch.stack([-torch.expm1(-tau), torch.exp(-tau)], dim=-1)


@dataclass
class RoutingStats:
    """Explicit per-step record of the density pass's routing, for the auxiliary loss and load logs: per density
    call, the probabilities, the choices and which samples are real (`live`; None when every one is)."""

    probs: list[Tensor] = field(default_factory=list)
    idx: list[Tensor] = field(default_factory=list)
    live: list[Tensor | None] = field(default_factory=list)

    def record(self, probs: Tensor, idx: Tensor, live: Tensor | None) -> None:
        self.probs.append(probs)
        self.idx.append(idx)
        self.live.append(live)

    def routed(self) -> Tensor | None:
        """(N,) bool: the recorded samples that are real; None when every one is."""
        if all(live is None for live in self.live):
            return None
        return torch.cat([torch.ones(p.shape[0], dtype=torch.bool, device=p.device) if live is None else live
                          for p, live in zip(self.probs, self.live)])

    def aux(self, weights: Tensor, norm: str = "batch", keep: Tensor | None = None) -> Tensor:
        """The auxiliary loss over the recorded samples, or those of them where `keep` (a bool mask) holds."""
        if not self.probs:
            return torch.zeros((), device=weights.device)
        probs, idx, routed = torch.cat(self.probs), torch.cat(self.idx), self.routed()
        sel = keep if routed is None else routed if keep is None else routed & keep
        if sel is not None and routed is None:  # the dynamic path's mask: the samples it keeps
            probs, idx, sel = probs[sel], idx[sel], None
        return aux_loss(probs, idx, weights, norm, sel)

    def load(self, m: int) -> Tensor:
        """(M,) the fraction of routed samples that each expert received (sums to k), on the device."""
        if not self.idx:
            return torch.zeros(m)
        idx, routed = torch.cat(self.idx), self.routed()
        n = idx.shape[0] if routed is None else routed.sum().clamp_min(1)
        return expert_counts(idx, m, routed) / (max(1, n) if isinstance(n, int) else n)


@dataclass
class RenderCells:
    """Rendering's choice per cell of a lattice of `shape` (vertices) over the gate's box (moe/cells.py): the gate's
    cells halved along every axis, or its own where the halves would be too many; made for the baked `gate`. `top1`: a
    renormalised Top-1's expert per cell (`route_cells`: the one all 8 vertices of the cell name, else the one leading
    at its centre); `top2`: a renormalised Top-2's experts and weights at each cell's centre (`pair_cells`); None for
    other mixtures and without a baked gate."""

    gate: Gate
    top1: Tensor | None
    shape: tuple[int, int, int] | None = None
    top2: C.PairCells | None = None


@dataclass
class SkipTables:
    """What V_D and the occupancy grid decide per cell (moe/cells.py): V_D's test per cell of its lattice, and both
    skips together per fine cell; made for V_D's table at `vd_version` and the grid `occupancy`. Neither changes while a
    mixture finetunes with V_D from the smallest expert, so training reads them as rendering does."""

    vd_version: int
    occupancy: OccupancyGrid | None
    vd: Tensor
    skip: C.SkipCells


class Mixture(nn.Module):
    """Sparse mixture of experts; satisfies the Field protocol."""

    family = "mixture"

    def __init__(self, experts: list[nn.Module], gate: Gate, vd: DensityVolume, occupancy: OccupancyGrid | None,
                 cfg: MixtureConfig):
        super().__init__()
        check_config(cfg, len(experts))
        self.experts = nn.ModuleList(experts)
        self.gate = gate
        self.vd = vd
        self.occupancy = occupancy
        self.cfg = cfg
        self.register_buffer("penalty", penalty_weights(len(experts), cfg.penalty))
        self._skip = MixtureSkip(self)
        self._cells: RenderCells | None = None
        self._skips: SkipTables | None = None

    @property
    def m(self) -> int:
        return len(self.experts)

    @property
    def bbox(self) -> Tensor:
        return self.vd.bbox

    # --- filtering ------------------------------------------------------------------------------
    @torch.no_grad()
    def vd_density(self, xyz: Tensor) -> Tensor:
        """V_D's density at (N, 3) points: the frozen density volume, or the largest expert's density as it is now
        (vd_source: largest, the official code: its V_D is the largest model's density grid, trained with it)."""
        return self.experts[-1].density(xyz) if self.cfg.vd_source == "largest" else self.vd.density(xyz)

    @property
    def skip(self) -> "MixtureSkip":
        """The renderer's empty-space filter: along the rays (`MixtureSkip.filter`), or called on (N, 3) points. One
        for the mixture's life: a compiled step traces the methods of an object it reaches from its inputs, not of
        one made inside the step."""
        return self._skip

    # --- routing --------------------------------------------------------------------------------
    def route(self, xyz: Tensor, need_probs: bool = True) -> tuple[Tensor | None, Tensor, Tensor]:
        """-> probabilities (N, M), weights (N, k), expert indices (N, k).

        Rendering (no autograd, `need_probs` False) with renormalised weights skips the probabilities:
        the renormalised top-k weights are the softmax of the k chosen logits alone (1 for k = 1), and
        the choice is the top-k of the logits; the probabilities are then returned as None. A baked Top-1 or Top-2
        chooses by its cells (`RenderCells`), gradients or not.
        """
        with part("routing"):
            return self._route(xyz, need_probs)

    def _route(self, xyz: Tensor, need_probs: bool) -> tuple[Tensor | None, Tensor, Tensor]:
        flops.add("routing", 4 * self.m * xyz.shape[0])
        if self.gate.cfg.gate_type == "uniform":  # the ensemble: every expert, equal weights
            probs = self.gate.probs(xyz)
            idx = torch.arange(self.m, device=xyz.device).expand(xyz.shape[0], self.m)
            return probs, probs, idx
        if not need_probs and not torch.is_grad_enabled():
            return None, *self._choose(xyz, self.cells())
        probs = self.gate.probs(xyz)
        cells = self._cells if self._cells_hold() else None
        if cells is not None and (cells.top1 is not None or cells.top2 is not None):
            # a baked Top-1 or Top-2 chooses by its cells as rendering does, gradients or not (`prune` follows the rows
            # rendering reads); the weights those of the gate's own probabilities for the choice, as `top_k` gives
            idx = self._choose(xyz, cells)[1]
            return probs, renormalized(probs.gather(1, idx)), idx
        vals, idx = top_k(probs, self.cfg.topk, self.cfg.renormalize)
        return probs, vals, idx

    def _choose(self, xyz: Tensor, cells: RenderCells | None) -> tuple[Tensor, Tensor]:
        """Rendering's choice (see `route`): weights (N, k), experts (N, k); by `cells` where they hold a table."""
        gate, k = self.gate, self.cfg.topk
        if not self.cfg.renormalize:
            return top_k(gate.probs(xyz), k, renormalize=False)
        if cells is not None and cells.top1 is not None:
            cell = C.cell_index(xyz, gate.bbox, cells.shape)
            return xyz.new_ones(xyz.shape[0], 1), cells.top1.index_select(0, cell).long()[:, None]
        if cells is not None and cells.top2 is not None:
            return cells.top2(C.cell_index(xyz, gate.bbox, cells.shape))
        chosen, idx = top_k(gate.logits(xyz).float(), k, renormalize=False)
        return (torch.ones_like(chosen) if k == 1 else softmax(chosen)), idx

    def _cells_hold(self) -> bool:
        """The per-cell decisions were made for this baked gate (`configure` makes them again for a new routing)."""
        c = self._cells
        return c is not None and c.gate is self.gate

    def _make_cells(self) -> RenderCells:
        """The per-cell decisions for the gate as it is (moe/cells.py): a renormalised Top-1's expert, or a renormalised
        Top-2's experts and weights, per cell of the baked gate's halved lattice (V_D's and the grid's tables made
        first; about 1 s for a 128^3 bake of 3-5 experts, on one thread)."""
        self.prepare_skips()
        gate = self.gate
        if gate.cfg.gate_type != "baked" or not self.cfg.renormalize or self.cfg.topk > 2:
            return RenderCells(gate, None)
        if self.cfg.topk == 1:
            top1, shape = C.route_cells(gate.logit_table, gate.shape, at_centre=True)
            return RenderCells(gate, top1, shape)
        top2, shape = C.pair_cells(gate.logit_table, gate.shape)
        return RenderCells(gate, None, shape, top2)

    def cells(self) -> RenderCells | None:
        """The per-cell decisions `for_rendering` made, while they still hold and nothing trains (no gradient)."""
        return self._cells if self._cells_hold() and not torch.is_grad_enabled() else None

    def skips(self) -> SkipTables | None:
        """V_D's and the occupancy grid's per-cell decisions (`prepare_skips`), while they hold: V_D from the smallest
        expert, its table and the grid as they were made for."""
        t = self._skips
        if t is None or self.cfg.vd_source != "smallest" or t.occupancy is not self.occupancy:
            return None
        return t if t.vd_version == self.vd.table._version else None

    @torch.no_grad()
    def prepare_skips(self) -> None:
        """Decide V_D's test, and both skips together, per cell (moe/cells.py) for V_D and the grid as they are."""
        if self.cfg.vd_source != "smallest" or self.skips() is not None:
            return
        vd, cfg = self.vd, self.cfg
        r = C.threshold_raw(cfg.density_threshold, cfg.step, vd.unit, vd.shift)
        self._skips = SkipTables(vd.table._version, self.occupancy, C.vd_states(vd.table, vd.shape, r),
                                 C.skip_states(vd.table, vd.shape, vd.bbox, r, self.occupancy))

    def render_min_weight(self) -> float:
        """The weight below which rendering leaves a choice out (`MixtureConfig.render_min_weight`): for a renormalised
        Top-2 without gradients, whose two weights sum to 1, so that the other one takes the share; else 0."""
        cfg = self.cfg
        return cfg.render_min_weight if cfg.topk == 2 and cfg.renormalize and not torch.is_grad_enabled() else 0.0

    def routes(self, vals: Tensor, idx: Tensor) -> Routes:
        """`route`'s choices as the dispatch takes them: `unit` for rendering's renormalised Top-1 (weight 1), `every`
        for the ensemble (every expert on every sample)."""
        unit = idx.shape[1] == 1 and self.cfg.renormalize and not vals.requires_grad and not torch.is_grad_enabled()
        return Routes(vals, idx, self.m, unit, every=self.gate.cfg.gate_type == "uniform" and idx.shape[1] == self.m)

    def _mix(self, xyz: Tensor, dirs: Tensor | None, vals: Tensor, idx: Tensor, packer: Packer = DYNAMIC,
             live: Tensor | None = None, listed: ExpertRows | None = None) -> Tensor:
        """Run each expert on its routed samples only: density (dirs None) -> (N,), colour -> (N, 3); `packer`,
        `live` (the real samples of a static packing) and `listed` as `router.dispatch` takes them."""
        experts, routes = self.experts, self.routes(vals, idx)
        if dirs is None and self.cfg.mix == "alpha" and not routes.unit:
            step = self.cfg.step
            out = dispatch(routes, lambda e, r: _alpha_and_trans(experts[e].density(take(xyz, r)), step), 2,
                           xyz, packer, live, "density", listed)
            return alpha_mix_density(out[:, 0], out[:, 1], vals.sum(-1), step)
        if dirs is None:  # mix density; or Top-1 at weight 1, whose alpha mix is its expert's opacity: its density
            out = dispatch(routes, lambda e, r: experts[e].density(take(xyz, r))[:, None], 1, xyz, packer,
                           live, "density", listed)
            return out[:, 0]
        return dispatch(routes, lambda e, r: experts[e].color(take(xyz, r), take(dirs, r)), 3, xyz,
                        packer, live, "color")

    # --- the Field contract ---------------------------------------------------------------------
    def density(self, xyz: Tensor) -> Tensor:
        _, vals, idx = self.route(xyz, need_probs=False)
        return self._mix(xyz, None, vals, idx)

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        _, vals, idx = self.route(xyz, need_probs=False)
        return self._mix(xyz, dirs, vals, idx)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        return self.density(xyz), self.color(xyz, dirs)

    def for_rendering(self, exact_gate: bool = False) -> "Mixture":
        """Ready to render a trained mixture: the gate baked when `cfg.bake_res` > 0 (unless exact_gate)."""
        if self.cfg.bake_res > 0 and not exact_gate:
            self.gate = self.gate.baked(self.cfg.bake_res)
        if not self._cells_hold():
            self._cells = self._make_cells()
        self.prepare_skips()
        return self

    def batch_view(self, packer: Packer = DYNAMIC) -> "RoutedMixture":
        """A per-batch view for the renderer: the gate runs once per sample (see RoutedMixture)."""
        return RoutedMixture(self, None, packer)

    def with_stats(self, stats: RoutingStats, packer: Packer | None = None) -> "RoutedMixture":
        """The per-batch view of a training step: routing recorded in `stats`, samples packed by `packer`."""
        return RoutedMixture(self, stats, DYNAMIC if packer is None else packer)

    def expert_only(self, e: int) -> "SingleExpertView":
        return SingleExpertView(self, e)

    def configure(self, **changes) -> None:
        """Change how the mixture routes, mixes and is penalised (`MixtureConfig` fields, e.g. finetune's top-k,
        weights, penalty and auxiliary-loss options over the mixture build-moe made); checked as a new one is."""
        cfg = dataclasses.replace(self.cfg, **changes)
        check_config(cfg, self.m)
        self.cfg = cfg
        self.penalty = penalty_weights(self.m, cfg.penalty, device=self.penalty.device)
        if self._cells_hold():  # ready to render: the per-cell decisions made again for the new routing
            self._cells = self._make_cells()

    def make_ensemble(self) -> None:
        """Every expert with equal weights (the paper's Ens): a uniform gate and k = M."""
        self.gate = Gate(GateConfig(gate_type="uniform"), self.m, self.bbox).to(self.bbox.device)
        self.configure(topk=self.m)

    def param_groups(self, lr_grid: float, lr_mlp: float, lr_gate: float, lr_gate_mlp: float) -> list[dict]:
        groups = []
        for ex in self.experts:
            groups += ex.param_groups(lr_grid, lr_mlp)
        if self.gate.grid_parameters():
            groups.append({"params": self.gate.grid_parameters(), "lr": lr_gate})
        if self.gate.mlp is not None:
            groups.append({"params": list(self.gate.mlp.parameters()), "lr": lr_gate_mlp})
        return groups


class MixtureSkip:
    """A mixture's empty-space filter for the renderer (`render.renderer.render_rays`'s `skip`).

    `filter` (what the renderer calls) keeps, of the (R, S) samples along the rays, those in an occupied cell whose V_D
    opacity over one step exceeds T, reading V_D once per sample that passes the occupancy grid; with vd_filter:
    visible, also only those whose rendering weight under V_D alone (V_D composited over the samples that pass)
    exceeds the renderer's colour threshold (the official code's second filter). Called on (N, 3) points, it is the
    first filter alone."""

    def __init__(self, mixture: Mixture):
        self.mixture = mixture

    @torch.no_grad()
    def filter(self, xyz: Tensor, valid: Tensor, step: float, threshold: float, packer: Packer = DYNAMIC) -> Tensor:
        """xyz (R, S, 3) samples, valid (R, S) those inside the box, `step` the sampling step -> (R, S) the samples
        that pass (see the class); V_D is read on the samples `packer` lists."""
        mix = self.mixture
        flat = xyz.reshape(-1, 3)
        keep = valid.reshape(-1)
        visible = mix.cfg.vd_filter == "visible" and threshold > 0
        tables = self._tables(threshold)
        if tables is not None and not packer.static:
            rows = self._rows_by_tables(tables, xyz, valid)
            one = torch.ones((), dtype=torch.bool, device=keep.device)
            return torch.zeros_like(keep).index_put_((rows,), one).reshape(valid.shape)
        certain = None
        if tables is not None:  # both skips decided per fine cell: tested only where mixed
            with part("V_D"):
                state = packer.where_kept(tables.skip, flat, keep, C.FAIL)
            certain, keep = state == C.PASS, state == C.MIXED
        if mix.occupancy is not None:
            keep = packer.keep_where(mix.occupancy, flat, keep)
        if tables is not None:  # V_D decided per cell: blended only where its surface crosses
            vd = mix.vd
            with part("V_D"):
                state = packer.where_kept(lambda p: torch.where(
                    vd.inside(p), tables.vd[C.cell_index(p, vd.bbox, vd.shape)], C.FAIL), flat, keep, C.FAIL)
            certain = state == C.PASS if certain is None else certain | (state == C.PASS)
            keep = state == C.MIXED
        inside = packer.pack("vd", keep)
        with part("V_D"):
            sigma = mix.vd_density(flat[inside.rows])
        opaque = inside.keep(-torch.expm1(-sigma * mix.cfg.step) > mix.cfg.density_threshold)
        keep = inside.scatter(opaque, fill=False)
        if certain is not None:
            keep = keep | certain
        keep = keep.reshape(valid.shape)
        if not visible:
            return keep
        density = inside.scatter(torch.where(opaque, sigma, sigma.new_zeros(())).to(xyz.dtype)).reshape(valid.shape)
        weights, _, _ = render_weights(density, torch.full_like(density, step))
        return keep & (weights > threshold)

    @torch.no_grad()
    def filter_rows(self, xyz: Tensor, valid: Tensor, step: float, threshold: float) -> Tensor:
        """`filter` on the dynamic packing, as the sorted rows of the kept samples among the flattened (R, S)."""
        tables = self._tables(threshold)
        if tables is None:
            return self.filter(xyz, valid, step, threshold).reshape(-1).nonzero().squeeze(-1)
        return self._rows_by_tables(tables, xyz, valid)

    def _tables(self, threshold: float) -> SkipTables | None:
        """The per-cell tables `filter` decides by: none with the visible filter (it needs V_D along every ray)."""
        mix = self.mixture
        return None if mix.cfg.vd_filter == "visible" and threshold > 0 else mix.skips()

    def keep_cells(self, threshold: float) -> OccupancyGrid | None:
        """The cells outside which `filter_list` keeps no sample: those its table does not fail (None without tables,
        see `lists`)."""
        tables = self._tables(threshold)
        return tables.skip.cells if tables is not None else None

    def lists(self, threshold: float) -> bool:
        """Whether `filter_list` can filter samples listed without their rays (it has per-cell tables)."""
        return self._tables(threshold) is not None

    @torch.no_grad()
    def filter_list(self, pts: Tensor, threshold: float) -> Tensor:
        """Of the samples `pts` (K, 3) inside the box, the indices of those that pass (see `lists`)."""
        tables = self._tables(threshold)
        if tables is None:
            raise ValueError("this mixture's filter needs the samples along their rays: call filter")
        return self._kept(tables, pts, inside=True)

    def _rows_by_tables(self, tables: SkipTables, xyz: Tensor, valid: Tensor) -> Tensor:
        """The sorted rows of the samples inside the box that pass, through the per-cell tables (dynamic packing)."""
        rows = valid.reshape(-1).nonzero().squeeze(-1)
        return rows.index_select(0, self._kept(tables, xyz.reshape(-1, 3).index_select(0, rows)))

    def _kept(self, tables: SkipTables, pts: Tensor, inside: bool = False) -> Tensor:
        """The indices of the points `pts` (K, 3, inside the box) that pass: one lookup per point in the fine cells
        (`inside`: by `SkipCells.within`), every further test on the list of the points still undecided."""
        with part("V_D"):
            state = tables.skip.within(pts) if inside else tables.skip(pts)  # a new tensor: marked in place below
        left = (state == C.MIXED).nonzero().squeeze(-1)  # near V_D's surface or an edge
        if len(left):
            state.index_fill_(0, left[~self._passed(tables, pts.index_select(0, left))], C.FAIL)
        return state.nonzero().squeeze(-1)  # PASS, or MIXED and passed (FAIL is 0)

    def _passed(self, tables: SkipTables, pts: Tensor) -> Tensor:
        """(N,) bool: which of the points `pts`, undecided by the fine cells, pass the occupancy grid and V_D: V_D
        looked up per cell of its own lattice, blended only where its surface crosses the cell."""
        mix = self.mixture
        vd, occupancy = mix.vd, mix.occupancy
        passed = torch.zeros(len(pts), dtype=torch.bool, device=pts.device)
        left = torch.arange(len(pts), device=pts.device)
        if occupancy is not None:
            left = occupancy(pts).nonzero().squeeze(-1)
        if len(left):
            p = pts.index_select(0, left)
            with part("V_D"):
                cell = torch.where(vd.inside(p), tables.vd.index_select(0, C.cell_index(p, vd.bbox, vd.shape)), C.FAIL)
            passed[left[cell == C.PASS]] = True
            left = left[cell == C.MIXED]  # V_D's surface crosses its cell: blended
        if len(left):
            with part("V_D"):
                sigma = mix.vd_density(pts.index_select(0, left))
            passed[left[-torch.expm1(-sigma * mix.cfg.step) > mix.cfg.density_threshold]] = True
        return passed

    def __call__(self, xyz: Tensor) -> Tensor:
        """(N, 3) -> (N,) bool: in an occupied cell, with V_D opacity over one step above T."""
        return self.filter(xyz[:, None], torch.ones(xyz.shape[0], 1, dtype=torch.bool, device=xyz.device), 1.0,
                           0.0)[:, 0]


class RoutedMixture:
    """A per-batch Field view of a mixture that routes each sample once.

    `density(xyz, live)` runs the gate and remembers the routing of those samples; the renderer's colour
    pass then calls `color_rows(rows, dirs, live)` for a subset `rows` of them, which reuses that routing
    instead of running the gate again. When `stats` is given, the density pass's probabilities and
    choices are also recorded there (for the auxiliary loss and the load logs). Experts run on the samples
    `packer` lists for them (render/packing.py); `live` marks a static packing's real samples.
    """

    def __init__(self, mixture: Mixture, stats: RoutingStats | None, packer: Packer):
        self.mixture, self.stats, self.packer = mixture, stats, packer
        self._last: tuple[Tensor, Tensor, Tensor] | None = None
        self._listed: ExpertRows | None = None

    def batch_view(self, packer: Packer) -> "RoutedMixture":
        self.packer = packer
        return self

    def density(self, xyz: Tensor, live: Tensor | None = None) -> Tensor:
        mix = self.mixture
        # the dynamic packing: each expert's samples listed once, for both passes, light choices left out
        listed = not self.packer.static and live is None
        probs, vals, idx = mix.route(xyz, need_probs=self.stats is not None)
        if self.stats is not None:
            self.stats.record(probs, idx, live)
        self._last = (xyz, vals, idx)
        self._listed = ExpertRows.of(mix.routes(vals, idx), mix.render_min_weight()) if listed else None
        return mix._mix(xyz, None, vals, idx, self.packer, live, self._listed)

    def color_rows(self, rows: Tensor, dirs: Tensor, live: Tensor | None = None) -> Tensor:
        """Colour of the samples `rows` of the last `density` call, seen from `dirs` (len(rows), 3)."""
        if self._last is None:
            raise RuntimeError("color_rows needs a density pass first")
        xyz, vals, idx = self._last
        if self._listed is not None and live is None:  # each expert's share of `rows`, from its density-pass list
            slots = torch.full((xyz.shape[0],), -1, dtype=torch.long, device=xyz.device)
            slots.index_copy_(0, rows, torch.arange(len(rows), device=xyz.device))
            experts = self.mixture.experts
            return self._listed.run(lambda e, r, at: experts[e].color(xyz.index_select(0, r), dirs.index_select(0, at)),
                                    xyz.new_zeros(len(rows), 3), slots)
        return self.mixture._mix(xyz[rows], dirs, vals[rows], idx[rows], self.packer, live)

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        return self.mixture.color(xyz, dirs)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        return self.density(xyz), self.color(xyz, dirs)


class SingleExpertView:
    """Expert e's contribution to the mixture: its own density (mix: alpha, its opacity) and colour, the
    density (opacity) times its routed weight."""

    def __init__(self, mixture: Mixture, e: int):
        self.mixture, self.e = mixture, e

    def _weight(self, xyz: Tensor) -> Tensor:
        _, vals, idx = self.mixture.route(xyz, need_probs=False)
        return (vals * (idx == self.e)).sum(-1)

    def density(self, xyz: Tensor) -> Tensor:
        w, sigma = self._weight(xyz), self.mixture.experts[self.e].density(xyz)
        if self.mixture.cfg.mix == "alpha":  # opacity w alpha_e over one step
            step = self.mixture.cfg.step
            at = _alpha_and_trans(sigma, step)
            return alpha_mix_density(w * at[:, 0], w * at[:, 1], w, step)
        return w * sigma

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        return self.mixture.experts[self.e].color(xyz, dirs)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        return self.density(xyz), self.color(xyz, dirs)


class GateView:
    """The gate as a picture: the mixture's density with colour G(x)_e (grey), so a rendered pixel is
    the rendering-weighted probability that its samples go to expert e (composite on black)."""

    def __init__(self, mixture: Mixture, e: int):
        self.mixture, self.e = mixture, e

    def density(self, xyz: Tensor) -> Tensor:
        return self.mixture.density(xyz)

    def color(self, xyz: Tensor, dirs: Tensor) -> Tensor:
        return self.mixture.gate.probs(xyz)[:, self.e : self.e + 1].expand(-1, 3)

    def query(self, xyz: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        return self.density(xyz), self.color(xyz, dirs)
