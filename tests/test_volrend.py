"""Volume rendering against float64 references, with extreme densities and steps."""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from boostnerf_cli.render.volrend import composite, render_weights


def reference_weights(sigma, delta):
    """The textbook product form, in float64, one sample at a time."""
    out = torch.zeros_like(sigma, dtype=torch.float64)
    for r in range(sigma.shape[0]):
        trans = 1.0
        for i in range(sigma.shape[1]):
            alpha = 1.0 - math.exp(-float(sigma[r, i]) * float(delta[r, i]))
            out[r, i] = trans * alpha
            trans *= 1.0 - alpha
    return out


def test_weights_match_float64_reference():
    g = torch.Generator().manual_seed(0)
    sigma = torch.rand(7, 33, generator=g) * 20
    delta = torch.rand(7, 33, generator=g) * 0.05
    w, alpha, trans = render_weights(sigma, delta)
    ref = reference_weights(sigma.double(), delta.double())
    assert torch.allclose(w.double(), ref, atol=1e-5, rtol=0)
    assert torch.allclose(alpha.double(), 1 - torch.exp(-(sigma * delta).double()), atol=1e-6)
    assert torch.equal(trans[:, 0], torch.ones(7))


def test_hand_computed_two_samples():
    # sigma*delta = ln 2 for both: alpha = 1/2, weights 1/2 and 1/4, colour = 1/2 c0 + 1/4 c1 + 1/4 bg
    sigma = torch.tensor([[math.log(2.0), math.log(2.0)]], dtype=torch.float64)
    delta = torch.ones_like(sigma)
    w, _, _ = render_weights(sigma, delta)
    assert torch.allclose(w, torch.tensor([[0.5, 0.25]], dtype=torch.float64))
    rgb = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0]]], dtype=torch.float64)
    color, depth, acc = composite(w, rgb, torch.tensor([[1.0, 2.0]], dtype=torch.float64), (0.0, 0.0, 1.0))
    assert torch.allclose(color, torch.tensor([[0.5, 0.25, 0.25]], dtype=torch.float64))
    assert torch.allclose(depth, torch.tensor([1.0], dtype=torch.float64))
    assert torch.allclose(acc, torch.tensor([0.75], dtype=torch.float64))


def test_gradcheck_float64():
    sigma = (torch.rand(3, 6, dtype=torch.float64) * 5).requires_grad_()
    rgb = torch.rand(3, 6, 3, dtype=torch.float64, requires_grad=True)
    delta = torch.rand(3, 6, dtype=torch.float64) * 0.3 + 0.01
    t = torch.cumsum(delta, -1)

    def f(s, c):
        w, _, _ = render_weights(s, delta)
        return composite(w, c, t, (1.0, 1.0, 1.0))

    assert torch.autograd.gradcheck(f, (sigma, rgb))


@settings(max_examples=60, deadline=None)
@given(
    log_sigma=st.floats(min_value=-8, max_value=10),
    log_delta=st.floats(min_value=-8, max_value=3),
    n=st.integers(min_value=1, max_value=64),
)
def test_extreme_densities_and_steps_stay_finite(log_sigma, log_delta, n):
    sigma = torch.full((2, n), 10.0**log_sigma, requires_grad=True)
    delta = torch.full((2, n), 10.0**log_delta)
    rgb = torch.rand(2, n, 3, requires_grad=True)
    w, _, _ = render_weights(sigma, delta)
    color, depth, acc = composite(w, rgb, torch.cumsum(delta, -1), (1.0, 1.0, 1.0))
    (color.sum() + depth.sum()).backward()
    for x in (w, color, depth, acc, sigma.grad, rgb.grad):
        assert torch.isfinite(x).all()
    assert (w >= 0).all() and (acc <= 1 + 1e-6).all()
    ref = reference_weights(sigma.detach().double(), delta.double())
    assert torch.allclose(w.double(), ref, atol=1e-5, rtol=0)


def test_empty_batch_and_zero_density():
    w, _, _ = render_weights(torch.zeros(0, 5), torch.ones(0, 5))
    assert w.shape == (0, 5)
    w, _, _ = render_weights(torch.zeros(2, 4), torch.ones(2, 4))
    color, _, acc = composite(w, torch.rand(2, 4, 3), torch.ones(2, 4), (0.2, 0.3, 0.4))
    assert torch.allclose(color, torch.tensor([[0.2, 0.3, 0.4]] * 2)) and (acc == 0).all()


def test_compositing_is_counted_once_at_14_flops_per_slot():
    """docs/flops.md: compositing costs 14 flops per (ray, sample) slot. The colour's weighted sum is an einsum that
    FlopCounterMode counts, and the analytic 14 counted it again: 20 per slot (1.2% of a tiny expert's GFLOPs)."""
    from boostnerf_cli.flops import count_flops
    from boostnerf_cli.render.renderer import RenderSettings, render_rays

    class Flat(torch.nn.Module):  # no flops of its own: what is counted is the renderer's
        def density(self, x):
            return torch.full(x.shape[:1], 5.0)

        def color(self, x, d):
            return torch.full((x.shape[0], 3), 0.5)

    settings = RenderSettings(step=0.05, near=0.5, far=5.0, bbox=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    origins = torch.tensor([[0.0, 0.0, -3.0]]).repeat(10, 1)
    dirs = torch.nn.functional.normalize(torch.randn(10, 3, generator=torch.Generator().manual_seed(0)) * 0.1
                                         + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    with count_flops() as fc:
        bundle = render_rays(Flat(), origins, dirs, settings, None)
    r, s = bundle.extras["weights"].shape
    assert s > 1 and fc.total == 14 * r * s, (fc.matmul, fc.analytic, r, s)
