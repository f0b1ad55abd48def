"""`boostnerf prune`: packed tables round-trip, pruned models render the training views unchanged."""

import json
import shutil

import pytest
import torch
from conftest import assert_clean_failure, no_temp_files, run_cli

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.workspace import load_tensors, pack_rows, save_tensors, unpack_rows


@pytest.mark.parametrize("rows", [1, 7, 8, 9, 1000])
def test_pack_rows_round_trip(rows):
    g = torch.Generator().manual_seed(rows)
    table = torch.randn(rows, 3, generator=g)
    keep = torch.rand(rows, generator=g) > 0.4
    parts = pack_rows(table, keep)
    assert parts["mask"].dtype == torch.uint8 and parts["mask"].numel() == (rows + 7) // 8
    assert parts["values"].shape == (int(keep.sum()), 3)
    dense = unpack_rows(parts["values"], parts["mask"], rows, [-5.0, 0.0, 2.0])
    assert torch.equal(dense[keep], table[keep])
    assert torch.equal(dense[~keep], torch.tensor([-5.0, 0.0, 2.0]).expand(int((~keep).sum()), 3))


def test_packed_file_loads_dense_and_a_damaged_one_fails_clearly(tmp_path):
    table = torch.arange(20.0).reshape(10, 2)
    keep = torch.tensor([1, 0, 1, 1, 0, 0, 1, 0, 0, 1], dtype=torch.bool)
    parts = pack_rows(table, keep)
    meta = {"family": "x", "packed": {"t": {"rows": 10, "fill": [0.0, -1.0]}}}
    save_tensors(tmp_path / "a.safetensors", {"t@values": parts["values"], "t@mask": parts["mask"], "b": table}, meta)
    tensors, _ = load_tensors(tmp_path / "a.safetensors")
    assert set(tensors) == {"t", "b"}
    assert torch.equal(tensors["t"][keep], table[keep]) and (tensors["t"][~keep] == torch.tensor([0.0, -1.0])).all()
    save_tensors(tmp_path / "b.safetensors", {"t@values": parts["values"][:2], "t@mask": parts["mask"]}, meta)
    with pytest.raises(BoostNerfError, match="packed table"):
        load_tensors(tmp_path / "b.safetensors")


def test_baked_gate_is_the_gate_at_its_lattice_vertices():
    """prune carries the baked logits' gradient back through exactly this relation."""
    from boostnerf_cli.fields import grid as G
    from boostnerf_cli.moe.gate import Gate, GateConfig

    bbox = torch.tensor([[-1.0, -0.5, -1.0], [1.0, 1.0, 0.5]])
    gate = Gate(GateConfig(gate_type="grid", gate_res=6), 3, bbox)
    baked = gate.baked(5)
    with torch.no_grad():
        ref = gate.logits(G.lattice_points(baked.bbox, baked.shape))
    assert torch.allclose(baked.logit_table, ref, atol=1e-6)


@pytest.fixture(scope="module")
def pruned_ws(trained_ws, tmp_path_factory):
    ws = tmp_path_factory.mktemp("prune") / "ws"
    shutil.copytree(trained_ws, ws)
    run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--device", "cpu", check=True)
    run_cli("prune", "--workspace", str(ws), "--model", "top1", "--device", "cpu", check=True)
    return ws


def test_prune_writes_a_smaller_model_and_its_report(pruned_ws):
    report = json.loads((pruned_ws / "moe" / "top1-pruned.json").read_text())
    assert report["from"] == "top1" and report["split"] == "train" and report["views"] == 12
    assert report["params_after"] < report["params_before"]
    assert report["file_bytes_after"] < report["file_bytes_before"]
    assert report["file_bytes_after"] == (pruned_ws / "moe" / "top1-pruned.safetensors").stat().st_size
    names = {t["name"] for t in report["tables"]}
    assert {"experts.0.density_table", "experts.1.feature_table", "gate.table"} <= names
    assert report["train_max_abs_diff"] <= 1e-5
    assert abs(report["test_psnr_after"] - report["test_psnr_before"]) < 0.5
    assert no_temp_files(pruned_ws)


def test_pruned_model_matches_the_original_on_kept_rows_and_renders_the_train_views_alike(pruned_ws):
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.models import load_model
    from boostnerf_cli.render.renderer import render_view
    from boostnerf_cli.workspace import Workspace

    ws = Workspace(pruned_ws)
    dense, _ = load_tensors(ws.model_path("top1"))
    pruned, meta = load_tensors(ws.model_path("top1-pruned"))
    assert set(dense) == set(pruned)
    report = json.loads((pruned_ws / "moe" / "top1-pruned.json").read_text())
    for t in report["tables"]:
        a, b = dense[t["name"]], pruned[t["name"]]
        same = (a == b).all(dim=1)
        assert int(same.sum()) >= t["kept_rows"]  # kept rows are exact (a dropped row may equal its fill)
        dropped = ~same
        assert (b[dropped] == torch.tensor(t["fill"])).all()
    for k in dense:  # everything else (MLPs, occupancy, V_D) is stored as is
        if k not in meta["packed"]:
            assert torch.equal(dense[k], pruned[k]), k
    scene = Survey(ws).scene()
    train = scene.split("train")
    for exact in (False, True):  # baked gate (what render/eval use) and the exact gate
        b, a = load_model(ws, "top1", "cpu", exact), load_model(ws, "top1-pruned", "cpu", exact)
        assert a.params == report["params_after"] and b.params == report["params_before"]
        for i in range(0, len(train), 2):
            rb = render_view(b.field, train, i, b.settings(scene), b.skip)
            ra = render_view(a.field, train, i, a.settings(scene), a.skip)
            assert torch.allclose(ra["rgb"], rb["rgb"], atol=1e-5, rtol=0), (exact, i)


def test_pruned_model_evaluates_by_name_and_experts_prune_too(pruned_ws):
    run_cli("eval", "--workspace", str(pruned_ws), "--model", "top1", "--model", "top1-pruned", "--views", "1",
            "--no-costs", "--report", "--device", "cpu", check=True)
    before, after = json.loads((pruned_ws / "reports" / "eval.json").read_text())["models"]
    assert (before["name"], after["name"]) == ("top1", "top1-pruned")
    assert after["psnr"] == pytest.approx(before["psnr"], abs=1e-3)  # pruning drops unused rows only
    run_cli("prune", "--workspace", str(pruned_ws), "--model", "dvgo-16", "--device", "cpu", check=True)
    report = json.loads((pruned_ws / "moe" / "dvgo-16-pruned.json").read_text())
    assert report["kind"] == "expert" and report["train_max_abs_diff"] <= 1e-5
    assert {t["name"] for t in report["tables"]} == {"density_table", "feature_table"}


def test_prune_skips_finished_work_and_refuses_bad_input(pruned_ws, tmp_path):
    path = pruned_ws / "moe" / "top1-pruned.safetensors"
    before = path.stat().st_mtime_ns
    proc = run_cli("prune", "--workspace", str(pruned_ws), "--model", "top1", "--device", "cpu", check=True)
    assert "already pruned" in proc.stderr and path.stat().st_mtime_ns == before
    assert_clean_failure(run_cli("prune", "--workspace", str(pruned_ws), "--model", "top1-pruned", "--device", "cpu"),
                          "already pruned")
    assert_clean_failure(run_cli("prune", "--workspace", str(pruned_ws), "--model", "nope", "--device", "cpu"),
                          "no model named 'nope'")
    assert_clean_failure(run_cli("prune", "--workspace", str(tmp_path / "empty"), "--model", "top1"),
                          "boostnerf pretrain")


def test_a_model_finetuned_again_after_prune_is_not_silently_kept(pruned_ws, tmp_path):
    """top1 finetuned again with --force: prune said "already pruned, skipping", and top1-pruned (12.13 dB) was
    still the old top1's (12.20 dB). Now the pruned file records the digest it came from, as finetune does."""
    ws = tmp_path / "ws"
    shutil.copytree(pruned_ws, ws)
    run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--force", "--iters", "2", "--device", "cpu", check=True)
    proc = run_cli("prune", "--workspace", str(ws), "--model", "top1", "--device", "cpu")
    assert_clean_failure(proc, "top1-pruned is stale: top1 was changed after top1-pruned was pruned from it",
                         "--model top1 --force")
    run_cli("prune", "--workspace", str(ws), "--model", "top1", "--force", "--device", "cpu", check=True)
    proc = run_cli("prune", "--workspace", str(ws), "--model", "top1", "--device", "cpu", check=True)
    assert "already pruned" in proc.stderr


def test_a_prune_on_the_first_views_checks_those_views(pruned_ws, tmp_path):
    """`--views 2` keeps the rows the first 2 training views use, so those are the views the check renders: their
    difference is 0. It rendered 4 views and reported the rows the other 2 lost as a difference (3e-1 on fern)."""
    ws = tmp_path / "ws"
    shutil.copytree(pruned_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    run_cli("prune", "--workspace", str(ws), "--model", "top1", "--views", "2", "--force", "--device", "cpu",
            check=True)
    report = json.loads((ws / "moe" / "top1-pruned.json").read_text())
    assert report["views"] == 2 and report["train_check_views"] == 2 and report["train_max_abs_diff"] <= 1e-5


def test_count_params_of_a_pruned_mixture_counts_what_its_file_stores(pruned_ws):
    """A pruned mixture's row said params 56,373 (what the file stores) while its experts and gate said the dense
    94,310, and its ||w||_0 counted gradients in rows the file no longer stores (constants now): the parts add up
    to the model and ||w||_0 stays within what is stored."""
    run_cli("count-params", "--workspace", str(pruned_ws), "--model", "top1", "--model", "top1-pruned",
            "--device", "cpu", check=True)
    dense, pruned = json.loads((pruned_ws / "reports" / "count-params.json").read_text())["models"]
    tables = json.loads((pruned_ws / "moe" / "top1-pruned.json").read_text())["tables"]
    assert any(t["kept_rows"] < t["rows"] for t in tables)
    for row in (dense, pruned):
        parts = row["experts"] + [row["gate"]]
        assert sum(p["params"] for p in parts) == row["params"], row
        assert sum(p["w0"] for p in parts) == row["w0"] and all(p["w0"] <= p["params"] for p in parts), row
    assert pruned["params"] < dense["params"] and pruned["w0"] <= dense["w0"]
    assert [p["params"] for p in pruned["experts"]] < [p["params"] for p in dense["experts"]] or \
        pruned["gate"]["params"] < dense["gate"]["params"]


def test_a_prune_stopped_before_its_check_leaves_no_model_the_other_stages_take(pruned_ws, tmp_path):
    """prune writes the pruned model, then renders the training views before and after, then writes its report. Killed
    in between, it left a model never checked, which eval and render took like any other. Without its report a
    pruned model is refused in one line that says how to finish it, and prune (no --force needed) makes it again."""
    ws = tmp_path / "ws"
    shutil.copytree(pruned_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    (ws / "moe" / "top1-pruned.json").unlink()
    proc = run_cli("eval", "--workspace", str(ws), "--model", "top1-pruned", "--views", "1", "--no-costs", "--device",
                   "cpu")
    assert_clean_failure(proc, "top1-pruned", "prune did not finish", f"boostnerf prune -w {ws} --model top1`")
    run_cli("prune", "--workspace", str(ws), "--model", "top1", "--device", "cpu", check=True)
    assert (ws / "moe" / "top1-pruned.json").exists()
    run_cli("eval", "--workspace", str(ws), "--model", "top1-pruned", "--views", "1", "--no-costs", "--device", "cpu",
            check=True)


def test_prune_of_a_scene_that_holds_no_view_out(tmp_path):
    """With no test split (one view, holdout_every 0) prune on the train views failed on the
    report's held-out PSNR, after writing the pruned model: that file, without its report, read as a stale prune
    for good, and `prune` again failed the same way. The held-out PSNR is now null there, and a prune that fails
    after writing leaves nothing."""
    from conftest import make_recipe

    from boostnerf_cli.scenes import make_scene

    scene = make_scene(tmp_path / "scene", size=24, n_train=2, n_test=0, seed=0)
    recipe = make_recipe(tmp_path / "r.yaml", data={"image_size": 24, "holdout_every": 0},
                         pretrain={"res": [8], "iters": 10})
    ws = tmp_path / "ws"
    run_cli("pretrain", "--data", str(scene), "--recipe", str(recipe), "-w", str(ws), "--device", "cpu", check=True)
    run_cli("prune", "-w", str(ws), "--model", "dvgo-8", "--split", "train", "--device", "cpu", check=True)
    report = json.loads((ws / "moe" / "dvgo-8-pruned.json").read_text())
    assert report["test_views"] == 0 and report["test_psnr_before"] is None and report["train_max_abs_diff"] < 1e-5
    run_cli("eval", "-w", str(ws), "--split", "train", "--no-costs", "--device", "cpu", check=True)
