"""fields/mlp.py: the one-node ReLU MLP gives nn.Sequential's outputs and gradients (float64)."""

import pytest
import torch
from torch import nn

from boostnerf_cli.fields.mlp import MLP


def _reference(mlp: MLP) -> nn.Sequential:
    """The same layers run by plain nn.Sequential (per-layer autograd)."""
    return nn.Sequential(*mlp)


@pytest.mark.parametrize("dims", [[8, 64, 64, 3], [39, 64, 64, 3], [12, 64, 16], [5, 3], [64, 8, 64, 4]])
@pytest.mark.parametrize("input_grad", [True, False])
def test_same_outputs_and_gradients_as_sequential(dims, input_grad):
    torch.manual_seed(0)
    mlp = MLP(dims).double()
    x = torch.randn(257, dims[0], dtype=torch.float64, requires_grad=input_grad)
    upstream = torch.randn(257, dims[-1], dtype=torch.float64)

    y = mlp(x)
    grads = torch.autograd.grad((y * upstream).sum(), [x] * input_grad + list(mlp.parameters()))
    y_ref = _reference(mlp)(x)
    ref = torch.autograd.grad((y_ref * upstream).sum(), [x] * input_grad + list(mlp.parameters()))

    assert y.grad_fn is not None and "ReluMLP" in type(y.grad_fn).__name__
    torch.testing.assert_close(y, y_ref, rtol=1e-12, atol=1e-12)
    for g, r in zip(grads, ref):
        assert g.shape == r.shape
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)
    for p, g in zip(mlp.parameters(), grads[input_grad:]):
        assert g.is_contiguous() and g.shape == p.shape  # what fused optimisers expect


def test_frozen_layers_get_no_gradient_and_the_rest_do():
    torch.manual_seed(1)
    mlp = MLP([6, 16, 2]).double()
    mlp[0].weight.requires_grad_(False)
    x = torch.randn(10, 6, dtype=torch.float64)
    mlp(x).sum().backward()
    assert mlp[0].weight.grad is None
    assert all(p.grad is not None for p in (mlp[0].bias, mlp[2].weight, mlp[2].bias))


def test_gradcheck_and_no_grad_path():
    torch.manual_seed(2)
    mlp = MLP([4, 7, 3]).double()
    x = torch.randn(9, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, *p: mlp(x), (x, *mlp.parameters()))
    with torch.no_grad():
        torch.testing.assert_close(mlp(x), _reference(mlp)(x))


def test_state_dict_names_are_sequentials():
    mlp = MLP([3, 8, 8, 2])
    assert list(mlp.state_dict()) == list(nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 8), nn.ReLU(),
                                                        nn.Linear(8, 2)).state_dict())
    with pytest.raises(ValueError):
        MLP([3])


def test_autocast_runs_each_layer_in_reduced_precision():
    mlp = MLP([8, 16, 3])
    x = torch.randn(5, 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = mlp(x)
    assert y.dtype == torch.bfloat16
    y.float().sum().backward()
    assert all(p.grad is not None for p in mlp.parameters())
