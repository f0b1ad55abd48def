"""The mixture as the official code trains it (moe.aux_norm, moe.aux_samples, moe.mix, moe.gate_init).

Each option against an independent float64 reference written here with plain loops; then the whole chain
through the CLI with every official option on.
"""

import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from conftest import assert_clean_failure, make_recipe, run_cli

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.models import load_expert, load_mixture, save_mixture
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig, RoutingStats, alpha_mix_density
from boostnerf_cli.moe.router import aux_loss, penalty_weights, top_k
from boostnerf_cli.recipe import MoERecipe, load_recipe
from boostnerf_cli.render.renderer import RenderSettings, render_rays, sample_rays
from boostnerf_cli.stages.build_moe import Member, gate_source
from boostnerf_cli.tasks import batch_routing, visible_samples
from boostnerf_cli.workspace import load_tensors, save_tensors

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
STEP = 0.05
RECIPES = Path(__file__).parent.parent / "recipes"


def _experts(m, seed=0, scale=2.0):
    torch.manual_seed(seed)
    out = []
    for i in range(m):
        e = DVGOExpert(DVGOConfig(res=6 + 2 * i, hidden=8, layers=1), BOX.float())
        with torch.no_grad():
            e.density_table.normal_(0, scale)
            e.feature_table.normal_()
            for p in e.rgbnet.parameters():
                p.normal_(0, 0.3)
        out.append(e.double())
    return out


def _mixture(m=3, k=2, mix="density", seed=0, scale=2.0, renormalize=True):
    experts = _experts(m, seed, scale)
    gate = Gate(GateConfig(gate_type="grid", gate_res=4, gate_channels=4, gate_hidden=8, gate_layers=2), m, BOX)
    with torch.no_grad():
        for p in gate.parameters():
            p.normal_(0, 0.5)
    vd = DensityVolume(BOX, 6).double()
    vd.init_from(experts[0].density)
    mixture = Mixture(experts, gate, vd, None, MixtureConfig(topk=k, renormalize=renormalize, step=STEP, mix=mix,
                                                             expert_names=[f"e{i}" for i in range(m)]))
    return mixture.double()


def _rays(n, seed=2):
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1) * 3
    target = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 0.8
    return origins, torch.nn.functional.normalize(target - origins, dim=-1)


def _settings(**kw):
    return RenderSettings(step=STEP, near=0.1, far=8.0, bbox=BOX, background=(1.0, 0.5, 0.25), **kw)


# --- the auxiliary loss: (sum c_i)^2 normalisation, visible samples ---------------------------------------
def _aux_reference(probs, idx, weights, norm):
    """M / Z^2 sum_i c_i m_i w_i with plain loops; Z = N (batch) or sum_i c_i (counts)."""
    n, m = probs.shape
    c = [0] * m
    for row in idx.tolist():
        for e in row:
            c[e] += 1
    mass = [sum(float(probs[s, i]) for s in range(n)) for i in range(m)]
    z = sum(c) if norm == "counts" else n
    return m / z**2 * sum(c[i] * mass[i] * float(weights[i]) for i in range(m))


@pytest.mark.parametrize("k", [1, 2, 3])
def test_counts_normalisation_is_the_official_sum_of_counts_squared(k):
    g = torch.Generator().manual_seed(k)
    probs = torch.softmax(torch.randn(37, 4, generator=g, dtype=torch.float64) * 2, dim=-1)
    _, idx = top_k(probs, k, renormalize=True)
    w = penalty_weights(4, "geometric").double()
    counts = float(aux_loss(probs, idx, w, "counts"))
    assert counts == pytest.approx(_aux_reference(probs, idx, w, "counts"), rel=1e-13, abs=0)
    batch = float(aux_loss(probs, idx, w, "batch"))
    assert batch == pytest.approx(_aux_reference(probs, idx, w, "batch"), rel=1e-13, abs=0)
    assert counts == pytest.approx(batch / k**2, rel=1e-13)  # sum_i c_i = k |B|


def _visible_reference(mix, origins, dirs, settings, rows, threshold):
    """V_D composited alone over the density pass's samples, ray by ray in float64: alpha and weight > threshold."""
    t, _, xyz, step = sample_rays(origins, dirs, settings, jitter=False, fit=True)  # the CPU renderer's slots
    s = t.shape[1]
    trans = {}  # ray -> transmittance so far
    out, opaque = [], []
    for row in rows.tolist():
        ray = row // s
        sigma = float(mix.vd.density(xyz[ray, row % s][None])[0])
        alpha = 1.0 - math.exp(-sigma * step)
        tr = trans.get(ray, 1.0)
        out.append(alpha > threshold and tr * alpha > threshold)
        opaque.append(alpha > threshold)
        trans[ray] = tr * (1.0 - alpha)
    return torch.tensor(out, dtype=torch.bool), torch.tensor(opaque, dtype=torch.bool)


def test_visible_samples_and_the_official_auxiliary_loss_match_a_per_ray_reference():
    torch.manual_seed(0)
    mix = _mixture(m=3, k=2, scale=3.0)
    origins, dirs = _rays(48)
    settings = _settings(color_threshold=1e-4)
    stats = RoutingStats()
    bundle = render_rays(mix.with_stats(stats), origins, dirs, settings)
    keep = visible_samples(mix, bundle, origins, dirs, 1e-4)
    rows = bundle.extras["rows"]
    ref, opaque = _visible_reference(mix, origins, dirs, settings, rows, 1e-4)
    assert keep.shape == (rows.numel(),) and torch.equal(keep, ref)
    assert 0 < int(keep.sum()) < int(opaque.sum()) < keep.numel()  # occluded samples (opaque enough) are dropped too
    probs, idx = torch.cat(stats.probs), torch.cat(stats.idx)
    aux, value, load = batch_routing(stats, mix.penalty.double(), 3, "counts", keep)
    expected = _aux_reference(probs[ref].detach(), idx[ref], mix.penalty, "counts")
    assert float(aux.detach()) == pytest.approx(expected, rel=1e-12) and value == pytest.approx(expected, rel=1e-12)
    assert sum(load) == pytest.approx(2.0)  # the load is still over every routed sample
    everything = _aux_reference(probs.detach(), idx, mix.penalty, "counts")
    assert abs(everything - expected) > 1e-3 * everything  # the visible batch is another loss
    aux.backward()
    assert mix.gate.table.grad is not None and torch.isfinite(mix.gate.table.grad).all()


# --- alpha mixing ---------------------------------------------------------------------------------------
def test_alpha_mixing_mixes_the_experts_opacities():
    mix = _mixture(m=3, k=2, mix="alpha", scale=3.0)
    g = torch.Generator().manual_seed(3)
    xyz = torch.rand(200, 3, generator=g, dtype=torch.float64) * 1.8 - 0.9
    with torch.no_grad():
        sigma = mix.density(xyz)
        _, vals, idx = mix.route(xyz, need_probs=False)
        for s in range(xyz.shape[0]):
            ref = 0.0
            for j in range(2):
                sig = float(mix.experts[int(idx[s, j])].density(xyz[s : s + 1])[0])
                ref += float(vals[s, j]) * (1.0 - math.exp(-sig * STEP))
            assert 1.0 - math.exp(-float(sigma[s]) * STEP) == pytest.approx(ref, rel=1e-10, abs=1e-14)


def test_a_renormalised_top1_renders_its_experts_own_density_under_alpha_mixing():
    """Weight 1 on one expert: the alpha mix's opacity is that expert's, so rendering takes its density as it is, not
    through an opacity and back (which rounds), and leaves the rest of the mix out."""
    mix = _mixture(m=3, k=1, mix="alpha", scale=3.0).float()
    g = torch.Generator().manual_seed(4)
    xyz = torch.rand(500, 3, generator=g) * 1.8 - 0.9
    with torch.no_grad():
        sigma = mix.density(xyz)
        _, _, idx = mix.route(xyz, need_probs=False)
        own = torch.zeros(len(xyz))
        for e, expert in enumerate(mix.experts):  # each expert on the samples routed to it, as the mixture runs it
            rows = (idx[:, 0] == e).nonzero().squeeze(-1)
            own[rows] = expert.density(xyz[rows])
    assert idx.unique().numel() > 1 and torch.equal(sigma, own)


def test_alpha_mixing_renders_the_hand_composited_colour():
    mix = _mixture(m=3, k=2, mix="alpha", scale=3.0)
    origins, dirs = _rays(24)
    settings = _settings(color_threshold=0.0)
    with torch.no_grad():
        bundle = render_rays(mix, origins, dirs, settings)
        t, valid, xyz, step = sample_rays(origins, dirs, settings, jitter=False)
        assert step == STEP
        bg = torch.tensor(settings.background, dtype=torch.float64)
        # the routing is an input here (float32 weights at render time): one batch, as the renderer routes them
        _, vals_all, idx_all = mix.route(xyz[valid], need_probs=False)
        n = 0
        for r in range(origins.shape[0]):
            trans, color = 1.0, torch.zeros(3, dtype=torch.float64)
            for j in range(t.shape[1]):
                if not valid[r, j]:
                    continue
                p = xyz[r, j][None]
                vals, idx = vals_all[n : n + 1], idx_all[n : n + 1]
                n += 1
                alpha, rgb = 0.0, torch.zeros(3, dtype=torch.float64)
                for c in range(2):
                    e = mix.experts[int(idx[0, c])]
                    alpha += float(vals[0, c]) * (1.0 - math.exp(-float(e.density(p)[0]) * STEP))
                    rgb += float(vals[0, c]) * e.color(p, dirs[r][None])[0]
                color += trans * alpha * rgb
                trans *= 1.0 - alpha
            color += trans * bg
            assert torch.allclose(bundle.color[r], color, rtol=0, atol=1e-10), (
                r, (bundle.color[r] - color).abs().max())


def test_density_and_alpha_mixing_differ_as_the_issue_says():
    """Half and half of an empty expert and one with sigma delta = 5: density mixing gives 0.92, alpha mixing 0.5."""
    w = torch.tensor([0.5], dtype=torch.float64)
    tau = torch.tensor([5.0], dtype=torch.float64)
    alpha_mixed = alpha_mix_density(w * -torch.expm1(-tau), w * torch.exp(-tau) + w * 1.0, 2 * w, 1.0)
    assert float(-torch.expm1(-alpha_mixed)) == pytest.approx(0.5 * (1 - math.exp(-5)), rel=1e-12)
    assert 1 - math.exp(-0.5 * 5.0) == pytest.approx(0.918, abs=1e-3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_alpha_mixing_is_finite_for_opaque_experts_and_tiny_steps(dtype):
    for step in (1e-8, 1e-3, 1.0):
        for tau in (0.0, 1e-9, 0.3, 0.69, 0.7, 30.0, 1e3, 1e10):
            for w in ((1.0,), (0.7, 0.3), (0.4, 0.35)):  # renormalised, and raw probabilities (sum below 1)
                vals = torch.tensor(w, dtype=dtype, requires_grad=True)
                sig = torch.full((len(w),), tau / step, dtype=dtype, requires_grad=True)
                a = -torch.expm1(-sig * step)
                out = alpha_mix_density((vals * a).sum()[None], (vals * torch.exp(-sig * step)).sum()[None],
                                        vals.sum()[None], step)
                got = -torch.expm1(-out * step)
                ref = sum(wi * (1 - math.exp(-tau)) for wi in w)
                assert torch.isfinite(out).all() and float(got.detach()) == pytest.approx(ref, rel=1e-5, abs=1e-6)
                got.sum().backward()
                assert torch.isfinite(vals.grad).all() and torch.isfinite(sig.grad).all()
                if tau < 20:  # d alpha_f / d w_i = alpha_i, where the opacity is not saturated
                    assert vals.grad.tolist() == pytest.approx([1 - math.exp(-tau)] * len(w), rel=1e-4, abs=1e-6)


def test_alpha_mixing_trains_with_finite_gradients_through_opaque_experts():
    mix = _mixture(m=3, k=2, mix="alpha", scale=1.0)
    with torch.no_grad():
        mix.experts[2].density_table.fill_(1e5)  # exp(-sigma step) underflows to 0: alpha = 1 exactly
        mix.experts[1].density_table.fill_(-200.0)  # empty
    origins, dirs = _rays(32)
    stats = RoutingStats()
    bundle = render_rays(mix.with_stats(stats), origins, dirs, _settings(), jitter=True)
    loss = (bundle.color - 0.3).square().mean() + stats.aux(mix.penalty, "counts")
    loss.backward()
    assert torch.isfinite(bundle.color).all()
    grads = [p.grad for p in mix.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert float(mix.gate.table.grad.abs().sum()) > 0


# --- gate initialisation from an expert -----------------------------------------------------------------
def _trilinear_reference(table, shape, bbox, point):
    """The value of a dense grid at `point`, from its 8 surrounding vertices, with explicit loops."""
    pos, base, frac = [], [], []
    for a in range(3):
        u = (float(point[a]) - float(bbox[0, a])) / (float(bbox[1, a]) - float(bbox[0, a])) * (shape[a] - 1)
        u = min(max(u, 0.0), shape[a] - 1.0)
        i = min(int(math.floor(u)), shape[a] - 2)
        base.append(i)
        frac.append(u - i)
        pos.append(u)
    out = torch.zeros(table.shape[1], dtype=torch.float64)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                wt = ((frac[0] if dx else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1])
                      * (frac[2] if dz else 1 - frac[2]))
                row = ((base[0] + dx) * shape[1] + (base[1] + dy)) * shape[2] + (base[2] + dz)
                out += wt * table[row].double()
    return out


def test_gate_init_copies_the_experts_feature_grid_on_the_same_lattice():
    box = torch.tensor([[-1.0, -0.5, -0.8], [1.0, 0.7, 0.9]])
    expert = DVGOExpert(DVGOConfig(res=10, hidden=8, layers=1), box)
    with torch.no_grad():
        expert.feature_table.normal_()
    gate = Gate(GateConfig(gate_res=10, gate_channels=expert.feature_table.shape[1], gate_hidden=8, gate_layers=1,
                           gate_init="expert"), 3, box)
    assert gate.shape == expert.shape
    gate.init_grid_from(expert.feature_table, expert.shape, expert.bbox)
    assert torch.equal(gate.table, expert.feature_table)
    xyz = torch.rand(4096, 3, generator=torch.Generator().manual_seed(0)) * (box[1] - box[0]) + box[0]
    assert gate.logits(xyz).mean(0).abs().max() < 1e-4  # centred again on the new features


def test_gate_init_resamples_another_lattice_trilinearly():
    box = torch.tensor([[-1.0, -0.5, -0.8], [1.0, 0.7, 0.9]], dtype=torch.float64)
    expert = DVGOExpert(DVGOConfig(res=9, hidden=8, layers=1), box).double()
    with torch.no_grad():
        expert.feature_table.normal_()
    gate = Gate(GateConfig(gate_res=6, gate_channels=12, gate_hidden=8, gate_layers=1, gate_init="expert"), 2,
                box).double()
    assert gate.shape != expert.shape
    gate.init_grid_from(expert.feature_table, expert.shape, expert.bbox)
    axes = [torch.linspace(float(box[0, a]), float(box[1, a]), gate.shape[a], dtype=torch.float64) for a in range(3)]
    row = 0
    for x in axes[0]:
        for y in axes[1]:
            for z in axes[2]:
                ref = _trilinear_reference(expert.feature_table.detach(), expert.shape, box, (x, y, z))
                assert torch.allclose(gate.table[row].detach(), ref, rtol=0, atol=1e-12), row
                row += 1
    assert row == gate.table.shape[0]


def test_gate_init_names_its_requirements():
    rec = MoERecipe(gate_init="expert")
    tensorf = [Member("tensorf-8", SimpleNamespace(family="tensorf"), 10, 0.1)]
    with pytest.raises(BoostNerfError, match="needs a dvgo expert"):
        gate_source(rec, "tensorf", tensorf)
    dvgo = [Member("dvgo-8", SimpleNamespace(family="dvgo"), 10, 0.1),
            Member("dvgo-9", SimpleNamespace(family="dvgo"), 20, 0.1)]
    assert gate_source(rec, "dense", dvgo).name == "dvgo-8"  # the smallest, as the official code's
    assert gate_source(MoERecipe(gate_init="expert", gate_from="dvgo-9"), "dense", dvgo).name == "dvgo-9"
    outside = Member("dvgo-6", SimpleNamespace(family="dvgo"), 5, 0.1)
    assert gate_source(MoERecipe(gate_init="expert", gate_from="dvgo-6"), "dense", dvgo, outside).name == "dvgo-6"
    with pytest.raises(BoostNerfError, match="moe.gate_from = 'dvgo-6' needs moe.gate_init = expert"):
        gate_source(MoERecipe(gate_from="dvgo-6"), "dense", dvgo, outside)
    with pytest.raises(BoostNerfError, match="dense feature grid"):
        gate_source(MoERecipe(gate_init="expert", gate_type="switch"), "dense", dvgo)
    assert gate_source(MoERecipe(), "dense", dvgo) is None


# --- persistence and the recipe -------------------------------------------------------------------------
def test_the_options_are_saved_and_old_files_load_with_the_paper_defaults(tmp_path):
    mix = _mixture(m=2, k=2, mix="alpha").float()
    mix.cfg.aux_norm, mix.cfg.aux_samples = "counts", "visible"
    save_mixture(tmp_path / "m.safetensors", mix)
    loaded, _ = load_mixture(tmp_path / "m.safetensors")
    assert (loaded.cfg.mix, loaded.cfg.aux_norm, loaded.cfg.aux_samples) == ("alpha", "counts", "visible")
    xyz = torch.rand(300, 3, generator=torch.Generator().manual_seed(0)) * 1.8 - 0.9
    with torch.no_grad():
        assert torch.equal(loaded.density(xyz), mix.eval().density(xyz))
    tensors, meta = load_tensors(tmp_path / "m.safetensors")
    for key in ("mix", "aux_norm", "aux_samples"):
        del meta["mixture"][key]
    del meta["gate"]["config"]["gate_init"]
    former = {"gate_type": "kind", "gate_res": "res", "gate_channels": "channels", "gate_hidden": "hidden",
              "gate_layers": "layers", "gate_grid": "grid"}  # a file written before the gate took the recipe's names
    meta["gate"]["config"] = {former.get(k, k): v for k, v in meta["gate"]["config"].items()}
    meta["mixture"]["threshold"] = meta["mixture"].pop("density_threshold")
    meta["mixture"]["color_min_weight"] = meta["mixture"].pop("render_min_weight")  # its former name
    meta["mixture"]["route_cells"] = True  # a rendering switch some files record, since removed
    meta.pop("digest", None), meta.pop("format_version", None)
    save_tensors(tmp_path / "old.safetensors", tensors, meta)
    old, _ = load_mixture(tmp_path / "old.safetensors")
    assert (old.cfg.mix, old.cfg.aux_norm, old.cfg.aux_samples, old.gate.cfg.gate_init) == (
        "density", "batch", "all", "random")
    assert (old.cfg.density_threshold, old.gate.cfg) == (loaded.cfg.density_threshold, loaded.gate.cfg)
    assert old.cfg.render_min_weight == loaded.cfg.render_min_weight
    with torch.no_grad():
        assert not torch.allclose(old.density(xyz), loaded.density(xyz))


def test_the_official_recipe_selects_every_official_option():
    rec = load_recipe(RECIPES / "blender-dvgo-cpu-official.yaml")
    cpu = load_recipe(RECIPES / "blender-dvgo-cpu.yaml")
    assert rec.pretrain.res == cpu.pretrain.res == [64, 72, 80] and rec.data.image_size == 100
    m = rec.moe
    assert (m.gate_init, m.aux_norm, m.aux_samples, m.mix) == ("expert", "counts", "visible", "alpha")
    assert m.gate_res == 64 and m.lr_gate == 0.1 and m.train.lr_grid == 0.1 and m.train.lr_mlp == 1e-3
    assert m.train.lr_decay == 0.1 and rec.pretrain.iters < m.iters
    d = MoERecipe()
    assert (d.gate_init, d.aux_norm, d.aux_samples, d.mix) == ("random", "batch", "all", "density")


# --- the official penalty list and V_D -------------------------------------------------------------------
OFFICIAL_WEIGHTS = "1, 1.5, 2.23"  # EIDOSLAB/boost-your-nerf, instant-ngp/moe_main.py: weights[:3]


def test_explicit_penalty_weights_are_used_as_listed_in_the_official_loss():
    assert penalty_weights(3, OFFICIAL_WEIGHTS).tolist() == pytest.approx([1.0, 1.5, 2.23], rel=1e-7)
    mix = _mixture(m=3, k=1, scale=3.0)
    mix.configure(penalty=OFFICIAL_WEIGHTS, aux_norm="counts")
    assert mix.cfg.penalty == OFFICIAL_WEIGHTS and mix.penalty.tolist() == pytest.approx([1.0, 1.5, 2.23], rel=1e-7)
    stats = RoutingStats()
    render_rays(mix.with_stats(stats), *_rays(32), _settings())
    probs, idx = torch.cat(stats.probs).detach(), torch.cat(stats.idx)
    aux, value, _ = batch_routing(stats, mix.penalty.double(), 3, "counts")
    expected = _aux_reference(probs, idx, torch.tensor([1.0, 1.5, 2.23], dtype=torch.float64), "counts")
    assert value == pytest.approx(expected, rel=1e-7) and float(aux.detach()) == pytest.approx(expected, rel=1e-7)
    geometric = _aux_reference(probs, idx, penalty_weights(3, "geometric").double(), "counts")
    assert abs(geometric - expected) > 1e-3 * expected  # another loss than the default geometric weights


def test_explicit_penalty_weights_are_checked_in_one_line(tmp_path):
    (tmp_path / "ok.yaml").write_text(f"moe:\n  penalty: {OFFICIAL_WEIGHTS}\n")  # plain YAML text, no quotes
    assert load_recipe(tmp_path / "ok.yaml").moe.penalty == OFFICIAL_WEIGHTS
    for bad, says in (("1, 0, 2", r"numbers in \(0, 1e\+06\]"), ("1, x", "one of geometric"),
                      ("1, nan, 2", r"numbers in \(0, 1e\+06\]"), ("steep", "one of geometric")):
        with pytest.raises(BoostNerfError, match=says):
            (tmp_path / "r.yaml").write_text(f"moe:\n  penalty: '{bad}'\n")
            load_recipe(tmp_path / "r.yaml")
    mix = _mixture(m=3, k=2)
    with pytest.raises(BoostNerfError, match="lists 2 weights but the mixture has 3 experts"):
        mix.configure(penalty="1, 1.5")
    assert mix.cfg.penalty == "geometric"  # refused before anything changed


def test_vd_source_largest_reads_the_largest_experts_density_as_it_trains():
    mix = _mixture(m=3, k=2, scale=3.0)
    xyz = torch.rand(500, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 1.8 - 0.9
    frozen = mix.skip(xyz)
    assert torch.equal(mix.vd_density(xyz), mix.vd.density(xyz))
    mix.configure(vd_source="largest")
    largest = mix.experts[-1]
    with torch.no_grad():  # V_D reads the expert's density as rendering does (no gradient)
        assert torch.equal(mix.vd_density(xyz), largest.density(xyz))
        largest.density_table.add_(-4.0)  # as if the largest expert had trained its density down
        sigma = largest.density(xyz)
    expected = torch.tensor([1.0 - math.exp(-float(v) * STEP) > mix.cfg.density_threshold for v in sigma])
    now = mix.skip(xyz)
    assert torch.equal(now, expected) and torch.equal(mix.vd_density(xyz), sigma)
    assert not torch.equal(now, frozen) and now.sum() < frozen.sum()
    mix.configure(vd_source="smallest")
    assert torch.equal(mix.skip(xyz), frozen)  # the frozen copy did not move


def _visible_rows_reference(mix, origins, dirs, settings, threshold):
    """The samples the official filters keep, ray by ray in float64: V_D opacity over the step above T, then
    V_D's rendering weight (composited over the samples that pass T) above `threshold`. -> flat sample indices."""
    t, valid, xyz, step = sample_rays(origins, dirs, settings, jitter=False, fit=True)  # the CPU renderer's slots
    s = t.shape[1]
    rows = []
    for ray in range(t.shape[0]):
        tr = 1.0
        for j in range(s):
            if not valid[ray, j]:
                continue
            alpha = 1.0 - math.exp(-float(mix.vd_density(xyz[ray, j][None])[0]) * step)
            if alpha <= mix.cfg.density_threshold:
                continue
            if tr * alpha > threshold:
                rows.append(ray * s + j)
            tr *= 1.0 - alpha
    return torch.tensor(rows, dtype=torch.long)


@pytest.mark.parametrize("source", ["smallest", "largest"])
def test_the_visible_filter_drops_what_V_D_hides_as_a_per_ray_reference_does(source):
    mix = _mixture(m=3, k=1, scale=3.0)
    with torch.no_grad():  # V_D opaque enough that surfaces hide what lies behind them
        mix.vd.table.add_(10.0)
        mix.experts[-1].density_table.add_(10.0)
    mix.configure(vd_source=source)
    origins, dirs = _rays(40)
    settings = _settings(color_threshold=1e-4)
    opacity_only = render_rays(mix, origins, dirs, settings, mix.skip).extras["rows"]
    mix.configure(vd_filter="visible")
    bundle = render_rays(mix, origins, dirs, settings, mix.skip)
    rows = bundle.extras["rows"]
    assert torch.equal(rows, _visible_rows_reference(mix, origins, dirs, settings, 1e-4))
    assert 0 < rows.numel() < opacity_only.numel()  # hidden samples reach neither the gate nor the experts
    assert torch.isin(rows, opacity_only).all()
    everything = render_rays(mix, origins, dirs, _settings(color_threshold=0.0), mix.skip).extras["rows"]
    assert torch.equal(everything, opacity_only)  # the terminated skip off (threshold 0): nothing more is dropped
    mix.configure(vd_filter="opacity")
    assert torch.equal(render_rays(mix, origins, dirs, settings, mix.skip).extras["rows"], opacity_only)


def test_with_the_visible_filter_the_official_aux_counts_every_routed_sample_and_reads_V_D_once():
    """With moe.vd_filter: visible the gate sees only what V_D leaves visible, so the official auxiliary loss over
    the visible samples (moe.aux_samples: visible) is the loss over every routed sample: V_D is read and composited
    once per step, by the filter, not a second time for the loss."""
    from boostnerf_cli.recipe import TrainRecipe
    from boostnerf_cli.tasks import MixtureTask

    mix = _mixture(m=3, k=1, scale=3.0)
    with torch.no_grad():  # V_D opaque enough that surfaces hide what lies behind them
        mix.vd.table.add_(10.0)
    mix.configure(vd_filter="visible", aux_samples="visible", aux_norm="counts")
    origins, dirs = _rays(40)
    settings = _settings(color_threshold=1e-4)
    task = MixtureTask(mix, settings, TrainRecipe(), MoERecipe(lam=1.0, topk=1))
    reads = []
    vd_density = mix.vd_density
    mix.vd_density = lambda xyz: reads.append(xyz.shape[0]) or vd_density(xyz)
    rgb = torch.rand(40, 3, dtype=torch.float64)
    torch.manual_seed(5)
    _, logs = task.loss(origins, dirs, rgb, None, 0)
    assert len(reads) == 1  # the filter's read; before the fix the loss composited V_D a second time
    torch.manual_seed(5)  # the same jitter: the same samples and routing
    stats = RoutingStats()
    bundle = render_rays(mix.with_stats(stats), origins, dirs, settings, mix.skip, jitter=True)
    assert visible_samples(mix, bundle, origins, dirs, 1e-4).all()  # the second composite dropped nothing: same loss
    probs, idx = torch.cat(stats.probs), torch.cat(stats.idx)
    expected = _aux_reference(probs.detach(), idx, mix.penalty, "counts")
    assert 0 < expected and logs["aux"] == pytest.approx(expected, rel=1e-12)

# --- the chain through the CLI --------------------------------------------------------------------------
OFFICIAL = {"gate_res": 12, "gate_init": "expert", "aux_norm": "counts", "aux_samples": "visible", "mix": "alpha",
            "lam": 0.01, "lr_gate": 0.1, "penalty": "1, 1.5", "vd_source": "largest", "vd_filter": "visible"}
# the tiny recipe's moe section with every official option (the penalty: the official list's first two weights)


def test_build_finetune_and_eval_with_every_official_option(trained_ws, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    recipe = make_recipe(tmp_path / "official.yaml", moe=OFFICIAL)
    run_cli("build-moe", "--workspace", str(ws), "--recipe", str(recipe), "--device", "cpu", check=True)
    init = json.loads((ws / "moe" / "init.json").read_text())
    assert init["gate_init"] == "dvgo-12" and init["experts"] == ["dvgo-12", "dvgo-16"]
    mix, meta = load_mixture(ws / "moe" / "init.safetensors")
    expert, _, _ = load_expert(ws / "experts" / "dvgo-12.safetensors")
    assert mix.gate.shape == expert.shape and meta["gate"]["config"]["gate_channels"] == expert.feature_table.shape[1]
    assert torch.equal(mix.gate.table, expert.feature_table)  # an exact copy of the smallest expert's features

    run_cli("finetune", "--workspace", str(ws), "--recipe", str(recipe), "--topk", "2", "--device", "cpu", check=True)
    report = json.loads((ws / "moe" / "top2.json").read_text())
    assert (report["mix"], report["aux_norm"], report["aux_samples"]) == ("alpha", "counts", "visible")
    assert (report["penalty"], report["vd_source"], report["vd_filter"]) == ("1, 1.5", "largest", "visible")
    auxes = [h["aux"] for h in report["history"] if "aux" in h]
    # lambda * M / (sum c)^2 sum c m w with k = 2: at most M * max(w) / k = 2 * 2 / 2
    assert auxes and all(0 < a <= 2.0 for a in auxes)
    top2, meta = load_mixture(ws / "moe" / "top2.safetensors")
    assert (top2.cfg.mix, top2.cfg.aux_norm, top2.cfg.aux_samples) == ("alpha", "counts", "visible")
    assert (top2.cfg.vd_source, top2.cfg.vd_filter) == ("largest", "visible")
    assert not torch.equal(top2.gate.table, expert.feature_table)  # trained

    proc = run_cli("eval", "--workspace", str(ws), "--model", "top2", "--views", "1", "--no-costs", "--report",
                   "--device", "cpu", check=True)
    row = json.loads((ws / "reports" / "eval.json").read_text())["models"][0]
    assert row["name"] == "top2" and 5 < row["psnr"] < 60, proc.stdout

    # eval rendered with alpha mixing: the same model rendered in-process matches, with density mixing it does not
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.models import load_model
    from boostnerf_cli.stages.evaluate import evaluate_model
    from boostnerf_cli.workspace import Workspace

    w = Workspace(ws)
    scene = Survey(w).scene()
    model = load_model(w, "top2", "cpu")
    assert evaluate_model(model, scene, scene.split("test"), "cpu", None, views=1)["psnr"] == row["psnr"]
    model.field.cfg.mix = "density"
    assert evaluate_model(model, scene, scene.split("test"), "cpu", None, views=1)["psnr"] != row["psnr"]


def test_the_gate_can_start_from_an_expert_left_out_of_the_mixture(trained_ws, tmp_path):
    """The official layout: the gate's grid is a copy of a model that is not one of the mixture's experts."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    recipe = make_recipe(tmp_path / "outside.yaml", moe={**OFFICIAL, "topk": 1, "penalty": "geometric",
                                                         "gate_from": "dvgo-12"})
    run_cli("build-moe", "--workspace", str(ws), "--recipe", str(recipe), "--experts", "dvgo-16", "--device", "cpu",
            check=True)
    init = json.loads((ws / "moe" / "init.json").read_text())
    assert init["experts"] == ["dvgo-16"] and init["gate_init"] == "dvgo-12"
    mix, meta = load_mixture(ws / "moe" / "init.safetensors")
    expert, _, _ = load_expert(ws / "experts" / "dvgo-12.safetensors")
    assert mix.m == 1 and torch.equal(mix.gate.table, expert.feature_table)  # an exact copy, from outside
    # retraining the gate's source makes moe/init stale
    assert set(meta["signature"]["inputs"]) == {"dvgo-12", "dvgo-16"}

    shutil.rmtree(ws / "moe")
    bad = make_recipe(tmp_path / "bad.yaml", moe={**OFFICIAL, "topk": 1, "gate_from": "dvgo-99"})
    proc = run_cli("build-moe", "--workspace", str(ws), "--recipe", str(bad), "--experts", "dvgo-16", "--device", "cpu")
    assert_clean_failure(proc, "moe.gate_from = 'dvgo-99': no pretrained expert")
    assert not (ws / "moe" / "init.safetensors").exists()


