"""Numerical stress (property-based): extreme densities, steps, logits and coordinates stay finite and
within the tolerances of docs/reliability.md of float64 references, in float32 and under CPU autocast.

Every tolerance used here is a named constant and is listed in docs/reliability.md.
"""

import copy
import math

import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from boostnerf_cli.fields import grid as G
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.router import aux_loss, penalty_weights, top_k
from boostnerf_cli.render.renderer import RenderSettings, render_rays
from boostnerf_cli.render.volrend import composite, render_weights

# documented tolerances (docs/reliability.md, "How close are the float32 and reduced-precision results to
# float64?")
W_ATOL = 1e-6  # rendering weights, float32 vs float64
COLOR_ATOL = 1e-6  # composited colour and opacity, float32 vs float64
GRAD_ATOL_PER_STEP = 1e-5  # d(colour)/d(sigma_i) scales with delta_i: |g32 - g64| <= 1e-5 * delta_i
SUM_SLACK = 1e-6  # sum of weights along a ray <= 1 + SUM_SLACK
PROB_ATOL = 1e-6  # gate probabilities (float32 softmax, also under autocast) vs float64
AUX_RTOL = 1e-5  # auxiliary loss vs float64
INTERP_ATOL = 1e-5  # trilinear interpolation vs float64
AUTOCAST_COLOR_ATOL = {torch.bfloat16: 1e-2, torch.float16: 2e-3}  # colour MLP in reduced precision
AUTOCAST_DEPTH_ATOL = 1e-4  # density pass and compositing stay float32 under autocast
AUTOCAST_DTYPES = [torch.bfloat16, torch.float16]

BOX = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 3.0]])


def reference_weights(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Textbook product form in float64: w_i = prod_{j<i} (1 - alpha_j) * alpha_i."""
    alpha = 1.0 - torch.exp(-sigma.double() * delta.double())
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]], dim=1), dim=1)
    return trans * alpha


@st.composite
def ray_batches(draw, max_rays=6, max_samples=48):
    """Densities 0..1e10 (a fifth exactly 0), steps 1e-8..1e3 (varying along a ray), 0..6 rays."""
    r = draw(st.integers(0, max_rays))
    s = draw(st.integers(1, max_samples))
    seed = draw(st.integers(0, 2**31 - 1))
    log_step_lo = draw(st.floats(-8, 3))
    log_step_span = draw(st.floats(0, 3))
    g = torch.Generator().manual_seed(seed)
    sigma = 10.0 ** (torch.rand(r, s, generator=g, dtype=torch.float64) * 18 - 8)
    sigma[torch.rand(r, s, generator=g) < 0.2] = 0.0
    log_delta = (log_step_lo + torch.rand(r, s, generator=g, dtype=torch.float64) * log_step_span).clamp(max=3)
    rgb = torch.rand(r, s, 3, generator=g, dtype=torch.float64)
    up = torch.randn(r, 3, generator=g, dtype=torch.float64)
    return sigma, 10.0**log_delta, rgb, up


# --- volume rendering -------------------------------------------------------------------------
@settings(max_examples=150, deadline=None)
@given(ray_batches())
def test_volume_rendering_matches_float64_with_extreme_densities_and_steps(batch):
    sigma64, delta64, rgb64, up64 = batch
    sigma = sigma64.float().requires_grad_()
    rgb = rgb64.float().requires_grad_()
    delta = delta64.float()
    w, alpha, trans = render_weights(sigma, delta)
    color, depth, acc = composite(w, rgb, torch.cumsum(delta, -1), (1.0, 1.0, 1.0))
    (color * up64.float()).sum().backward()
    for x in (w, alpha, trans, color, depth, acc, sigma.grad, rgb.grad):
        assert torch.isfinite(x).all()
    assert (w >= 0).all() and (w.sum(-1) <= 1 + SUM_SLACK).all() and (acc <= 1 + SUM_SLACK).all()

    s64 = sigma64.clone().requires_grad_()
    w64 = reference_weights(s64, delta64)
    c64 = (w64[..., None] * rgb64).sum(1) + (1 - w64.sum(1))[:, None]
    (c64 * up64).sum().backward()
    assert torch.allclose(w.double(), w64.detach(), atol=W_ATOL, rtol=0)
    assert torch.allclose(color.double(), c64.detach(), atol=COLOR_ATOL, rtol=0)
    assert torch.allclose(acc.double(), w64.detach().sum(1), atol=COLOR_ATOL, rtol=0)
    assert ((sigma.grad.double() - s64.grad).abs() <= GRAD_ATOL_PER_STEP * delta64 + 1e-12).all()


@settings(max_examples=40, deadline=None)
@given(ray_batches(), st.sampled_from(AUTOCAST_DTYPES))
def test_volume_rendering_is_unchanged_under_autocast(batch, dtype):
    """cumsum/exp/expm1 are not downcast by autocast and `accumulate` turns it off: float32 results."""
    sigma64, delta64, rgb64, _ = batch
    sigma, delta, rgb = sigma64.float(), delta64.float(), rgb64.float()
    w32, _, _ = render_weights(sigma, delta)
    c32, d32, a32 = composite(w32, rgb, torch.cumsum(delta, -1), (1.0, 1.0, 1.0))
    with torch.autocast("cpu", dtype=dtype):
        w, _, _ = render_weights(sigma, delta)
        c, d, a = composite(w, rgb, torch.cumsum(delta, -1), (1.0, 1.0, 1.0))
    assert c.dtype == torch.float32 and w.dtype == torch.float32
    assert torch.equal(w, w32) and torch.allclose(c, c32, atol=1e-7) and torch.allclose(a, a32, atol=1e-7)
    assert torch.allclose(d, d32, rtol=1e-6, atol=0)


def _expert() -> DVGOExpert:
    torch.manual_seed(0)
    model = DVGOExpert(DVGOConfig(res=10, hidden=16, layers=1), BOX)
    with torch.no_grad():
        model.density_table.normal_(0, 3)
        model.feature_table.normal_()
    return model


def _rays(n: int, seed: int, towards_box: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([[0.0, 0.0, -4.0]]).repeat(n, 1) + 0.3 * torch.randn(n, 3, generator=g)
    aim = torch.tensor([0.0, 0.0, 1.0]) if towards_box else torch.tensor([0.0, 0.0, -1.0])
    d = torch.nn.functional.normalize(aim + 0.2 * torch.randn(n, 3, generator=g), dim=-1)
    return o, d


@settings(max_examples=12, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from(AUTOCAST_DTYPES), st.floats(-3, 0))
def test_render_rays_through_a_field_under_autocast(seed, dtype, log_step):
    """A user-enabled autocast: the colour MLP runs in bfloat16/float16, the rest stays float32."""
    model = _expert()
    o, d = _rays(24, seed)
    step = 10.0**log_step
    settings64 = RenderSettings(step=step, near=0.1, far=12.0, bbox=BOX.double(), color_threshold=0.0)
    ref = render_rays(copy.deepcopy(model).double(), o.double(), d.double(), settings64)
    with torch.autocast("cpu", dtype=dtype):
        out = render_rays(model, o, d, RenderSettings(step=step, near=0.1, far=12.0, bbox=BOX, color_threshold=0.0))
    (out.color.sum() + out.depth.sum()).backward()
    assert out.color.dtype == torch.float32
    for x in (out.color, out.depth, out.acc, *(p.grad for p in model.parameters())):
        assert torch.isfinite(x).all()
    assert torch.allclose(out.color.double(), ref.color.detach(), atol=AUTOCAST_COLOR_ATOL[dtype], rtol=0)
    assert torch.allclose(out.acc.double(), ref.acc.detach(), atol=AUTOCAST_DEPTH_ATOL, rtol=0)
    assert torch.allclose(out.depth.double(), ref.depth.detach(), atol=AUTOCAST_DEPTH_ATOL * 12, rtol=0)


def test_empty_batches_and_rays_that_miss_the_box():
    model = _expert()
    settings_ = RenderSettings(step=0.05, near=0.1, far=12.0, bbox=BOX, background=(0.2, 0.3, 0.4))
    empty = render_rays(model, torch.zeros(0, 3), torch.zeros(0, 3), settings_)
    assert empty.color.shape == (0, 3) and empty.depth.shape == (0,) and empty.n_samples == 0
    o, d = _rays(16, 0, towards_box=False)  # pointing away from the box
    out = render_rays(model, o, d, settings_, jitter=True)
    assert out.n_samples == 0
    assert torch.equal(out.color, torch.tensor([[0.2, 0.3, 0.4]]).expand(16, 3))
    assert (out.acc == 0).all() and (out.depth == 0).all()
    # no sample, so nothing to learn: the colour is the constant background, cut off from the parameters
    # (train.batch_gradients then skips the step as not learnable)
    assert not out.color.requires_grad
    # one ray through the box among them: its colour learns, the missed rays keep the exact background
    o_hit, d_hit = torch.tensor([[0.0, 0.0, -4.0]]), torch.tensor([[0.0, 0.0, 1.0]])  # through the box centre
    mixed = render_rays(model, torch.cat([o_hit, o]), torch.cat([d_hit, d]), settings_, jitter=True)
    assert mixed.n_samples > 0 and mixed.color.requires_grad
    assert torch.equal(mixed.color[1:].detach(), torch.tensor([[0.2, 0.3, 0.4]]).expand(16, 3))
    mixed.color.sum().backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads) and any(g.abs().max() > 0 for g in grads)
    # parallel to a slab, outside it: no NaN from 0 * inf in the slab test
    par = render_rays(model, torch.tensor([[5.0, 0.0, 1.0]]), torch.tensor([[0.0, 1.0, 0.0]]), settings_)
    assert torch.isfinite(par.color).all() and par.n_samples == 0
    with torch.autocast("cpu", dtype=torch.bfloat16):
        empty = render_rays(model, torch.zeros(0, 3), torch.zeros(0, 3), settings_)
    assert empty.color.shape == (0, 3)


def test_zero_and_huge_density_limits_exactly():
    sigma = torch.tensor([[0.0, 0.0, 0.0], [1e10, 1e10, 1e10], [0.0, 1e10, 5.0]])
    delta = torch.full_like(sigma, 1e3)
    w, _, _ = render_weights(sigma, delta)
    assert torch.equal(w[0], torch.zeros(3))  # empty ray: no weight, pure background
    assert torch.equal(w[1], torch.tensor([1.0, 0.0, 0.0]))  # opaque at the first sample
    assert torch.equal(w[2], torch.tensor([0.0, 1.0, 0.0]))


# --- gate softmax, top-k and the auxiliary loss -----------------------------------------------
finite_logit = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)


def reference_aux(probs64: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> float:
    """L = M / N^2 * sum_i c_i m_i w_i, counted with plain Python loops in float64."""
    n, m = probs64.shape
    if n == 0:
        return 0.0
    counts = [0] * m
    for row in idx.tolist():
        for e in row:
            counts[e] += 1
    mass = probs64.sum(0).tolist()
    return m / n**2 * sum(counts[i] * mass[i] * float(w[i]) for i in range(m))


@settings(max_examples=120, deadline=None)
@given(st.integers(1, 6).flatmap(lambda m: st.tuples(
    st.just(m), st.lists(st.lists(finite_logit, min_size=m, max_size=m), min_size=0, max_size=20),
    st.integers(1, m), st.booleans(), st.sampled_from(["geometric", "linear", "quadratic", "none"]))))
def test_softmax_topk_and_aux_loss_with_extreme_logits(case):
    m, rows, k, renorm, penalty = case
    logits = torch.tensor(rows, dtype=torch.float32).reshape(len(rows), m).requires_grad_()
    probs = torch.softmax(logits, -1)
    vals, idx = top_k(probs, k, renorm)
    w = penalty_weights(m, penalty)
    aux = aux_loss(probs, idx, w)
    (vals.sum() + aux).backward()
    for x in (probs, vals, aux, logits.grad):
        assert torch.isfinite(x).all()
    probs64 = torch.softmax(logits.detach().double(), -1)
    assert torch.allclose(probs.double(), probs64, atol=PROB_ATOL, rtol=0)
    assert torch.allclose(probs.sum(-1), torch.ones(len(rows)), atol=PROB_ATOL)
    # the chosen experts carry the k largest probabilities (ties may pick either)
    kth = probs64.topk(k, -1).values[:, -1:]
    assert (probs64.gather(1, idx) >= kth - PROB_ATOL).all()
    if renorm and len(rows):
        assert torch.allclose(vals.sum(-1), torch.ones(len(rows)), atol=PROB_ATOL)
    ref = reference_aux(probs64, idx, w.double())
    assert abs(float(aux.detach()) - ref) <= AUX_RTOL * max(1.0, abs(ref))
    assert 0 <= float(aux.detach()) <= m * float(w.max()) * k + 1e-4


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from(["grid", "linear", "switch"]), st.sampled_from(AUTOCAST_DTYPES),
       st.floats(0, 4))
def test_gate_under_autocast_with_logits_up_to_1e4(seed, kind, dtype, log_scale):
    """The gate's MLP may run in bfloat16/float16; its probabilities are a float32 softmax."""
    torch.manual_seed(seed)
    gate = Gate(GateConfig(gate_type=kind, gate_res=4, gate_hidden=16, gate_layers=1), 3, BOX)
    with torch.no_grad():  # scale the logits up to +-1e4
        gate.mlp[-1].weight.mul_(10.0**log_scale)
        gate.mlp[-1].bias.mul_(10.0**log_scale)
    xyz = BOX[0] + torch.rand(64, 3) * (BOX[1] - BOX[0]) * 1.4 - 0.2 * (BOX[1] - BOX[0])
    with torch.autocast("cpu", dtype=dtype):
        logits = gate.logits(xyz)
        probs = gate.probs(xyz)
        vals, idx = top_k(probs, 2, True)
        aux = aux_loss(probs, idx, penalty_weights(3, "geometric"))
    assume(bool(torch.isfinite(logits).all()))  # float16 saturates at 65504: documented, not a gate defect
    (vals.sum() + aux).backward()
    assert probs.dtype == torch.float32 and torch.isfinite(probs).all() and torch.isfinite(aux)
    assert torch.allclose(probs.double(), torch.softmax(logits.detach().double(), -1), atol=PROB_ATOL, rtol=0)
    assert all(torch.isfinite(p.grad).all() for p in gate.parameters() if p.grad is not None)


# --- grid interpolation at and beyond the box boundary ----------------------------------------
def reference_trilinear(table64: torch.Tensor, xyz64: torch.Tensor, bbox: torch.Tensor, shape) -> torch.Tensor:
    """Clamp to the box, then blend the 8 vertices around the point, in float64 with Python indexing."""
    out = []
    lo, hi = bbox[0].double(), bbox[1].double()
    for p in xyz64:
        q = torch.minimum(torch.maximum(p, lo), hi)
        u = (q - lo) / (hi - lo) * (torch.tensor(shape, dtype=torch.float64) - 1)
        i0 = [min(math.floor(float(u[a])), shape[a] - 2) for a in range(3)]
        f = [float(u[a]) - i0[a] for a in range(3)]
        v = torch.zeros(table64.shape[1], dtype=torch.float64)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    wt = (f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1]) * (f[2] if dz else 1 - f[2])
                    row = (i0[0] + dx) * shape[1] * shape[2] + (i0[1] + dy) * shape[2] + (i0[2] + dz)
                    v += wt * table64[row]
        out.append(v)
    return torch.stack(out) if out else table64.new_zeros(0, table64.shape[1])


coordinate = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False),
    st.sampled_from([-1.0, 1.0, -2.0, 2.0, 0.0, 3.0, float("inf"), float("-inf"), 1e30, -1e30]),  # faces, beyond
    st.floats(-3.0, 4.0),
)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=0, max_size=25), st.booleans())
def test_grid_interpolation_at_and_beyond_the_box(points, under_autocast):
    shape = (5, 6, 7)
    g = torch.Generator().manual_seed(len(points))
    table = torch.randn(5 * 6 * 7, 4, generator=g).requires_grad_()
    xyz = torch.tensor(points, dtype=torch.float32).reshape(-1, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=under_autocast):
        idx, w = G.corners(xyz, BOX, shape)
        out = G.lookup(table, idx, w)
    assert (idx >= 0).all() and (idx < table.shape[0]).all()
    assert torch.allclose(w.sum(-1), torch.ones(len(points)), atol=1e-5) and (w >= -1e-6).all()
    if len(points):
        out.sum().backward()
        assert torch.isfinite(table.grad).all()
        assert torch.allclose(table.grad.sum(0), torch.full((4,), float(len(points))), atol=1e-3)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    ref = reference_trilinear(table.detach().double(), xyz.double(), BOX, shape)
    assert torch.allclose(out.detach().double(), ref, atol=INTERP_ATOL, rtol=0)


def test_interpolation_hits_vertex_values_exactly_at_box_corners():
    shape = (3, 4, 5)
    table = torch.randn(3 * 4 * 5, 2)
    corners_xyz = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-2.0, 2.0) for z in (0.0, 3.0)])
    idx, w = G.corners(corners_xyz, BOX, shape)
    out = G.lookup(table, idx, w)
    rows = [(2 if i else 0) * 20 + (3 if j else 0) * 5 + (4 if k else 0)
            for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    assert torch.allclose(out, table[rows], atol=1e-6)


# --- hash indexing at extreme coordinates ------------------------------------------------------
# The hash-grid expert is developed on another branch. When it is merged, add here a property test
# of its hash indexing over `coordinate` points (the strategy above: box faces, +-1e6, +-1e30, +-inf)
# at every level: indices inside the table, finite outputs and table gradients, and equality with a
# float64 / integer reference of the spatial hash, also under autocast (AUTOCAST_DTYPES).
