"""The mixture of experts: aux loss, sparse dispatch vs a dense reference, edge cases, persistence."""

import math

import pytest
import torch
from helpers import TOY_BOX, toy_mixture
from reference import dispatch_dense_reference

from boostnerf_cli.fields import grid as G
from boostnerf_cli.fields.base import BareField
from boostnerf_cli.models import load_mixture, save_mixture
from boostnerf_cli.moe.mixture import RoutingStats
from boostnerf_cli.moe.router import Routes, aux_loss, dispatch, penalty_weights, top_k
from boostnerf_cli.render.packing import DYNAMIC, Budgets
from boostnerf_cli.render.renderer import RenderSettings, render_rays


def _points(n, seed=1):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(n, 3, generator=g) * 1.8 - 0.9
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return xyz, d


def test_penalty_weights():
    assert torch.allclose(penalty_weights(3, "geometric"), torch.tensor([1.0, math.sqrt(3.0), 3.0]))
    assert torch.allclose(penalty_weights(5, "geometric")[-1], torch.tensor(5.0))
    assert penalty_weights(3, "linear").tolist() == [1.0, 2.0, 3.0]
    assert penalty_weights(3, "quadratic").tolist() == [1.0, 2.0, 4.0]
    assert penalty_weights(3, "none").tolist() == [1.0, 1.0, 1.0]
    for kind in ("geometric", "linear", "quadratic", "none"):
        assert penalty_weights(1, kind).tolist() == [1.0]


def test_aux_loss_equals_a_float64_hand_computation():
    g = torch.Generator().manual_seed(0)
    probs = torch.softmax(torch.randn(37, 4, generator=g, dtype=torch.float64), -1)
    _, idx = top_k(probs, 2, renormalize=True)
    w = penalty_weights(4, "geometric").double()
    n, m = probs.shape
    total = 0.0
    for i in range(m):
        c_i = sum(1 for s in range(n) for j in range(2) if int(idx[s, j]) == i)
        m_i = sum(float(probs[s, i]) for s in range(n))
        total += c_i * m_i * float(w[i])
    expected = m / n**2 * total
    assert abs(float(aux_loss(probs, idx, w)) - expected) < 1e-12
    # balanced and fully imbalanced limits from the paper: 1 and M (with w = 1, top-1)
    uniform = torch.full((8, 4), 0.25, dtype=torch.float64)
    bal_idx = torch.arange(8).remainder(4)[:, None]
    assert abs(float(aux_loss(uniform, bal_idx, torch.ones(4, dtype=torch.float64))) - 1.0) < 1e-12
    one_hot = torch.zeros(8, 4, dtype=torch.float64)
    one_hot[:, 0] = 1
    assert abs(float(aux_loss(one_hot, torch.zeros(8, 1, dtype=torch.long),
                              torch.ones(4, dtype=torch.float64))) - 4.0) < 1e-12


def test_aux_loss_empty_batch_is_zero_with_a_gradient_path():
    probs = torch.zeros(0, 3, requires_grad=True)
    loss = aux_loss(probs, torch.zeros(0, 2, dtype=torch.long), torch.ones(3))
    assert float(loss.detach()) == 0.0
    loss.backward()


@pytest.mark.parametrize("k", [1, 2, 3])
def test_render_routing_without_probabilities_matches_training_routing(k):
    """Rendering skips the softmax: top-k of the logits, weights = softmax of the chosen logits."""
    mix = toy_mixture(m=3, k=k)
    xyz, d = _points(500)
    with torch.no_grad():
        probs, vals, idx = mix.route(xyz)  # the full path (probabilities wanted)
        none, fast_vals, fast_idx = mix.route(xyz, need_probs=False)
        assert probs is not None and none is None
        assert torch.equal(fast_idx, idx)
        assert torch.allclose(fast_vals, vals, atol=1e-6, rtol=0)
        ref = torch.softmax(mix.gate.logits(xyz).double(), -1)
        chosen = ref.gather(1, idx)
        assert torch.allclose(fast_vals.double(), chosen / chosen.sum(-1, keepdim=True), atol=1e-6, rtol=0)
    mix.train()
    probs, _, _ = mix.route(xyz, need_probs=False)  # autograd on: the trained path, probabilities kept
    assert probs is not None


def _per_sample_reference(mix, xyz, dirs):
    """The paper's Sec. 3 written out one sample at a time in float64, with the experts, the gate's logits
    and V_D's density as black boxes: keep = 1 - exp(-sigma_D step) > T; p = softmax(logits);
    K = the k largest p; g_i = p_i (/ sum_K p when renormalised; 1 for k = 1); sigma = sum_K g_i sigma_i,
    c = sum_K g_i c_i. -> sigma (N,), colour (N, 3), keep (N,) as Python lists."""
    with torch.no_grad():
        logits = mix.gate.logits(xyz).double().tolist()
        sig = [e.density(xyz).double().tolist() for e in mix.experts]
        col = [e.color(xyz, dirs).double().tolist() for e in mix.experts]
        vd = mix.vd.density(xyz).double().tolist()
    k, out_s, out_c, keep = mix.cfg.topk, [], [], []
    for s in range(xyz.shape[0]):
        z = [math.exp(v - max(logits[s])) for v in logits[s]]
        p = [v / sum(z) for v in z]
        chosen = sorted(range(mix.m), key=lambda i: -p[i])[:k]
        if mix.cfg.renormalize:
            g = {i: (1.0 if k == 1 else p[i] / sum(p[j] for j in chosen)) for i in chosen}
        else:
            g = {i: p[i] for i in chosen}
        out_s.append(sum(g[i] * sig[i][s] for i in chosen))
        out_c.append([sum(g[i] * col[i][s][c] for i in chosen) for c in range(3)])
        keep.append(1.0 - math.exp(-vd[s] * mix.cfg.step) > mix.cfg.density_threshold)
    return torch.tensor(out_s, dtype=torch.float64), torch.tensor(out_c, dtype=torch.float64), torch.tensor(keep)


@pytest.mark.parametrize("k,renormalize", [(1, True), (2, True), (3, True), (1, False), (2, False)])
def test_mixture_equals_a_float64_per_sample_reference(k, renormalize):
    """Every way the tool evaluates a mixture -- the Field calls (rendering), the renderer's routed view
    (density, then colour of a subset of its samples), the training view with routing statistics -- and
    the V_D filter, against the hand-written reference."""
    mix = toy_mixture(m=3, k=k, renormalize=renormalize)
    xyz, d = _points(400, seed=5)
    ref_s, ref_c, ref_keep = _per_sample_reference(mix, xyz, d)
    assert 0 < int(ref_keep.sum()) < len(ref_keep)  # the filter keeps some samples and drops others
    tol = dict(atol=1e-4, rtol=1e-5)
    with torch.no_grad():
        assert torch.allclose(mix.density(xyz).double(), ref_s, **tol)
        assert torch.allclose(mix.color(xyz, d).double(), ref_c, **tol)
        assert torch.equal(mix.skip(xyz).cpu(), ref_keep)
        view = mix.batch_view()
        assert torch.allclose(view.density(xyz).double(), ref_s, **tol)
        rows = torch.nonzero(ref_keep).reshape(-1)
        assert torch.allclose(view.color_rows(rows, d[rows]).double(), ref_c[rows], **tol)
    stats = RoutingStats()
    trained = mix.with_stats(stats)  # autograd on: the training path, probabilities recorded
    assert torch.allclose(trained.density(xyz).detach().double(), ref_s, **tol)
    assert len(stats.probs) == 1 and stats.probs[0].shape == (400, 3)


def test_the_per_sample_reference_is_not_the_code_it_checks():
    """The reference fails a mixture whose routing is wrong: a mixture that takes the k *smallest* probabilities."""
    mix = toy_mixture(m=3, k=2)
    xyz, d = _points(200, seed=5)
    ref_s, _, _ = _per_sample_reference(mix, xyz, d)
    real = mix.gate.logits
    mix.gate.logits = lambda x: -real(x)  # routes to the other experts; the reference reads the true logits first
    with torch.no_grad():
        wrong = mix.density(xyz).double()
    assert not torch.allclose(wrong, ref_s, atol=1e-2)


@pytest.mark.parametrize("static", [False, True], ids=["dynamic", "static"])
def test_rendering_top1_with_unit_weights_skips_the_scaling_and_gives_the_same_bits(static, monkeypatch):
    """Rendering's renormalised Top-1 weighs every sample 1 exactly: the mixture tells the dispatch so (`Routes.unit`),
    which then adds each expert's output unscaled, bit for bit what scaling by the ones gives."""
    mix = toy_mixture(m=3, k=1)
    xyz, d = _points(300)
    packer = Budgets(quantum=16) if static else DYNAMIC
    with torch.no_grad():
        _, vals, idx = mix.route(xyz, need_probs=False)
        assert torch.equal(vals, torch.ones_like(vals))
        outs = [dispatch(Routes(vals, idx, 3, unit), lambda e, r: mix.experts[e].color(xyz[r], d[r]), 3, xyz, packer)
                for unit in (True, False)]
    assert torch.equal(outs[0], outs[1])
    import boostnerf_cli.moe.mixture as mixture_module

    units = []
    monkeypatch.setattr(mixture_module, "dispatch", lambda routes, *a, **kw: units.append(routes.unit) or dispatch(
        routes, *a, **kw))
    with torch.no_grad():
        mix.color(xyz, d)  # rendering: the unscaled sum
    mix.color(xyz, d)  # training (gradients on): scaled by the straight-through weight
    assert units == [True, False]


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_expert_rows_list_each_experts_choices_in_sample_order_and_leave_out_the_light_ones(k):
    """`ExpertRows.of` lists, per expert, the samples that chose it, in order, with their weights; with a minimum
    weight (two weights a sample that sum to 1), a choice under it is left out and the other one weighs 1."""
    from boostnerf_cli.moe.router import ExpertRows

    g = torch.Generator().manual_seed(k)
    m, n = 5, 400
    idx = torch.stack([torch.randperm(m, generator=g)[:k] for _ in range(n)])
    vals = torch.rand(n, k, generator=g)
    if k == 2:
        vals[:, 0] = torch.where(torch.rand(n, generator=g) < 0.4, 0.995, vals[:, 0])
        vals[:, 1] = 1 - vals[:, 0]
    for w in ([0.0, 0.01] if k == 2 else [0.0]):
        listed = ExpertRows.of(Routes(vals, idx, m), w)
        for e in range(m):
            hit = (idx == e) & (vals >= w)
            rows = hit.any(-1).nonzero().squeeze(-1)
            weight = (vals * hit).sum(-1)[rows]
            if w > 0:
                weight = torch.where(weight > 1 - w, 1.0, weight)
            assert torch.equal(listed.rows[e], rows) and torch.equal(listed.weights[e], weight), (k, w, e)
    assert ExpertRows.of(Routes(vals, idx, m, unit=True)).weights == [None] * m


@pytest.mark.parametrize("static", [False, True], ids=["dynamic", "static"])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_sparse_dispatch_matches_dense_reference_in_values_and_gradients(k, static):
    """Each expert on its own samples gives the dense reference's values and gradients, with the samples listed
    exactly (dynamic packing) or in fixed budgets whose pads must not count (static; a small quantum, so the
    budgets hold pads)."""
    mix = toy_mixture(m=3, k=k)
    xyz, d = _points(300)
    probs, vals, idx = mix.route(xyz)
    packer = Budgets(quantum=16) if static else DYNAMIC

    def sparse():
        s = dispatch(Routes(vals, idx, 3), lambda e, r: mix.experts[e].density(xyz[r])[:, None], 1, xyz, packer)
        c = dispatch(Routes(vals, idx, 3), lambda e, r: mix.experts[e].color(xyz[r], d[r]), 3, xyz, packer)
        return s, c

    def dense():
        s = dispatch_dense_reference(300, idx, vals, 3, lambda e: mix.experts[e].density(xyz)[:, None], 1, xyz)
        c = dispatch_dense_reference(300, idx, vals, 3, lambda e: mix.experts[e].color(xyz, d), 3, xyz)
        return s, c

    params = list(mix.parameters())
    up_s, up_c = torch.randn(300, 1), torch.randn(300, 3)
    outs = []
    for fn in (sparse, dense):
        probs, vals, idx = mix.route(xyz)  # fresh graph each time
        s, c = fn()
        grads = torch.autograd.grad((s * up_s).sum() + (c * up_c).sum(), params, allow_unused=True)
        outs.append((s, c, grads))
    (s1, c1, g1), (s2, c2, g2) = outs
    assert torch.allclose(s1, s2, atol=1e-5) and torch.allclose(c1, c2, atol=1e-6)
    assert packer.overflowed() is None or not bool(packer.overflowed())
    for a, b in zip(g1, g2):
        if a is None or b is None:
            assert (a is None or a.abs().max() == 0) and (b is None or b.abs().max() == 0)
        else:
            assert torch.allclose(a, b, atol=1e-5)


def test_mixture_density_matches_the_papers_formula():
    mix = toy_mixture(m=3, k=2, renormalize=False)
    xyz, d = _points(50)
    probs = mix.gate.probs(xyz)
    vals, idx = torch.topk(probs, 2, dim=-1)
    sig = torch.stack([e.density(xyz) for e in mix.experts], -1)
    expected = (vals * sig.gather(1, idx)).sum(-1)
    assert torch.allclose(mix.density(xyz), expected, atol=1e-5)


def test_ensemble_is_the_plain_average():
    mix = toy_mixture(m=3, k=3, kind="uniform")
    xyz, d = _points(40)
    expected = torch.stack([e.color(xyz, d) for e in mix.experts]).mean(0)
    assert torch.allclose(mix.color(xyz, d), expected, atol=1e-6)


def test_an_expert_with_no_samples_and_extreme_gate_logits_stay_finite():
    mix = toy_mixture(m=3, k=1)
    with torch.no_grad():
        last = mix.gate.mlp[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([1e4, -1e4, 0.0]))
    xyz, d = _points(100)
    stats = RoutingStats()
    view = mix.with_stats(stats)
    sigma = view.density(xyz)
    rgb = view.color(xyz, d)
    aux = stats.aux(mix.penalty)
    (sigma.sum() + rgb.sum() + aux).backward()
    assert stats.load(3).tolist() == [1.0, 0.0, 0.0]
    for t in (sigma, rgb, aux):
        assert torch.isfinite(t).all()
    for p in mix.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()


def test_every_sample_filtered_gives_background_and_no_nan():
    mix = toy_mixture(m=2, k=1)
    o = torch.tensor([[0.0, 0.0, 3.0]]).repeat(8, 1)
    d = torch.tensor([[0.0, 0.0, -1.0]]).repeat(8, 1)
    s = RenderSettings(step=0.05, near=0.1, far=6.0, bbox=TOY_BOX, background=(1.0, 0.5, 0.0))
    stats = RoutingStats()
    b = render_rays(mix.with_stats(stats), o, d, s, skip=lambda x: torch.zeros(x.shape[0], dtype=torch.bool))
    assert b.n_samples == 0 and torch.allclose(b.color, torch.tensor([[1.0, 0.5, 0.0]]).repeat(8, 1))
    assert float(stats.aux(mix.penalty)) == 0.0 and torch.isfinite(b.depth).all()


def test_a_single_expert_mixture_equals_the_expert():
    mix = toy_mixture(m=1, k=1)
    xyz, d = _points(60)
    e = mix.experts[0]
    assert torch.allclose(mix.density(xyz), e.density(xyz), atol=1e-6)
    assert torch.allclose(mix.color(xyz, d), e.color(xyz, d), atol=1e-6)


def test_topk_larger_than_m_is_refused():
    from boostnerf_cli.errors import BoostNerfError

    with pytest.raises(BoostNerfError, match="moe.topk = 3 but the mixture has 2 experts"):
        toy_mixture(m=2, k=3)


@pytest.mark.parametrize("kind", ["grid", "linear", "switch"])
def test_save_load_round_trip(tmp_path, kind):
    mix = toy_mixture(m=3, k=2, kind=kind)
    save_mixture(tmp_path / "m.safetensors", mix)
    mix2, meta = load_mixture(tmp_path / "m.safetensors")
    xyz, d = _points(30)
    assert torch.equal(mix.density(xyz), mix2.density(xyz))
    assert torch.equal(mix.color(xyz, d), mix2.color(xyz, d))
    assert torch.equal(mix.skip(xyz), mix2.skip(xyz))
    assert meta["mixture"]["topk"] == 2 and meta["gate"]["config"]["gate_type"] == kind


def test_top1_renormalised_is_a_straight_through_one():
    logits = torch.randn(20, 3, dtype=torch.float64, requires_grad=True)
    probs = torch.softmax(logits, -1)
    vals, idx = top_k(probs, 1, renormalize=True)
    assert torch.equal(vals.detach(), torch.ones(20, 1, dtype=torch.float64))
    raw, raw_idx = top_k(probs, 1, renormalize=False)
    assert torch.equal(idx, raw_idx)
    g = torch.randn(20, 1, dtype=torch.float64)
    (grad_st,) = torch.autograd.grad((vals * g).sum(), logits, retain_graph=True)
    (grad_raw,) = torch.autograd.grad((raw * g).sum(), logits)
    assert torch.allclose(grad_st, grad_raw, atol=1e-15)  # the gate still learns from the photometric loss


@pytest.mark.parametrize("k", [1, 2])
def test_renderer_routes_each_sample_once_and_matches_the_plain_mixture(k, monkeypatch):
    """The routed view reuses the density pass's routing for colour: same image and gradients, one gate call."""
    mix = toy_mixture(k=k)
    g = torch.Generator().manual_seed(3)
    origins = torch.tensor([0.0, 0.0, -3.0]).expand(16, 3).clone()
    dirs = torch.nn.functional.normalize(torch.randn(16, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    settings = RenderSettings(step=0.05, near=0.1, far=6.0, bbox=TOY_BOX, color_threshold=1e-4)

    def render(routed: bool):
        mix.zero_grad()
        field = mix if routed else BareField(mix)
        b = render_rays(field, origins, dirs, settings, mix.skip)
        b.color.sum().backward()
        return b.color.detach(), [p.grad.clone() if p.grad is not None else None for p in mix.parameters()]

    calls = []
    real_probs = mix.gate.probs
    monkeypatch.setattr(mix.gate, "probs", lambda x: calls.append(x.shape[0]) or real_probs(x))
    color_routed, grads_routed = render(routed=True)
    assert len(calls) == 1  # the gate ran once, on the density pass
    color_plain, grads_plain = render(routed=False)
    assert len(calls) == 3  # the plain field runs it again for the colour pass
    assert torch.allclose(color_routed, color_plain, atol=1e-6)
    for a, b in zip(grads_routed, grads_plain):
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.allclose(a, b, atol=1e-5)


def test_baked_gate_equals_the_gate_at_its_lattice_and_has_nothing_to_train():
    from boostnerf_cli.fields import grid as G

    mix = toy_mixture()
    baked = mix.gate.baked(9)
    pts = G.lattice_points(baked.bbox, baked.shape)
    assert torch.allclose(baked.logits(pts), mix.gate.logits(pts), atol=1e-5)
    assert list(baked.parameters()) == []
    # between vertices it interpolates the logits: close to the gate, closer with a finer lattice
    xyz, _ = _points(500)
    with torch.no_grad():
        err = [float((mix.gate.probs(xyz) - mix.gate.baked(r).probs(xyz)).abs().max()) for r in (5, 17, 65)]
    assert err[2] < err[0] and err[2] < 0.05


def test_rendering_a_mixture_uses_the_baked_gate_unless_asked_for_the_exact_one():
    import dataclasses

    mix = toy_mixture(k=1)
    mix.cfg = dataclasses.replace(mix.cfg, bake_res=0)
    assert mix.for_rendering().gate.cfg.gate_type == "grid"
    mix.cfg = dataclasses.replace(mix.cfg, bake_res=33)
    assert mix.for_rendering(exact_gate=True).gate.cfg.gate_type == "grid"
    exact = mix.gate
    assert mix.for_rendering().gate.cfg.gate_type == "baked"
    xyz, _ = _points(300)
    agree = (exact.probs(xyz).argmax(-1) == mix.gate.probs(xyz).argmax(-1)).float().mean()
    assert agree > 0.9  # top-1 routing changes only next to the gate's decision boundaries


@pytest.mark.parametrize("k", [1, 2])
def test_topk_routing_changes_with_the_gate(k):
    """The experts chosen are the gate's: perturbing the gate's parameters changes them, restoring them restores
    them."""
    mix = toy_mixture(m=3, k=k)
    xyz, _ = _points(500)
    with torch.no_grad():
        _, _, before = mix.route(xyz, need_probs=False)
        saved = [p.clone() for p in mix.gate.parameters()]
        g = torch.Generator().manual_seed(7)
        for p in mix.gate.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.5)
        _, _, after = mix.route(xyz, need_probs=False)
        changed = (torch.sort(after, -1).values != torch.sort(before, -1).values).any(-1).float().mean()
        assert changed > 0.2, float(changed)
        for p, q in zip(mix.gate.parameters(), saved, strict=True):
            p.copy_(q)
        _, _, again = mix.route(xyz, need_probs=False)
    assert torch.equal(again, before)


def test_lambda_moves_the_load_to_the_cheap_experts_in_inverse_proportion_to_their_weights():
    """Descending lambda * L_rw-aux alone (Top-1, from a gate that sends 95% of the samples to the middle expert):
    at lambda 0 the routing does not move; at lambda > 0 it settles where c_i w_i is equal for every expert, i.e.
    the load is proportional to 1 / w_i (geometric w = 1, 1.73, 3: loads 0.52, 0.30, 0.17), the cheapest expert
    taking the most. Measured when written: [0.051, 0.949, 0.0] -> [0.523, 0.301, 0.176] after 100 Adam steps."""
    from boostnerf_cli.moe.router import expert_counts

    torch.manual_seed(1)
    xyz = TOY_BOX[0] + torch.rand(4096, 3) * (TOY_BOX[1] - TOY_BOX[0])
    loads = {}
    for lam in (0.0, 1.0):
        mix = toy_mixture(m=3, k=1, seed=0).train()

        def load(mix=mix):
            with torch.no_grad():
                _, _, idx = mix.route(xyz)
            return expert_counts(idx, 3) / idx.shape[0]

        start = load()
        opt = torch.optim.Adam(mix.gate.parameters(), lr=0.05)
        for _ in range(100):
            stats = RoutingStats()
            mix.with_stats(stats).density(xyz)
            loss = lam * stats.aux(mix.penalty)
            opt.zero_grad()
            loss.backward()
            opt.step()
        loads[lam] = (start, load())
    start, end = loads[0.0]
    assert start[1] > 0.9 and torch.equal(start, end)  # no auxiliary loss: the routing stays where it was
    start, end = loads[1.0]
    target = (1 / penalty_weights(3, "geometric")) / (1 / penalty_weights(3, "geometric")).sum()
    assert torch.allclose(end, target, atol=0.03), (end, target)
    assert end[0] > end[1] > end[2]


# ----------------------------------------------------------------------------- decisions per cell (moe/cells.py)


def _rendered(mix, image_camera, settings, use_cells: bool, monkeypatch, route_by_cells: bool = False):
    """The image through the per-cell tables, or (`use_cells` False) testing V_D and the grid on every sample and
    blending the gate on every sample (but with `route_by_cells`: Top-1 routed by its cells as rendering does)."""
    from boostnerf_cli.render.renderer import render_image

    with monkeypatch.context() as m:
        if not use_cells:
            if not route_by_cells:
                m.setattr(type(mix), "cells", lambda self: None)
            m.setattr(type(mix), "skips", lambda self: None)
        return render_image(mix, image_camera, settings, mix.skip)


def _renders_close_without_blending_the_gate(mix, monkeypatch):
    """Rendering `mix` through its cells blends the gate on no sample, and gives an image close to (not equal to)
    blending it on every sample."""
    from boostnerf_cli.render.renderer import Camera, RenderSettings

    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.0, 0.0, 2.5])
    camera = Camera(pose, torch.tensor([24.0, 24.0, 12.0, 12.0]), 24, 24)
    settings = RenderSettings(step=0.05, near=0.5, far=5.0, bbox=TOY_BOX)
    logits, calls = type(mix.gate).logits, []
    monkeypatch.setattr(type(mix.gate), "logits", lambda self, xyz: calls.append(len(xyz)) or logits(self, xyz))
    fast = _rendered(mix, camera, settings, True, monkeypatch)
    assert not calls  # no sample blended the gate
    slow = _rendered(mix, camera, settings, False, monkeypatch)
    assert sum(calls) == slow["n_samples"] > 0
    diff = (fast["rgb"] - slow["rgb"]).abs()
    assert 0 < diff.max() and diff.mean() < 0.01, (diff.max(), diff.mean())


@pytest.mark.parametrize("k", [1, 2])
def test_deciding_per_cell_renders_the_same_image_bit_for_bit(k, monkeypatch):
    """V_D's test looked up per lattice cell (where all 8 vertices agree), and the samples made only where the cells
    may keep them (`renderer.sample_list`'s runs), give the image that testing every sample gives, to the last bit
    (Top-1 routed by its cells both ways: `test_top1_routes_by_its_cells_without_blending_the_gate`)."""
    from boostnerf_cli.moe import cells as C
    from boostnerf_cli.render import renderer as R
    from boostnerf_cli.render.renderer import Camera, RenderSettings

    mix = toy_mixture(k=k, seed=3)
    mix.cfg.bake_res = 16
    with torch.no_grad():  # V_D with a surface: dense inside a ball, empty outside
        pts = G.lattice_points(mix.vd.bbox, mix.vd.shape)
        mix.vd.table.copy_(torch.where(pts.norm(dim=-1, keepdim=True) < 0.6, 3.0, -8.0))
    mix.for_rendering()
    with torch.no_grad():
        cells, tables = mix.cells(), mix.skips()
    assert cells is not None and tables is not None and (cells.top1 is not None) == (k == 1)
    states = torch.bincount(tables.vd.long(), minlength=3)
    assert states[C.PASS] > 0 and states[C.FAIL] > 0 and states[C.MIXED] > 0, states
    if k == 1:  # most cells (the baked gate's, halved) have one clear expert
        assert (cells.top1 >= 0).float().mean() > 0.5 and cells.shape == C.halved(mix.gate.shape)
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.0, 0.0, 2.5])
    camera = Camera(pose, torch.tensor([24.0, 24.0, 12.0, 12.0]), 24, 24)
    settings = RenderSettings(step=0.05, near=0.5, far=5.0, bbox=TOY_BOX)
    runs = []  # with the tables, the samples are made only in runs that reach a cell they may keep
    monkeypatch.setattr(R, "_runs_kept", lambda *a, _made=R._runs_kept: runs.append(1) or _made(*a))
    fast = _rendered(mix, camera, settings, True, monkeypatch)
    assert runs
    slow = _rendered(mix, camera, settings, False, monkeypatch, route_by_cells=True)
    assert fast["n_samples"] == slow["n_samples"] > 0 and fast["n_color"] == slow["n_color"]
    for key in ("rgb", "depth", "acc"):
        assert torch.equal(fast[key], slow[key]), key
    # Top-1's shortcut is for rendering: a mixture that trains (gradients on) routes every sample by its gate; V_D and
    # the grid do not train, so their decisions hold, until V_D's table changes
    with torch.enable_grad():
        assert mix.cells() is None and mix.skips() is tables
    with torch.no_grad():
        mix.vd.table.add_(0.0)
    assert mix.skips() is None


def test_top1_routes_by_its_cells_without_blending_the_gate(monkeypatch):
    """Rendering a renormalised Top-1 through a baked gate routes every sample by its half-cell (`cells.route_cells`
    with `at_centre`): the gate is never blended per sample, a sample in a cell its vertices decide goes where the
    blend sends it, and the image differs from blending every sample only where a cell straddles the gate's border
    between two experts, and little there."""
    from boostnerf_cli.moe import cells as C

    mix = toy_mixture(k=1, seed=3)
    mix.cfg.bake_res = 16
    mix.for_rendering()
    with torch.no_grad():
        cells = mix.cells()
    assert cells is not None and cells.top1 is not None and bool((cells.top1 >= 0).all())
    decided = C.route_cells(mix.gate.logit_table, mix.gate.shape)[0]
    assert (decided < 0).any() and torch.equal(cells.top1[decided >= 0], decided[decided >= 0])
    g = torch.Generator().manual_seed(1)
    box = mix.gate.bbox
    pts = box[0] + torch.rand(20000, 3, generator=g) * (box[1] - box[0])
    with torch.no_grad():
        _, _, chosen = mix.route(pts, need_probs=False)
        blended = mix.gate.logits(pts).max(-1).indices
    clear = decided.index_select(0, C.cell_index(pts, box, cells.shape)) >= 0
    assert torch.equal(chosen[:, 0][clear], blended[clear]) and 0.5 < clear.float().mean() < 1
    with torch.enable_grad():  # with gradients too (`prune` follows what rendering reads): the same choice, weight 1
        probs, vals, idx = mix.route(pts)
    assert torch.equal(idx, chosen) and torch.equal(vals, torch.ones_like(vals)) and probs.shape == (len(pts), 3)
    _renders_close_without_blending_the_gate(mix, monkeypatch)


def test_top2_leaves_out_a_choice_below_the_render_min_weight_and_moves_pixels_little(monkeypatch):
    """`moe.render_min_weight` w: rendering a renormalised Top-2 leaves out, in both passes, a choice weighing less
    than w (its share goes to the other): fewer expert densities and colours, images within a few w."""
    from boostnerf_cli.render.renderer import Camera, RenderSettings, render_image

    mix = toy_mixture(k=2, seed=4)
    mix.cfg.bake_res = 16
    mix.for_rendering()
    with torch.no_grad():
        mix.gate.logit_table.mul_(12.0)  # a sharp gate: many second choices weigh little
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.0, 0.0, 2.5])
    camera = Camera(pose, torch.tensor([24.0, 24.0, 12.0, 12.0]), 24, 24)
    settings = RenderSettings(step=0.05, near=0.5, far=5.0, bbox=TOY_BOX)
    calls = {"density": [], "color": []}
    for e in mix.experts:
        monkeypatch.setattr(e, "density", lambda xyz, f=e.density: calls["density"].append(len(xyz)) or f(xyz))
        monkeypatch.setattr(e, "color", lambda xyz, d, f=e.color: calls["color"].append(len(xyz)) or f(xyz, d))
    images, counts = {}, {}
    for w in (0.0, 0.05):
        mix.configure(render_min_weight=w)
        for v in calls.values():
            v.clear()
        images[w] = render_image(mix, camera, settings, mix.skip)["rgb"]
        counts[w] = {k: sum(v) for k, v in calls.items()}
    assert counts[0.05]["density"] < 0.9 * counts[0.0]["density"]
    assert counts[0.05]["color"] < 0.9 * counts[0.0]["color"]
    assert 0 < (images[0.05] - images[0.0]).abs().max() <= 0.1
    mix.configure(topk=1)  # one weight a sample: nothing to leave out
    assert mix.render_min_weight() == 0.0


def test_top2_takes_its_pair_and_weights_at_each_half_cells_centre_without_blending_the_gate(monkeypatch):
    """Rendering a renormalised Top-2 through a baked gate looks each sample's two experts and weights up in its
    half-cell (`cells.pair_cells`): the gate's top two at the cell's centre and their softmax, to 1/510; the gate is
    never blended per sample, and the image stays close to blending every sample. With gradients (`prune`) the same
    pair, weighted by the gate's own probabilities."""
    from boostnerf_cli.moe import cells as C
    from boostnerf_cli.moe.gate import softmax

    mix = toy_mixture(k=2, seed=4)
    mix.cfg.bake_res = 16
    mix.for_rendering()
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():  # a baked gate whose top two change across the box
        mix.gate.logit_table.copy_(torch.randn(mix.gate.logit_table.shape, generator=g) * 3)
    mix.configure()  # its cells made again
    with torch.no_grad():
        cells = mix.cells()
    assert cells is not None and cells.top1 is None and cells.top2 is not None
    assert cells.shape == C.halved(mix.gate.shape)
    box = mix.gate.bbox
    pts = box[0] + torch.rand(5000, 3, generator=g) * (box[1] - box[0])
    cell = C.cell_index(pts, box, cells.shape)
    dims = torch.tensor([n - 1 for n in cells.shape])
    ijk = torch.stack([cell // (dims[1] * dims[2]), cell // dims[2] % dims[1], cell % dims[2]], -1)
    with torch.no_grad():
        _, vals, idx = mix.route(pts, need_probs=False)
        top, expected = mix.gate.logits(box[0] + (ijk + 0.5) / dims * (box[1] - box[0])).topk(2, dim=-1)
        blended = mix.gate.logits(pts).topk(2, dim=-1).indices
    assert torch.equal(idx, expected)
    assert torch.allclose(vals, softmax(top), atol=1 / 1020 + 1e-6) and torch.allclose(vals.sum(-1), torch.ones(5000))
    assert 0.5 < (idx == blended).all(-1).float().mean() < 1  # the blend's pair where the cell's centre has it
    with torch.enable_grad():
        probs, graded, same = mix.route(pts)
    assert torch.equal(same, idx)
    assert torch.allclose(graded, probs.gather(1, idx) / probs.gather(1, idx).sum(-1, keepdim=True))
    monkeypatch.setattr(C, "SLAB_VALUES", 1)  # slabs of one gate cell: the same cells
    again, _ = C.pair_cells(mix.gate.logit_table, mix.gate.shape)
    assert torch.equal(again.pair, cells.top2.pair) and torch.equal(again.weight, cells.top2.weight)
    monkeypatch.setattr(C, "MAX_ROUTE_CELLS", 1)  # too many halves: the gate's own cells, slab by slab or at once
    whole, lattice = C.pair_cells(mix.gate.logit_table, mix.gate.shape)
    monkeypatch.setattr(C, "SLAB_VALUES", 1 << 30)
    once, _ = C.pair_cells(mix.gate.logit_table, mix.gate.shape)
    assert lattice == mix.gate.shape and torch.equal(whole.pair, once.pair) and torch.equal(whole.weight, once.weight)
    monkeypatch.undo()
    _renders_close_without_blending_the_gate(mix, monkeypatch)


@pytest.mark.parametrize("m", [2, 3, 5, 8])
def test_the_top_two_of_each_cell_are_a_stable_sorts_first_two(m):
    """`cells._top_two` (Top-2's pair at a cell's centre): the largest and second largest channel, the first of equals
    first, as a stable descending sort gives them, with their values."""
    from boostnerf_cli.moe import cells as C

    values = torch.randint(0, 4, (m, 50, 7), generator=torch.Generator().manual_seed(m)).float()  # many ties
    first, i1, second, i2 = C._top_two(values)
    order = torch.sort(-values.movedim(0, -1), dim=-1, stable=True).indices
    assert torch.equal(i1.long(), order[..., 0]) and torch.equal(i2.long(), order[..., 1])
    assert torch.equal(first, values.max(0).values) and torch.equal(second, values.gather(0, i2.long()[None])[0])


def test_a_cell_is_decided_only_where_all_its_vertices_agree_with_a_margin():
    from boostnerf_cli.moe import cells as C

    shape = (3, 2, 2)  # two cells along x
    raw = torch.tensor([5.0, 5, 5, 5, 5, 5, 5, 5, -5, -5, -5, -5])[:, None]  # cell 0: all above; cell 1: mixed
    assert C.vd_states(raw, shape, 0.0).tolist() == [C.PASS, C.MIXED]
    assert C.vd_states(raw - 10, shape, 0.0).tolist() == [C.FAIL, C.FAIL]
    assert C.vd_states(torch.zeros(12, 1), shape, 0.0).tolist() == [C.MIXED, C.MIXED]  # on the threshold: blend
    logits = torch.zeros(12, 2)
    logits[:, 1] = 1.0  # expert 1 everywhere ...
    logits[8:, 0] = 2.0  # ... but expert 0 at the last four vertices
    assert C.top1_cells(logits, shape).tolist() == [1, -1]
    logits[:, 0] = logits[:, 1]  # a tie at every vertex: blended, never decided by the cell
    assert C.top1_cells(logits, shape).tolist() == [-1, -1]
    xyz = torch.tensor([[-1.0, -1.0, -1.0], [0.2, 0.5, 0.5], [1.0, 1.0, 1.0], [3.0, 0.0, 0.0]])
    assert C.cell_index(xyz, TOY_BOX, shape).tolist() == [0, 1, 1, 1]
    # the raw value where V_D's opacity over one step is T
    r = C.threshold_raw(1e-3, 0.05, 0.1, -4.0)
    sigma = torch.nn.functional.softplus(torch.tensor(r, dtype=torch.float64) - 4.0) / 0.1
    assert float(-torch.expm1(-sigma * 0.05)) == pytest.approx(1e-3, rel=1e-9)


def test_halved_gate_cells_decide_more_samples_and_each_as_the_blend_does(monkeypatch):
    """`cells.route_cells` decides Top-1's expert on the gate's cells halved along every axis: every sample in a decided
    half-cell is the gate blend's choice there, more samples are decided than by whole cells, slabs of any size give
    the same table, and a lattice whose halves would be too many keeps the gate's own cells."""
    from boostnerf_cli.moe import cells as C

    g = torch.Generator().manual_seed(5)
    shape, m = (6, 7, 5), 3
    box = torch.tensor([[-1.0, -0.5, -1.2], [1.0, 0.9, 0.4]])
    logits = torch.randn(math.prod(shape), m, generator=g) * 3
    table, fine = C.route_cells(logits, shape)
    assert fine == C.halved(shape) == (11, 13, 9) and table.shape == (10 * 12 * 8,)
    monkeypatch.setattr(C, "SLAB_VALUES", 1)  # one of the gate's x-cells a slab
    assert torch.equal(C.route_cells(logits, shape)[0], table)
    pts = box[0] + torch.rand(20000, 3, generator=g) * (box[1] - box[0])
    blended = G.lookup(logits, *G.corners(pts, box, shape)).max(-1).indices
    halves = table.index_select(0, C.cell_index(pts, box, fine)).long()
    wholes = C.top1_cells(logits, shape).index_select(0, C.cell_index(pts, box, shape)).long()
    decided = halves >= 0
    assert torch.equal(halves[decided], blended[decided])
    assert decided.float().mean() > (wholes >= 0).float().mean() + 0.1

    def centres_decided(lattice: tuple[int, int, int], decided: torch.Tensor) -> torch.Tensor:
        """at_centre: every cell its vertices decide as they do, the others the expert the blend gives at its centre."""
        filled, got = C.route_cells(logits, shape, at_centre=True)
        assert got == lattice and bool((filled >= 0).all()) and (decided < 0).any()
        assert torch.equal(filled[decided >= 0], decided[decided >= 0])
        cell = torch.arange(decided.numel())[decided < 0]
        dims = torch.tensor([n - 1 for n in lattice])
        ijk = torch.stack([cell // (dims[1] * dims[2]), cell // dims[2] % dims[1], cell % dims[2]], -1)
        centres = box[0] + (ijk + 0.5) / dims * (box[1] - box[0])
        assert torch.equal(filled[cell].long(), G.lookup(logits, *G.corners(centres, box, shape)).max(-1).indices)
        return filled

    filled = centres_decided(fine, table)
    monkeypatch.setattr(C, "SLAB_VALUES", 1)
    assert torch.equal(C.route_cells(logits, shape, at_centre=True)[0], filled)
    monkeypatch.setattr(C, "MAX_ROUTE_CELLS", 10 * 12 * 8 - 1)  # too many halves: the gate's own cells, the same rule
    decided, lattice = C.route_cells(logits, shape)
    assert lattice == shape and torch.equal(decided, C.top1_cells(logits, shape))
    centres_decided(shape, decided)


@pytest.mark.parametrize("seed,occupied", [(0, True), (1, True), (2, True), (0, False)])
def test_both_skips_looked_up_per_fine_cell_keep_exactly_the_samples_testing_each_keeps(seed, occupied):
    """The occupancy grid and V_D's test decided together per fine cell (`cells.skip_states`) keep the same samples
    as testing each in turn, on lattices that do not line up, with points on the box's faces, just past them and
    outside; and most points are decided by their fine cell."""
    from boostnerf_cli.moe import cells as C
    from boostnerf_cli.render.occupancy import OccupancyGrid

    g = torch.Generator().manual_seed(seed)
    mix = toy_mixture(k=1, seed=seed)
    with torch.no_grad():  # V_D: a lumpy ball and a slab reaching three of the box's faces, empty elsewhere
        pts = G.lattice_points(mix.vd.bbox, mix.vd.shape)
        lump = 0.55 + 0.1 * torch.rand(pts.shape[0], generator=g)
        dense = (pts.norm(dim=-1) < lump) | (pts[:, 0] > 0.3)
        mix.vd.table.copy_(torch.where(dense, 4.0, -9.0)[:, None])
    occ = torch.rand(7, 5, 6, generator=g) < 0.8  # cells of another size than V_D's
    box = TOY_BOX * (0.85 if seed == 1 else 1.0)  # a grid over a smaller box than V_D's: past it, empty
    mix.occupancy = OccupancyGrid(occ, box) if occupied else None
    mix.for_rendering()
    lo, hi = TOY_BOX
    xyz = lo + (hi - lo) * torch.rand(40000, 3, generator=g) * 1.2 - 0.1 * (hi - lo)
    face = lo + (hi - lo) * torch.rand(3000, 3, generator=g)
    for a in range(3):  # on each face, and a float32 step past and short of it
        for end in (lo, hi):
            for nudge in (0.0, 1.0, -1.0):
                p = face.clone()
                p[:, a] = torch.nextafter(end[a], end[a] + nudge) if nudge else end[a]
                xyz = torch.cat([xyz, p])
    valid = torch.ones(xyz.shape[0], 1, dtype=torch.bool)
    with torch.no_grad():
        tables = mix.skips()
        fused = mix.skip.filter(xyz[:, None], valid, 0.05, 0.0)
        decided = tables.skip(xyz)
        tables.skip = C.SkipCells(torch.full_like(tables.skip.state, C.MIXED), tables.skip.bbox)  # every cell mixed
        each = mix.skip.filter(xyz[:, None], valid, 0.05, 0.0)
    assert torch.equal(fused, each)
    assert 0 < int(fused.sum()) < xyz.shape[0]
    assert float((decided != C.MIXED).float().mean()) > 0.5


@pytest.mark.parametrize("mix_mode", ["density", "alpha"])
def test_the_ensemble_runs_every_expert_on_the_samples_themselves_with_the_same_bits(mix_mode, monkeypatch):
    """The ensemble sends every sample to every expert: rendering runs each expert on the samples as they are, no
    sort, no gathered copy, outputs added in order (`Routes.every`), and gives, to the bit, what listing each
    expert's samples through the sort gives: the density pass, a colour pass over some of its samples, and the
    training view with its gradients."""
    import boostnerf_cli.moe.mixture as mixture_module

    mix = toy_mixture(m=3, k=2)
    mix.configure(mix=mix_mode)
    mix.make_ensemble()
    xyz, d = _points(500, seed=7)
    rows = torch.arange(0, 500, 3)
    seen = []
    real = mixture_module.Mixture.routes

    def both(listed: bool):
        def routes(self, vals, idx):
            r = real(self, vals, idx)
            seen.append(r.every)
            return r if listed else r._replace(every=False)

        monkeypatch.setattr(mixture_module.Mixture, "routes", routes)
        with torch.no_grad():
            view = mix.batch_view()
            out = [view.density(xyz), view.color_rows(rows, d[rows]), mix.density(xyz), mix.color(xyz, d)]
        trained = mix.with_stats(RoutingStats())
        s = trained.density(xyz)
        grads = torch.autograd.grad(s.square().sum(), [p for p in mix.parameters() if p.requires_grad],
                                    allow_unused=True)
        return out, [s.detach(), *[g for g in grads if g is not None]]

    (every, every_grads), (listed, listed_grads) = both(True), both(False)
    assert seen and all(seen)  # the mixture marks every ensemble's routes
    assert len(every_grads) >= 4  # the density and its gradients in every expert's density grid
    for a, b in zip(every + every_grads, listed + listed_grads, strict=True):
        assert torch.equal(a, b)
    assert float(every[1].abs().sum()) > 0 and len(every[1]) == len(rows)


def test_the_ensemble_refuses_half_points_as_every_mixture_does():
    """Points of another precision than the experts' outputs are refused alike by the ensemble's every-sample path
    and by a Top-2's lists (an index_add of another dtype), never rounded silently into the output."""
    for make in (lambda m: m.make_ensemble(), lambda m: None):
        mix = toy_mixture(m=3, k=2)
        make(mix)
        xyz, _ = _points(50, seed=3)
        with torch.no_grad(), pytest.raises(RuntimeError, match="same scalar type|dtype"):
            mix.batch_view().density(xyz.half())
