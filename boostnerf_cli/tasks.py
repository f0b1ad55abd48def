"""Training tasks: what one training step of a field computes, for the loop in `train.py`.

`train.train(task, rays, schedule, ...)` draws a batch of training rays and calls `task.loss(origins, dirs,
rgb, alpha, step)`; a task renders the batch through its field (`render.renderer.render_rays`) and returns the loss
and what to log. `FieldTask` trains one expert (pretrain, the geometry stage, the finetuned baseline);
`MixtureTask` a mixture of experts (finetune: photometric loss plus lambda times the auxiliary loss).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

from boostnerf_cli import distributed as dist
from boostnerf_cli.device import constant, from_host
from boostnerf_cli.moe.mixture import Mixture, RoutingStats
from boostnerf_cli.moe.router import aux_denominator, expert_counts
from boostnerf_cli.recipe import MoERecipe, TrainRecipe
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.packing import Packed, Packer, packer_for
from boostnerf_cli.render.renderer import RayBundle, RenderSettings, render_rays
from boostnerf_cli.render.volrend import distortion, render_weights
from boostnerf_cli.scenes import Scene
from boostnerf_cli.startup import timed
from boostnerf_cli.train import RayData, compiled, compiles


@timed("rays")
def train_rays(scene: Scene, bbox: Tensor, device: str, tcfg: TrainRecipe) -> RayData:
    """Every training ray of `scene` that crosses `bbox`, with its pixel colour (and, for `tcfg.random_background`,
    its alpha when the images had one), on `device`."""
    return RayData.from_split(scene.splits["train"], bbox, scene.near, scene.far, scene.ndc,
                              keep_alpha=tcfg.random_background, device=device)


def random_background(n: int, step: int, device: torch.device | str) -> Tensor:
    """(n, 3) colours in [0, 1) for this process's n training rays of step `step` (`train.random_background`).

    Drawn from a generator seeded by the step alone, for the whole global batch, of which this rank takes its
    shard's rows: one process and N data-parallel ranks composite the same rays on the same colours, a resumed
    run draws what an uninterrupted one does, and torch's own random stream (the renderer's jitter) is untouched."""
    gen = torch.Generator().manual_seed(1_000_003 + step)
    colours = torch.rand(dist.world_size() * n, 3, generator=gen)
    return from_host(colours[dist.rank() * n : (dist.rank() + 1) * n], device)


def photometric_loss(bundle, rgb: Tensor, alpha: Tensor | None, tcfg: TrainRecipe,
                     background: tuple[float, float, float], step: int) -> tuple[Tensor, dict[str, float]]:
    """MSE + DVGO's per-sample colour loss and background entropy loss.

    With `tcfg.random_background` each ray's colour is composited on a random colour instead of `background`
    (the scene's, which `bundle.color` was composited on): a scene whose every pixel is opaque then leaves no
    colour that empty space in front of the background could fake. The pixel `rgb` (composited on `background`)
    moves to the same colour by its `alpha` (None: opaque pixels, which stay as they are), as the rendered
    colour does by its opacity: on a scene with alpha (Blender) empty space still matches a transparent pixel."""
    color = bundle.color
    if tcfg.random_background:
        bg = constant(tuple(background), color.device, color.dtype)
        shift = random_background(color.shape[0], step, color.device).to(color.dtype) - bg
        color = color + (1.0 - bundle.acc)[:, None] * shift
        if alpha is not None:
            rgb = rgb + (1.0 - alpha.to(rgb.dtype))[:, None] * shift.to(rgb.dtype)
    mse = torch.mean((color - rgb) ** 2)
    loss = mse
    if tcfg.weight_rgbper > 0:
        w, c = bundle.extras["weights"], bundle.extras["rgb"]
        loss = loss + tcfg.weight_rgbper * (w * ((c - rgb[:, None, :]) ** 2).sum(-1)).sum(-1).mean()
    if tcfg.weight_entropy > 0:
        acc = bundle.acc.clamp(1e-6, 1 - 1e-6)
        loss = loss + tcfg.weight_entropy * -(acc * torch.log(acc) + (1 - acc) * torch.log(1 - acc)).mean()
    if tcfg.weight_distortion > 0:
        w = bundle.extras["weights"]
        deltas = bundle.extras.get("deltas")  # an unbounded scene's contracted intervals; else the fixed step
        deltas = torch.full_like(w, bundle.extras["step"]) if deltas is None else deltas
        loss = loss + tcfg.weight_distortion * distortion(w, deltas).mean()
    # device values: the loop reads them on its logging steps only, so the step never waits for the device
    return loss, {"loss": loss.detach(), "psnr": psnr_of(mse.detach())}


def psnr_of(mse: Tensor) -> Tensor:
    """-10 log10(mse) on the device, in float64 (as `metrics.mse_to_psnr` computes it; inf when mse == 0)."""
    return -10.0 * torch.log10(mse.double())


def step_setup(loss, tcfg: TrainRecipe, device: torch.device, packer: Packer | None) -> tuple[Packer, Callable]:
    """A task's packing (`packer`, or the device's: static budgets on a GPU and for a compiled step) and its loss,
    compiled when train.compile says so (`train.compiles`)."""
    compiling = compiles(tcfg.compile, device)
    if packer is None:
        packer = packer_for(device, static=compiling)
    return packer, compiled(loss) if compiling else loss


@dataclass
class FieldTask:
    """Train one expert-like field: growth schedule, occupancy refresh, photometric loss."""

    model: nn.Module
    settings: RenderSettings
    tcfg: TrainRecipe
    skip: OccupancyGrid | None
    base_mask: OccupancyGrid | None  # skips never reopen cells outside it
    growth_steps: tuple[int, ...] = ()
    final_voxels: int = 0
    packer: Packer | None = None  # how the renderer lists kept samples (render/packing.py; default: for the device)

    def __post_init__(self) -> None:
        self.packer, self.loss = step_setup(self.loss, self.tcfg, self.settings.bbox.device, self.packer)

    def param_groups(self) -> list[dict]:
        return self.model.param_groups(self.tcfg.lr_grid, self.tcfg.lr_mlp)

    def before_step(self, step: int) -> bool:
        changed = False
        if step in self.growth_steps:
            k = len(self.growth_steps) - (self.growth_steps.index(step) + 1)
            self.model.regrid(self.final_voxels // (2 ** k))
            changed = True
        every = self.tcfg.occupancy_every
        if every > 0 and step > 0 and (step % every == 0 or step in self.growth_steps):
            self.refresh_occupancy()
        return changed

    def refresh_occupancy(self) -> None:
        grid = OccupancyGrid.from_density(
            self.model.density, self.model.bbox, occupancy_shape(self.model), self.settings.step,
            self.tcfg.occupancy_threshold,
        )
        if self.base_mask is not None:
            base = self.base_mask.sample_cells(grid)
            kept = grid.occupied & base
            # Never prune to nothing: with no sample left, no gradient could raise the density again, and the model
            # would train on no sample for the rest of its steps (a weak warm start refreshed after 3 steps: every
            # step then evaluated 0 samples, exit 0). The geometry's cells stay until the density has learnt them.
            grid = OccupancyGrid(kept if kept.any() else base, grid.bbox)
        self.skip = grid

    def loss(self, origins: Tensor, dirs: Tensor, rgb: Tensor, alpha: Tensor | None, step: int):
        bundle = render_rays(self.model, origins, dirs, self.settings, self.skip, jitter=True, packer=self.packer)
        loss, logs = photometric_loss(bundle, rgb, alpha, self.tcfg, self.settings.background, step)
        reg = self.model.regularization()
        if reg is not None:
            loss = loss + reg
        logs["samples"] = bundle.n_samples / origins.shape[0]
        logs["colored"] = bundle.n_color / origins.shape[0]
        return loss, logs

    def state(self) -> dict:
        return {
            "meta": self.model.config_dict(),
            "model": self.model.state_dict(),
            "skip": None if self.skip is None else self.skip.occupied,
            "skip_bbox": None if self.skip is None else self.skip.bbox,  # the geometry's box until the first refresh
        }

    def load_state(self, state: dict) -> None:
        skip = load_field_state(self.model, state)
        if skip is not None:
            self.skip = skip


def load_field_state(model: nn.Module, state: dict) -> OccupancyGrid | None:
    """Put a `FieldTask.state` into `model` (its grid resized to the state's first) -> the state's empty-space grid,
    None when it has none. Until its first refresh the grid is the geometry stage's, over the geometry's own box."""
    model.resize_to(tuple(state["meta"]["shape"]))
    model.load_state_dict(state["model"])
    if state["skip"] is None:
        return None
    return OccupancyGrid(state["skip"], state["skip_bbox"].to(model.bbox.device))


def occupancy_shape(model: nn.Module) -> tuple[int, int, int]:
    """Occupancy cells: the model's lattice, capped at 128 per side."""
    s = model.shape
    f = max(1.0, max(s) / 128)
    return tuple(max(2, int(math.ceil(v / f))) for v in s)  # type: ignore[return-value]


@dataclass
class MixtureTask:
    """One finetuning step of a mixture: render with routing stats, photometric + lambda * aux loss."""

    mix: Mixture
    settings: RenderSettings
    tcfg: TrainRecipe
    rec: MoERecipe
    packer: Packer | None = None  # how the renderer and the experts list kept samples (default: for the device)

    def param_groups(self) -> list[dict]:
        return self.mix.param_groups(self.tcfg.lr_grid, self.tcfg.lr_mlp, self.rec.lr_gate, self.rec.lr_gate_mlp)

    def __post_init__(self) -> None:
        self.packer, self.loss = step_setup(self.loss, self.tcfg, self.mix.bbox.device, self.packer)
        self.mix.prepare_skips()  # V_D and the grid stay as they are while the mixture trains: decided per cell once

    def before_step(self, step: int) -> bool:
        """Nothing changes the mixture's parameters between steps."""
        return False

    def loss(self, origins: Tensor, dirs: Tensor, rgb: Tensor, alpha: Tensor | None, step: int):
        stats = RoutingStats()
        bundle = render_rays(self.mix.with_stats(stats, self.packer), origins, dirs, self.settings, self.mix.skip,
                             jitter=True, packer=self.packer)
        loss, logs = photometric_loss(bundle, rgb, alpha, self.tcfg, self.settings.background, step)
        for ex in self.mix.experts:  # family-specific terms (TensoRF's L1), as in pretraining
            reg = ex.regularization()
            if reg is not None:
                loss = loss + reg
        keep = None  # the auxiliary loss's batch: every routed sample, or (aux_samples: visible) the visible ones
        routed_visible = self.mix.cfg.vd_filter == "visible" and self.settings.color_threshold > 0
        if self.mix.cfg.aux_samples == "visible" and not routed_visible:  # with the visible V_D filter the gate saw
            keep = visible_samples(self.mix, bundle, origins, dirs, self.settings.color_threshold)  # only those
        aux, aux_value, load = batch_routing(stats, self.mix.penalty, self.mix.m, self.mix.cfg.aux_norm, keep)
        if self.rec.lam > 0 and self.mix.gate.cfg.gate_type != "uniform":
            loss = loss + self.rec.lam * aux
            logs["aux"] = aux_value
        for i in range(self.mix.m):
            logs[f"load{i}"] = load[i]
        logs["samples"] = bundle.n_samples / origins.shape[0]
        return loss, logs

    def state(self) -> dict:
        return {"model": self.mix.state_dict()}

    def load_state(self, state: dict) -> None:
        self.mix.load_state_dict(state["model"])


@torch.no_grad()
def visible_samples(mix: Mixture, bundle: RayBundle, origins: Tensor, dirs: Tensor, threshold: float) -> Tensor:
    """Which samples of the density pass are visible, as the official code counts them for its auxiliary loss
    (EIDOSLAB/boost-your-nerf, dvgo/moe.py, DVGOMoE.forward): the density volume's opacity over the step and its
    rendering weight along the ray (V_D alone composited over the density pass's samples) both above `threshold`
    (its fast_color_thres, 1e-4; here moe.train.color_threshold). -> (n_samples,) bool, in the routing order (a
    static packing's pads: False)."""
    rows, live, t, step = bundle.extras["rows"], bundle.extras["live"], bundle.extras["t"], bundle.extras["step"]
    dens = Packed(rows, live, t.numel())
    r, s = t.shape
    ray = torch.div(rows, s, rounding_mode="floor")
    xyz = origins[ray] + t.reshape(-1)[rows, None] * dirs[ray]  # the renderer's sample positions
    sigma = dens.scatter(mix.vd_density(xyz).to(t.dtype)).reshape(r, s)
    weights, alpha, _ = render_weights(sigma, torch.full((r, s), step, device=t.device, dtype=t.dtype))
    return dens.keep((alpha.reshape(-1)[rows] > threshold) & (weights.reshape(-1)[rows] > threshold))


def batch_routing(stats: RoutingStats, weights: Tensor, m: int, norm: str = "batch",
                  keep: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """The auxiliary loss L = M / Z^2 sum_i c_i m_i w_i of the step's whole batch, and the load per expert.

    Z = |B| (norm "batch") or sum_i c_i (norm "counts", `router.aux_loss`); the batch is every routed sample, or
    those where `keep` holds (mask over the routed samples; the load is over every routed sample).
    -> (the term to add to this rank's loss, L's value, the fraction of routed samples each expert got (M,)), the
    last two detached, on the device.
    Data parallel, the batch is the union of the ranks' shards and L is not a mean of per-shard terms:
    the counts c_i and the number of samples |B| are summed over the ranks (they carry no gradient), and
    each rank's term keeps its own samples' probability mass m_i^(r), times the number of ranks N, so the
    ranks' averaged gradient, (1/N) sum_r N M/Z^2 sum_i c_i w_i grad m_i^(r), is exactly L's gradient.
    """
    if dist.world_size() == 1:
        aux = stats.aux(weights, norm, keep)
        return aux, aux.detach(), stats.load(m)
    probs = torch.cat(stats.probs) if stats.probs else weights.new_zeros(0, m)
    idx = torch.cat(stats.idx) if stats.idx else torch.zeros(0, 1, dtype=torch.long, device=weights.device)
    routed = stats.routed()
    if routed is not None:  # a static packing's pads count nowhere
        probs, idx = probs[routed], idx[routed]
        keep = None if keep is None else keep[routed]
    n_routed = float(idx.shape[0])
    routed_counts = expert_counts(idx, m).to(weights)
    if keep is not None:
        probs, idx = probs[keep], idx[keep]
    mass = probs.sum(dim=0)
    local = torch.cat([expert_counts(idx, m).to(mass), mass, mass.new_tensor([float(probs.shape[0])]),
                       routed_counts.to(mass), mass.new_tensor([n_routed])])
    total = dist.all_sum(local.double())
    counts, n = total[:m].to(mass), float(total[2 * m])
    routed_total, n_routed = total[2 * m + 1 : 3 * m + 1], float(total[-1])
    load = (routed_total / n_routed).to(mass) if n_routed > 0 else mass.new_zeros(m)
    if n == 0:
        return mass.sum() * 0.0, mass.new_zeros(()), load
    z = aux_denominator(n, idx.shape[1], norm)
    value = m / z**2 * (total[:m] * total[m : 2 * m] * weights.double()).sum()
    return dist.world_size() * m / z**2 * (counts * mass * weights.to(mass)).sum(), value.to(mass), load
