"""TensoRF-style and Instant-NGP-style experts (and the DVGO one, where the contract is shared):
Field/Expert contract, gradients, growth, warm start, safetensors round trip, the hash encoding
against a slow pure-Python reference, the VM lookup against grid_sample, and the family gates."""

import math

import pytest
import torch
import torch.nn.functional as F
from reference import reference_encoding

from boostnerf_cli import flops
from boostnerf_cli.fields.base import BareField, Expert, Field
from boostnerf_cli.fields.hashgrid import (
    PRIMES,
    HashEncoding,
    level_resolutions,
)
from boostnerf_cli.fields.registry import build_expert, count_params
from boostnerf_cli.fields.vm import LINE_AXIS, PLANE_AXES, VMGrid
from boostnerf_cli.models import load_expert, load_mixture, save_expert, save_mixture
from boostnerf_cli.moe.density_volume import DensityVolume
from boostnerf_cli.moe.gate import Gate, GateConfig
from boostnerf_cli.moe.mixture import Mixture, MixtureConfig
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.renderer import RenderSettings, render_rays

BOX = torch.tensor([[-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]])
SMALL = {
    "dvgo": {"res": 10, "hidden": 16, "layers": 1},
    "tensorf": {"res": 10, "density_rank": 3, "app_rank": 4, "app_dim": 6, "hidden": 16, "layers": 1,
                "fit_steps": 150},
    "ngp": {"res": 4, "log2_table": 9, "base_res": 4, "max_res": 24, "grid_res": 12, "hidden": 16,
            "color_hidden": 16, "color_layers": 1, "fit_steps": 150},
}
FAMILIES = list(SMALL)


def _expert(family: str, seed: int = 0):
    torch.manual_seed(seed)
    m = build_expert(family, SMALL[family], BOX)
    with torch.no_grad():  # away from the zero / tiny initialisation, so every output depends on every parameter
        for name, p in m.named_parameters():
            if "table" in name or "vm" in name:
                p.normal_(0, 0.5 if family != "ngp" else 1.0)
    return m


def _points(n: int, seed: int = 1, margin: float = 0.95):
    g = torch.Generator().manual_seed(seed)
    xyz = BOX[0] + (torch.rand(n, 3, generator=g) * margin + (1 - margin) / 2) * (BOX[1] - BOX[0])
    dirs = F.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return xyz, dirs


@pytest.mark.parametrize("family", FAMILIES)
def test_satisfies_the_field_and_expert_contracts(family):
    m = _expert(family)
    assert isinstance(m, Field) and isinstance(m, Expert) and m.family == family
    xyz, dirs = _points(64)
    sigma, rgb = m.query(xyz, dirs)
    assert sigma.shape == (64,) and rgb.shape == (64, 3)
    assert (sigma >= 0).all() and (rgb >= 0).all() and (rgb <= 1).all() and torch.isfinite(sigma).all()
    assert torch.allclose(m.density(xyz), sigma) and torch.allclose(m.color(xyz, dirs), rgb)
    assert m.density(torch.tensor([[3.0, 0.0, 0.0]])).item() == 0.0  # empty outside its box
    assert m.density(xyz[:0]).shape == (0,) and m.color(xyz[:0], dirs[:0]).shape == (0, 3)
    meta = m.config_dict()
    assert {"family", "config", "unit", "shape"} <= set(meta) and tuple(meta["shape"]) == tuple(m.shape)


def test_ngp_batch_view_encodes_each_sample_once_with_the_plain_fields_image_and_gradients(monkeypatch):
    m = _expert("ngp").double()
    with torch.no_grad():
        m.sigma_net[-1].bias[0] = 12.0  # dense enough that rays saturate: the colour pass skips some samples
    g = torch.Generator().manual_seed(2)
    origins = torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64).expand(24, 3).clone()
    dirs = F.normalize(torch.randn(24, 3, generator=g, dtype=torch.float64) * 0.3
                       + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), dim=-1)
    settings = RenderSettings(step=0.05, near=0.1, far=6.0, bbox=BOX.double(), color_threshold=1e-3)
    calls = []
    real = m.encoding.forward
    monkeypatch.setattr(m.encoding, "forward", lambda x: calls.append(x.shape[0]) or real(x))

    def render(field):
        m.zero_grad()
        b = render_rays(field, origins, dirs, settings)
        (b.color * torch.linspace(0.5, 1.5, 3, dtype=torch.float64)).sum().backward()
        assert 0 < b.n_color < b.n_samples  # the colour pass is a proper subset of the samples
        return b.color.detach(), [p.grad.clone() for p in m.parameters()]

    color_view, grads_view = render(m)
    assert len(calls) == 1  # the density pass alone ran the hash encoding
    color_plain, grads_plain = render(BareField(m))
    assert len(calls) == 3
    assert torch.allclose(color_view, color_plain, atol=1e-12)
    for a, b in zip(grads_view, grads_plain):
        assert torch.allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("family", FAMILIES)
def test_gradients_reach_every_parameter_and_param_groups_cover_them_once(family):
    m = _expert(family)
    xyz, dirs = _points(500)
    sigma, rgb = m.query(xyz, dirs)
    loss = (sigma * torch.linspace(-1, 1, 500)).sum() + (rgb * torch.randn(500, 3)).sum()
    reg = m.regularization()
    if reg is not None:
        loss = loss + reg
    loss.backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    grouped = [p for g in m.param_groups(0.1, 1e-3) for p in g["params"]]
    assert len(grouped) == len(list(m.parameters())) and {id(p) for p in grouped} == {id(p) for p in m.parameters()}


def test_tensorf_l1_regularisation_is_the_weighted_mean_absolute_density_component():
    m = _expert("tensorf")
    params = list(m.density_vm.parameters())
    expected = sum(float(p.detach().abs().sum()) for p in params) / sum(p.numel() for p in params)
    assert math.isclose(float(m.regularization().detach()), m.cfg.l1_weight * expected, rel_tol=1e-5)
    assert _expert("dvgo").regularization() is None and _expert("ngp").regularization() is None


@pytest.mark.parametrize("family", FAMILIES)
def test_save_load_round_trip_is_exact(family, tmp_path):
    m = _expert(family)
    if m.grows:
        m.regrid(8 ** 3)  # a grown (here: shrunk) lattice must round-trip too
    occ = OccupancyGrid(torch.rand(4, 4, 4) > 0.5, BOX)
    save_expert(tmp_path / "e.safetensors", m, occ, {"step": 0.01})
    m2, occ2, meta = load_expert(tmp_path / "e.safetensors")
    assert type(m2) is type(m) and tuple(m2.shape) == tuple(m.shape) and m2.unit == m.unit
    sd, sd2 = m.state_dict(), m2.state_dict()
    assert sd.keys() == sd2.keys() and all(torch.equal(sd[k], sd2[k]) for k in sd)
    assert torch.equal(occ.occupied, occ2.occupied) and meta["step"] == 0.01
    xyz, d = _points(40)
    m.eval()
    assert all(torch.equal(a, b) for a, b in zip(m.query(xyz, d), m2.query(xyz, d)))
    assert count_params(m2) == count_params(m)


def test_tensorf_growth_keeps_the_field_and_the_density_unit_and_resize_restores_a_checkpoint():
    m = _expert("tensorf")
    xyz, _ = _points(200)
    before, unit = m.raw_density(xyz), m.unit
    m.regrid(20 ** 3)
    assert m.unit == unit and m.shape == m.density_vm.shape == m.app_vm.shape
    # Bilinear / linear upsampling of planes and lines is exact at the old vertices; a random field
    # changes between them but stays strongly correlated.
    assert torch.corrcoef(torch.stack([before, m.raw_density(xyz)]))[0, 1] > 0.8
    fresh = build_expert("tensorf", SMALL["tensorf"], BOX)
    fresh.resize_to(m.shape)
    fresh.load_state_dict(m.state_dict())
    assert torch.equal(fresh.raw_density(xyz), m.raw_density(xyz))


def test_ngp_does_not_grow_and_refuses_another_lattice():
    from boostnerf_cli.errors import BoostNerfError

    m = _expert("ngp")
    assert not m.grows
    with pytest.raises(BoostNerfError, match="do not grow"):
        m.regrid(10)
    m.resize_to(m.shape)  # the same lattice is fine (checkpoint reload)
    with pytest.raises(BoostNerfError, match="fixed"):
        m.resize_to((3, 3, 3))


@pytest.mark.parametrize("family", ["tensorf", "ngp"])
def test_init_density_fits_the_coarse_geometry(family):
    """The warm start reproduces a prior density: a dense ball in an empty box."""
    from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert, raw_from_sigma

    prior = DVGOExpert(DVGOConfig(res=16, hidden=0), BOX)
    from boostnerf_cli.fields import grid as G

    pts = G.lattice_points(prior.bbox, prior.shape)
    sigma = torch.where(pts.norm(dim=-1) < 0.4, 200.0, 0.0)
    with torch.no_grad():
        prior.density_table.copy_(raw_from_sigma(sigma, prior.unit, prior.shift)[:, None])
    m = build_expert(family, {**SMALL[family], "fit_steps": 200}, BOX)
    m.init_density(prior.density)
    xyz, _ = _points(2000, seed=5)
    inside, outside = xyz.norm(dim=-1) < 0.3, xyz.norm(dim=-1) > 0.55
    alpha = -torch.expm1(-m.density(xyz).detach() * 0.5 * m.unit)
    assert alpha[inside].median() > 0.5 and alpha[outside].median() < 0.01
    assert all(p.grad is None for p in m.parameters())


# --- the hash encoding ------------------------------------------------------------------------
def test_level_resolutions_follow_the_growth_factor():
    res = level_resolutions(5, 16, 256)
    assert res[0] == 16 and res[-1] == 256
    b = math.exp(math.log(256 / 16) / 4)
    assert res == [math.floor(16 * b ** level + 1e-6) for level in range(5)]


def test_vectorised_hash_encoding_matches_the_slow_reference():
    box = torch.tensor([[-0.9, -1.4, -1.0], [1.0, 1.5, 1.3]], dtype=torch.float64)
    enc = HashEncoding(box, levels=6, log2_table=11, features=3, base_res=4, max_res=64, init_std=1.0).double()
    assert any(enc.dense) and not all(enc.dense)  # both indexing schemes are exercised
    g = torch.Generator().manual_seed(0)
    xyz = box[0] + torch.rand(60, 3, generator=g, dtype=torch.float64) * (box[1] - box[0])
    xyz = torch.cat([xyz, box, box[1:] + 0.25, box[:1] - 0.25, (box[0] + box[1])[None] / 2])  # corners, outside
    out = enc(xyz)
    table = enc.table.detach().tolist()
    for i in range(xyz.shape[0]):
        ref = reference_encoding(table, enc, xyz[i].tolist())
        assert torch.allclose(out[i], torch.tensor(ref, dtype=torch.float64), atol=1e-12, rtol=0), i


def test_hash_rows_match_the_uint32_scheme_without_overflow_at_huge_resolutions():
    """Coordinates near 2^22 times the 32-bit primes exceed 2^53: int64 must still give the rows of
    the usual uint32 implementation (Python integers, reduced mod 2^32 then mod 2^T)."""
    box = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    enc = HashEncoding(box, levels=2, log2_table=12, features=1, base_res=1 << 21, max_res=1 << 22, init_std=0.0)
    xyz = torch.tensor([[0.999999, 0.999, 0.5], [0.123456, 0.98765, 0.999999], [1.0, 1.0, 1.0]], dtype=torch.float64)
    rows, _ = enc.corners(xyz)
    assert rows.dtype == torch.int64
    for lv, n in enumerate(enc.resolutions):
        assert not enc.dense[lv]
        for i in range(xyz.shape[0]):
            base = [min(math.floor(min(float(xyz[i, a]) * n, n)), n - 1) for a in range(3)]
            for k in range(8):
                c = [base[0] + (k >> 2 & 1), base[1] + (k >> 1 & 1), base[2] + (k & 1)]
                h = ((c[0] * PRIMES[0]) ^ (c[1] * PRIMES[1]) ^ (c[2] * PRIMES[2])) % (1 << 32) % (1 << 12)
                assert int(rows[lv, i, k]) == enc.offsets[lv] + h
    assert int(rows.min()) >= 0 and int(rows.max()) < enc.table.shape[0]


def test_dense_levels_index_every_vertex_once():
    enc = HashEncoding(BOX, levels=2, log2_table=12, features=1, base_res=4, max_res=8)
    assert enc.dense == [True, True]
    for lv in range(2):
        v = enc.verts[lv]
        axes = [torch.arange(v[a], dtype=torch.float32) / enc.resolutions[lv] * enc.extent for a in range(3)]
        pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) + BOX[0]
        rows, w = enc.corners(pts)
        # each vertex is its own corner with weight 1 (up to rounding): collect the heaviest corner's row
        best = rows[lv].gather(1, w[lv].argmax(1, keepdim=True))[:, 0]
        assert best.unique().numel() == math.prod(v) == enc.sizes[lv]
        assert int(best.min()) == enc.offsets[lv] and int(best.max()) == enc.offsets[lv + 1] - 1


def test_hash_encoding_flops_are_counted():
    enc = HashEncoding(BOX, levels=4, log2_table=9, features=2, base_res=4, max_res=32)
    nd = sum(enc.dense)
    with flops.count_flops() as fc:
        enc(torch.zeros(10, 3))
    assert fc.analytic["hash"] == (flops.CORNER_FLOPS * 4 + (6 + 32) * (4 - nd)) * 10
    assert fc.analytic["interp"] == 16 * 2 * 4 * 10


# --- the VM grid --------------------------------------------------------------------------------
def test_vm_grid_matches_grid_sample_in_float64():
    torch.manual_seed(0)
    shape = (5, 7, 4)
    vm = VMGrid(shape, rank=3, init_std=1.0).double()
    box = BOX.double()
    xyz = box[0] + torch.rand(50, 3, dtype=torch.float64) * (box[1] - box[0])
    out = vm(xyz, box)
    u = (xyz - box[0]) / (box[1] - box[0]) * 2 - 1  # [-1, 1] per axis
    ref = []
    for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXIS)):
        plane = vm.planes[m].detach().T.reshape(1, 3, shape[a], shape[b])
        # grid_sample: grid[..., 0] indexes the last (width) dimension
        grid = torch.stack([u[:, b], u[:, a]], -1)[None, :, None, :]
        pv = F.grid_sample(plane, grid, mode="bilinear", align_corners=True)[0, :, :, 0].T
        line = vm.lines[m].detach().T.reshape(1, 3, shape[c], 1)
        lgrid = torch.stack([torch.zeros_like(u[:, c]), u[:, c]], -1)[None, :, None, :]
        lv = F.grid_sample(line, lgrid, mode="bilinear", align_corners=True)[0, :, :, 0].T
        ref.append(pv * lv)
    assert torch.allclose(out, torch.cat(ref, -1), atol=1e-12)


# --- gates and mixed-family mixtures ----------------------------------------------------------
@pytest.mark.parametrize("grid", ["dense", "tensorf", "hash"])
def test_gate_feature_grids(grid):
    torch.manual_seed(0)
    gate = Gate(GateConfig(gate_type="grid", gate_res=8, gate_grid=grid, levels=3, log2_table=8), 3, BOX)
    xyz, _ = _points(300)
    p = gate.probs(xyz)
    assert p.shape == (300, 3) and torch.allclose(p.sum(-1), torch.ones(300))
    assert p.argmax(-1).unique().numel() == 3  # spatially varied initial routing
    (p * torch.randn(300, 3)).sum().backward()
    params = gate.grid_parameters()
    assert params and all(q.grad is not None and q.grad.abs().sum() > 0 for q in params)


def test_a_mixture_of_experts_of_three_families_round_trips(tmp_path):
    experts = [_expert(f, seed=i) for i, f in enumerate(FAMILIES)]
    vd = DensityVolume(BOX, 8)
    vd.init_from(experts[0].density)
    gate = Gate(GateConfig(gate_type="grid", gate_res=8, gate_grid="hash", levels=3, log2_table=8), 3, BOX)
    mix = Mixture(experts, gate, vd, None, MixtureConfig(topk=2, vd_res=8, step=0.05, expert_names=FAMILIES))
    mix.eval()
    xyz, d = _points(100)
    sigma, rgb = mix.query(xyz, d)
    assert isinstance(mix, Field) and sigma.shape == (100,) and rgb.shape == (100, 3)
    groups = mix.param_groups(0.1, 1e-3, 1e-2, 1e-3)
    assert {id(p) for g in groups for p in g["params"]} == {id(p) for p in mix.parameters()}
    save_mixture(tmp_path / "m.safetensors", mix, {"name": "m"})
    mix2, _ = load_mixture(tmp_path / "m.safetensors")
    assert [type(e).family for e in mix2.experts] == FAMILIES and mix2.gate.cfg.gate_grid == "hash"
    s2, c2 = mix2.query(xyz, d)
    assert torch.equal(s2, sigma) and torch.equal(c2, rgb)


def test_gate_grid_auto_follows_the_family():
    from boostnerf_cli.stages.build_moe import resolve_gate_grid

    assert resolve_gate_grid("auto", ["dvgo", "dvgo"]) == "dense"
    assert resolve_gate_grid("auto", ["tensorf"] * 3) == "tensorf"
    assert resolve_gate_grid("auto", ["ngp"] * 3) == "hash"
    assert resolve_gate_grid("auto", ["ngp", "dvgo"]) == "dense"
    assert resolve_gate_grid("hash", ["dvgo"]) == "hash"


@pytest.mark.parametrize("family", ["dvgo", "tensorf", "ngp"])
def test_rendering_evaluates_a_field_in_cache_sized_blocks_to_the_same_values(family, monkeypatch):
    """Without gradients on the CPU an expert runs over blocks of `BLOCK_ROWS` samples (fields/base.py `blockwise`):
    the density and colour of one pass over every sample, to float32 rounding (a matrix product over fewer rows may
    sum in another order)."""
    from boostnerf_cli.fields import base

    expert = build_expert(family, SMALL[family], BOX)
    with torch.no_grad():
        for p in expert.parameters():
            p.normal_(0, 0.5)
    g = torch.Generator().manual_seed(0)
    xyz = BOX[0] + torch.rand(5000, 3, generator=g) * (BOX[1] - BOX[0])
    dirs = F.normalize(torch.randn(5000, 3, generator=g), dim=-1)
    monkeypatch.setattr(base, "BLOCK_ROWS", 1 << 30)
    with torch.no_grad():
        whole = expert.density(xyz), expert.color(xyz, dirs)
    monkeypatch.setattr(base, "BLOCK_ROWS", 1000)
    with torch.no_grad():
        blocks = expert.density(xyz), expert.color(xyz, dirs)
    for a, b in zip(whole, blocks):
        assert a.shape[0] == 5000 and torch.allclose(a, b, rtol=1e-5, atol=1e-6)
