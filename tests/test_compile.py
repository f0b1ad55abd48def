"""What a compiled step (train.compile) traces as one graph: a graph break splits the step into pieces, each its own
launches, and a function the compiler cannot trace at all runs eagerly for good. Traced with `fullgraph=True` and
the compiler's `eager` backend (no code generated), so a break fails the test in a second on a CPU."""

from __future__ import annotations

import pytest
import torch

from boostnerf_cli.fields.hashgrid import HashEncoding
from boostnerf_cli.render.renderer import RenderSettings, sample_rays

BOX = torch.tensor([[-0.9, -1.4, -1.0], [1.0, 1.5, 1.3]])


@pytest.fixture(autouse=True)
def fresh_compiler():
    yield
    torch._dynamo.reset()


def whole(fn):
    return torch.compile(fn, backend="eager", fullgraph=True)


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


def test_sampling_compiles_whole_with_settings_made_outside_the_step():
    """The samples per ray and the step are worked out when the settings are made: worked out lazily in the step,
    a cached_property took a lock there (Python 3.11), which stopped the compiler."""
    settings = RenderSettings(step=0.05, near=0.1, far=6.0, bbox=BOX)
    origins = torch.tensor([0.0, 0.0, 4.0]).expand(8, 3)
    dirs = torch.nn.functional.normalize(torch.randn(8, 3, generator=torch.Generator().manual_seed(0)) * 0.1
                                         + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    t, valid, xyz, step = whole(sample_rays)(origins, dirs, settings, False)
    ref = sample_rays(origins, dirs, settings, False)
    assert step == ref[3] and torch.equal(valid, ref[1]) and torch.equal(t, ref[0]) and torch.equal(xyz, ref[2])
    assert settings.sampling[0] == t.shape[1] > 1
