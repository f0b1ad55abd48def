"""What a compiled step (train.compile) traces as one graph: a graph break splits the step into pieces, each its own
launches, and a function the compiler cannot trace at all runs eagerly for good. Traced with the compiler's `eager`
backend (no code generated, seconds on a CPU); the compiler's own counter lists every break (`fullgraph=True` would
not do: it captures a tensor's `.item()` that a plain compile breaks at)."""

from __future__ import annotations

import pytest
import torch

from boostnerf_cli.fields.hashgrid import HashEncoding
from boostnerf_cli.render.renderer import RenderSettings, sample_rays

BOX = torch.tensor([[-0.9, -1.4, -1.0], [1.0, 1.5, 1.3]])


@pytest.fixture(autouse=True)
def fresh_compiler():
    from torch._dynamo.utils import counters

    torch._dynamo.reset()
    counters.clear()
    yield
    torch._dynamo.reset()


def whole(fn):
    """`fn` compiled as a training step is (without inductor's code generation); `breaks()` lists its breaks."""
    return torch.compile(fn, backend="eager")


def breaks() -> dict:
    from torch._dynamo.utils import counters

    assert counters["stats"]["unique_graphs"] > 0, "nothing was compiled"
    return dict(counters["graph_break"])


def test_the_hash_encoding_compiles_whole_and_gives_the_eager_rows_weights_and_features():
    """Eager, the corners are written into preallocated slots (`out=`), which the compiler cannot trace (7 breaks
    a call before); compiled, they are stacked: the same values."""
    enc = HashEncoding(BOX, levels=6, log2_table=11, features=3, base_res=4, max_res=64, init_std=1.0)
    assert any(enc.dense) and not all(enc.dense)  # dense and hashed levels both
    xyz = BOX[0] + torch.rand(60, 3, generator=torch.Generator().manual_seed(0)) * (BOX[1] - BOX[0])
    rows, w = enc.corners(xyz)
    compiled_rows, compiled_w = whole(enc.corners)(xyz)
    assert torch.equal(compiled_rows, rows) and torch.equal(compiled_w, w)
    assert torch.allclose(whole(enc)(xyz), enc(xyz), atol=1e-6, rtol=0)
    assert breaks() == {}


def test_sampling_compiles_whole_with_settings_made_outside_the_step():
    """The samples per ray and the step are worked out when the settings are made: worked out lazily in the step,
    a cached_property took a lock there (Python 3.11), which stopped the compiler."""
    settings = RenderSettings(step=0.05, near=0.1, far=6.0, bbox=BOX)
    origins = torch.tensor([0.0, 0.0, 4.0]).expand(8, 3)
    dirs = torch.nn.functional.normalize(torch.randn(8, 3, generator=torch.Generator().manual_seed(0)) * 0.1
                                         + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    # fullgraph: a function the compiler gives up on runs eagerly without a break on its counter
    t, valid, xyz, step = torch.compile(sample_rays, backend="eager", fullgraph=True)(origins, dirs, settings, False)
    ref = sample_rays(origins, dirs, settings, False)
    assert step == ref[3] and torch.equal(valid, ref[1]) and torch.equal(t, ref[0]) and torch.equal(xyz, ref[2])
    assert settings.sampling[0] == t.shape[1] > 1
    assert breaks() == {}


@pytest.mark.parametrize("kind", ["dvgo", "tensorf", "ngp", "top1", "top2", "ens"])
def test_a_compiled_training_step_traces_whole_after_its_first_step(monkeypatch, kind):
    """train.compile: on, on the CPU's static packing (a GPU's). The first step runs eagerly: it sizes the sample
    budgets, each with one wait for the device, which the compiler cannot trace. Every later step must trace as one
    graph: a mixture's step broke at each budget's first wait and at its empty-space filter, a new object made inside
    the step, and ran in 26 pieces."""
    from helpers import TOY_BOX, family_expert, routed_mixture, toward_box_rays

    from boostnerf_cli.recipe import MoERecipe, TrainRecipe
    from boostnerf_cli.render.occupancy import OccupancyGrid
    from boostnerf_cli.tasks import FieldTask, MixtureTask
    from boostnerf_cli.train import Schedule, train

    real = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: real(fn, backend="eager"))
    settings = RenderSettings(step=0.1, near=0.1, far=6.0, bbox=TOY_BOX, color_threshold=1e-4)
    tcfg = TrainRecipe(compile="on", occupancy_every=0)
    if kind in ("top1", "top2", "ens"):
        task = MixtureTask(routed_mixture(kind, "cpu"), settings, tcfg, MoERecipe(lam=0.01))
    else:
        occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
        occupied[2:6, 2:6, 2:6] = True
        task = FieldTask(family_expert(kind), settings, tcfg, skip=OccupancyGrid(occupied, TOY_BOX), base_mask=None)
    assert task.packer.static
    schedule = Schedule(4, batch_rays=64, log_every=1000, checkpoint_every=1000)
    train(task, toward_box_rays(), schedule, seed=0, title="t")
    assert breaks() == {}
