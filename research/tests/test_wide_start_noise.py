"""research/wide_start_noise.py: the wide start and noisy top-k gating patched into finetuning."""

import importlib.util
import sys
from pathlib import Path

import pytest
import torch
from conftest import run_script  # noqa: I001
from helpers import toy_mixture  # the product suite's (research/tests/conftest.py puts tests/ on the path)

from boostnerf_cli.moe.mixture import RoutingStats
from boostnerf_cli.recipe import MoERecipe, TrainRecipe

ROOT = Path(__file__).resolve().parents[2]


def _research():
    spec = importlib.util.spec_from_file_location("wide_start_noise", ROOT / "research" / "wide_start_noise.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks itself up there
    spec.loader.exec_module(module)
    return module


def _task(ws, mix, **switches):
    class Task(ws.SwitchedTask):
        pass

    Task.switches = ws.Switches(**switches)
    return Task(mix, None, TrainRecipe(), MoERecipe(iters=10))


def test_a_wide_start_routes_to_one_expert_more_then_narrows_by_step():
    """The first floor(fraction * iters) steps route to k + 1 experts with renormalised weights, then to k with the
    recipe's weights; the routing is a function of the step alone (a resumed run, which starts at a later step,
    routes as an uninterrupted one), the last step is always narrow, and the ensemble is left as it is."""
    ws = _research()
    mix = toy_mixture(m=3, k=1, renormalize=False)
    task = _task(ws, mix, wide_start=0.35)
    assert task.wide_steps == 3
    seen = []
    for step in (0, 2, 3, 9, 1, 5):  # out of order, as after a resume
        task.before_step(step)
        seen.append((mix.cfg.topk, mix.cfg.renormalize))
    assert seen == [(2, True), (2, True), (1, False), (1, False), (2, True), (1, False)]
    assert _task(ws, toy_mixture(3, k=1), wide_start=0.99).wide_steps == 9
    assert _task(ws, toy_mixture(3, k=3), wide_start=0.5).wide_steps == 0
    ens = toy_mixture(3, k=1)
    ens.make_ensemble()
    assert _task(ws, ens, wide_start=0.5).wide_steps == 0


def test_noisy_top_k_chooses_by_perturbed_log_probabilities_and_weights_by_the_clean_ones():
    """(float64 reference) the choice is the top-k of log p + noise * N(0, 1) drawn from torch's generator, the
    weights are the chosen experts' noiseless probabilities (renormalised over k for k > 1, the straight-through 1
    for k = 1), and gradients reach exactly the chosen probabilities."""
    ws = _research()
    probs = torch.softmax(torch.randn(64, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)), -1)
    for k, renorm in ((1, False), (1, True), (2, True), (2, False)):
        p = probs.clone().requires_grad_(True)
        torch.manual_seed(7)
        vals, idx = ws.noisy_top_k(p, k, renorm, 0.8)
        torch.manual_seed(7)
        ref_idx = torch.topk(probs.log() + 0.8 * torch.randn_like(probs), k, dim=-1).indices
        assert torch.equal(idx, ref_idx)
        chosen = probs.gather(-1, ref_idx)
        ref = chosen / chosen.sum(-1, keepdim=True) if renorm and k > 1 else chosen
        assert torch.allclose(vals, torch.ones_like(ref) if renorm and k == 1 else ref, rtol=0, atol=1e-15)
        (vals * torch.linspace(1, 2, k, dtype=vals.dtype)).sum().backward()
        assert torch.equal(p.grad.abs() > 1e-12, torch.zeros_like(probs, dtype=torch.bool).scatter(-1, ref_idx, True))
    top = probs.argmax(-1, keepdim=True)
    torch.manual_seed(0)
    moved = [float((ws.noisy_top_k(probs, 1, False, s)[1] != top).double().mean()) for s in (0.1, 1.0)]
    assert 0 < moved[0] < moved[1]
    many = probs[:1].expand(30000, 4)
    share = torch.bincount(ws.noisy_top_k(many, 1, False, 50.0)[1].reshape(-1), minlength=4) / 30000
    assert torch.allclose(share, torch.full((4,), 0.25, dtype=share.dtype), atol=0.02), share


def test_gate_noise_only_perturbs_the_training_steps_of_a_sparse_gate():
    """The noise reaches the task's training renders only (`noisy_routing` restores the plain choice after them);
    the ensemble or k = M, which choose every expert, get none."""
    ws = _research()
    mix = toy_mixture(m=3, k=1, renormalize=False)
    assert _task(ws, mix, gate_noise=1.0).gate_noise == 1.0
    assert _task(ws, toy_mixture(3, k=3), gate_noise=1.0).gate_noise == 0.0
    ens = toy_mixture(3, k=1)
    ens.make_ensemble()
    assert _task(ws, ens, gate_noise=1.0).gate_noise == 0.0
    xyz = torch.rand(2000, 3) * 2 - 1
    plain, noisy, after = RoutingStats(), RoutingStats(), RoutingStats()
    mix.with_stats(plain).density(xyz)
    torch.manual_seed(0)
    with ws.noisy_routing(1.0):
        mix.with_stats(noisy).density(xyz)
    mix.with_stats(after).density(xyz)
    assert torch.equal(plain.probs[0], noisy.probs[0])  # the same gate
    assert bool((plain.idx[0] != noisy.idx[0]).any()) and bool((plain.idx[0] == noisy.idx[0]).float().mean() > 0.3)
    assert torch.equal(plain.idx[0], after.idx[0])


@pytest.mark.parametrize("args, needle", [
    (["finetune", "--wide-start", "1.5"], "--wide-start = 1.5: must be in [0, 1)"),
    (["finetune", "--gate-noise=-1"], "--gate-noise = -1: must be in [0, 10)"),
    (["finetune", "--gate-noise", "x"], "--gate-noise needs a number, got 'x'"),
    (["eval"], "usage: python research/wide_start_noise.py finetune [--wide-start F] [--gate-noise S] [boostnerf "
               "finetune options]"),
])
def test_a_bad_switch_is_one_line(args, needle):
    proc = run_script(ROOT / "research" / "wide_start_noise.py", *args, timeout=120)
    assert proc.returncode != 0 and proc.stderr.strip() == f"error: {needle}", proc.stderr
