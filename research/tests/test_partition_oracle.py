"""research/partition_oracle.py (docs/results.md, "Why does Top-1 stay below its baseline at 100 px?"): a partition
of single models, rendered as it claims to be, and its choice of model per cell."""

from __future__ import annotations

import json
import subprocess

import pytest
import torch
from conftest import run_script  # the product suite's (research/tests/conftest.py puts tests/ on the path)

from boostnerf_cli.models import load_model
from boostnerf_cli.scenes import load_scene
from boostnerf_cli.workspace import Workspace
from research import partition_oracle as oracle


def run_oracle(*args: str) -> subprocess.CompletedProcess:
    """`python research/partition_oracle.py ARGS`, as a user runs it."""
    return run_script(oracle.__file__, *args)


def test_cells_index_the_lattice_and_clamp_the_box_edges():
    bbox = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 4.0]])
    xyz = torch.tensor([[0.0, 0.0, 0.0], [0.99, 1.99, 3.99], [1.0, 2.0, 4.0], [0.5, 0.0, 0.0], [0.0, 0.0, 2.0]])
    assert oracle.cells(xyz, bbox, 2).tolist() == [0, 7, 7, 4, 1]


def test_each_cell_goes_to_its_lowest_error_model_and_unseen_cells_to_the_default():
    inf = float("inf")
    err = torch.tensor([[0.1, 0.5, inf], [0.2, 0.4, inf], [0.3, 0.6, inf]], dtype=torch.float64)
    assert oracle.choose(err, default=2).tolist() == [0, 1, 2]


def test_a_models_share_is_the_rendering_weight_its_cells_hold_not_their_count(trained_ws, tiny_scene):
    """The table's last column is the rendering weight each model's cells hold, not the count of cells seen."""
    assert oracle.shares(torch.tensor([0, 1, 1]), torch.tensor([3.0, 1.0, 0.0], dtype=torch.float64), 2) == [0.75, 0.25]
    ws = Workspace(trained_ws)
    models = [load_model(ws, name, "cpu") for name in ws.expert_names()]
    scene = load_scene(tiny_scene)
    settings = scene.render_settings(min(m.step for m in models), models[0].bbox)
    test = scene.split("test")
    err, mass = oracle.splat(models, test, [0, 1], settings, models[0].bbox, [4])[4]
    total = 0.0
    for i in (0, 1):
        w = torch.stack([oracle.render(m.field, m.skip, test, i, settings)[1] for m in models]).mean(0)
        total += float(w[w > 1e-4].double().sum())
    assert abs(float(mass.sum()) - total) < 1e-6 * total
    assert torch.isfinite(err).all(0).tolist() == (mass > 0).tolist()


def test_a_partition_that_sends_every_cell_to_one_model_renders_that_model(trained_ws, tiny_scene):
    """The Routed field is only a fair partition if a one-model route is the model itself: same samples, same
    empty-space filter, same colours (bit for bit)."""
    ws = Workspace(trained_ws)
    models = [load_model(ws, name, "cpu") for name in ws.expert_names()]
    scene = load_scene(tiny_scene)
    bbox = models[0].bbox
    settings = scene.render_settings(min(m.step for m in models), bbox)
    test = scene.split("test")
    for e, m in enumerate(models):
        alone, _ = oracle.render(m.field, m.skip, test, 0, settings)
        routed = oracle.Routed(models, torch.full((4**3,), e, dtype=torch.long), bbox)
        mixed, _ = oracle.render(routed, routed.skip, test, 0, settings)
        assert torch.equal(alone, mixed)
    # and a split lattice renders something of each, and neither alone
    half = torch.tensor([(i // 16) % 2 for i in range(4**3)])
    routed = oracle.Routed(models, half, bbox)
    assert set(routed.which(torch.rand(500, 3) * (bbox[1] - bbox[0]) + bbox[0]).tolist()) == {0, 1}


def test_the_script_scores_every_choice_and_the_models_alone(trained_ws, tmp_path):
    out = tmp_path / "oracle.json"
    specs = [f"--model={name}={trained_ws}" for name in Workspace(trained_ws).expert_names()]
    proc = run_oracle(*specs, "--map-res", "4", "--train-views", "2", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert json.loads(proc.stdout) == result
    assert len(result["alone"]) == 2 and all(v["all"]["psnr"] > 10 for v in result["alone"].values())
    row = result["maps"]["4"]
    assert set(row) == {"training views", "the other held-out half", "the scored views (upper bound)",
                        "random, the held-out proportions"}
    for choice in row.values():
        assert abs(sum(choice["cells"]) - 1) < 1e-3 and choice["psnr"] > 10
    # the table docs/results.md prints (scripts/tables.py's generic table): each model alone, then each choice
    assert len(result["rows"]) == 2 + 4 and all(len(r) == len(result["columns"]) for r in result["rows"])
    assert result["rows"][1][4] == "+0.00"  # the largest model alone, against itself


def test_a_model_the_workspace_lacks_is_one_line(trained_ws):
    proc = run_oracle(f"--model=dvgo-99={trained_ws}", f"--model=dvgo-16={trained_ws}")
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [
        f"error: no model named 'dvgo-99' in {trained_ws} (models: dvgo-12, dvgo-16)"]


@pytest.mark.parametrize("args, says", [
    (["--map-res", "abc"], "argument --map-res: 'abc': give lattice sizes from 1 to 256"),
    (["--map-res", "0"], "argument --map-res: '0': give lattice sizes from 1 to 256"),
    (["--train-views", "0"], "argument --train-views: '0': give a whole number of at least 1"),
    (["--model", "dvgo-16"], "argument --model: 'dvgo-16': give NAME=WORKSPACE"),
])
def test_a_bad_value_is_one_line_not_a_traceback(trained_ws, args, says):
    proc = run_oracle(f"--model=dvgo-12={trained_ws}", f"--model=dvgo-16={trained_ws}", *args)
    assert proc.returncode == 2 and proc.stdout == "" and "Traceback" not in proc.stderr, proc.stderr
    assert says in proc.stderr.strip().splitlines()[-1]


def test_one_model_or_cuda_without_a_gpu_is_refused_in_one_line(trained_ws):
    proc = run_oracle(f"--model=dvgo-16={trained_ws}")
    assert proc.returncode == 2 and "give at least two --model" in proc.stderr and "Traceback" not in proc.stderr
    if not torch.cuda.is_available():
        proc = run_oracle(f"--model=dvgo-12={trained_ws}", f"--model=dvgo-16={trained_ws}", "--device", "cuda")
        assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert proc.stderr.strip().splitlines() == [
            "error: --device cuda was asked for but torch sees no CUDA GPU: use --device cpu or auto"]


def test_the_partition_routes_models_of_any_family(family_ws, tiny_scene):
    """The oracle treats models as black boxes, as the mixture does: a route that sends every cell to one TensoRF or
    Instant-NGP model renders exactly that model, and a split route renders both families in one image."""
    ws = Workspace(family_ws)
    models = [load_model(ws, name, "cpu") for name in ("tensorf-14", "ngp-3")]
    assert torch.allclose(models[0].bbox, models[1].bbox)
    scene = load_scene(tiny_scene)
    settings = scene.render_settings(min(m.step for m in models), models[0].bbox)
    test = scene.split("test")
    alone = [oracle.render(m.field, m.skip, test, 0, settings)[0] for m in models]
    for e in range(2):
        routed = oracle.Routed(models, torch.full((8,), e, dtype=torch.long), models[0].bbox)
        assert torch.equal(oracle.render(routed, routed.skip, test, 0, settings)[0], alone[e])
    half = oracle.Routed(models, torch.tensor([0, 0, 0, 0, 1, 1, 1, 1]), models[0].bbox)  # x below / above the middle
    mixed = oracle.render(half, half.skip, test, 0, settings)[0]
    assert not torch.equal(mixed, alone[0]) and not torch.equal(mixed, alone[1])
