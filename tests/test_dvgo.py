"""The DVGO-style expert: Field contract, gradients, growth, save/load round trip."""

import torch

from boostnerf_cli.fields.base import Field
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.fields.registry import build_expert, count_params
from boostnerf_cli.models import load_expert, save_expert
from boostnerf_cli.render.occupancy import OccupancyGrid

BOX = torch.tensor([[-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]])


def _expert(**kw):
    torch.manual_seed(0)
    m = DVGOExpert(DVGOConfig(res=10, hidden=16, layers=1, **kw), BOX)
    with torch.no_grad():
        m.density_table.normal_()
        m.feature_table.normal_()
    return m


def test_satisfies_the_field_contract_with_the_right_shapes():
    m = _expert()
    assert isinstance(m, Field)
    xyz = torch.rand(50, 3) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    sigma, rgb = m.query(xyz, dirs)
    assert sigma.shape == (50,) and rgb.shape == (50, 3)
    assert (sigma >= 0).all() and (rgb >= 0).all() and (rgb <= 1).all()
    assert torch.allclose(m.density(xyz), sigma) and torch.allclose(m.color(xyz, dirs), rgb)


def test_empty_outside_its_box_and_initial_alpha():
    m = DVGOExpert(DVGOConfig(res=10, alpha_init=1e-2), BOX)
    assert m.density(torch.tensor([[3.0, 0.0, 0.0]])).item() == 0.0
    sigma = m.density(torch.zeros(1, 3))
    alpha = 1 - torch.exp(-sigma * m.unit)
    assert torch.allclose(alpha, torch.tensor([1e-2]), rtol=1e-4)


def test_gradients_reach_every_parameter():
    m = _expert()
    xyz = torch.rand(400, 3) * torch.tensor([2.0, 2.0, 1.0]) - torch.tensor([1.0, 1.0, 0.5])
    dirs = torch.nn.functional.normalize(torch.randn(400, 3), dim=-1)
    sigma, rgb = m.query(xyz, dirs)
    (sigma.sum() + rgb.sum()).backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_regrid_keeps_the_field_and_the_density_unit():
    m = _expert()
    xyz = torch.rand(100, 3) * torch.tensor([1.6, 1.6, 0.8]) - torch.tensor([0.8, 0.8, 0.4])
    unit = m.unit
    before = m.density(xyz)
    m.regrid(12 ** 3 * 8)  # twice as fine: trilinear data is reproduced exactly only at old vertices,
    after = m.density(xyz)  # but a smooth field stays close
    assert m.unit == unit
    assert torch.corrcoef(torch.stack([before, after]))[0, 1] > 0.9


def test_init_density_reproduces_a_field():
    src = _expert()
    dst = DVGOExpert(DVGOConfig(res=10), BOX)
    dst.init_density(src.density)
    xyz = torch.rand(100, 3) * torch.tensor([2.0, 2.0, 1.0]) - torch.tensor([1.0, 1.0, 0.5])
    assert torch.allclose(dst.density(xyz), src.density(xyz), rtol=1e-3, atol=1e-3)


def test_save_load_round_trip_is_exact(tmp_path):
    m = _expert()
    occ = OccupancyGrid(torch.rand(4, 4, 4) > 0.5, BOX)
    save_expert(tmp_path / "e.safetensors", m, occ, {"step": 0.01})
    m2, occ2, meta = load_expert(tmp_path / "e.safetensors")
    sd, sd2 = m.state_dict(), m2.state_dict()
    assert sd.keys() == sd2.keys()  # a tensor missing from the file fails here, not silently skipped
    for k in sd:
        assert torch.equal(sd[k], sd2[k]), k
    assert torch.equal(occ.occupied, occ2.occupied) and meta["step"] == 0.01
    xyz = torch.rand(30, 3) - 0.5
    d = torch.nn.functional.normalize(torch.randn(30, 3), dim=-1)
    assert all(torch.equal(a, b) for a, b in zip(m.query(xyz, d), m2.query(xyz, d)))
    assert count_params(m2) == count_params(m)


def test_build_expert_rejects_unknown_settings():
    import pytest

    from boostnerf_cli.errors import BoostNerfError

    with pytest.raises(BoostNerfError, match="unknown dvgo setting"):
        build_expert("dvgo", {"res": 8, "width": 3}, BOX)
    with pytest.raises(BoostNerfError, match="unknown model family"):
        build_expert("nerf", {}, BOX)
