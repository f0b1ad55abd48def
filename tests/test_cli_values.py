"""Issue 20 through the real CLI: bad recipe values and bad files end in one `error:` line, exit code 2."""

import json
import shutil

import pytest
import torch
from conftest import REMOVE, assert_clean_failure, make_recipe, run_cli

from boostnerf_cli.workspace import FORMAT_VERSION


def test_recipe_that_is_a_folder(tmp_path):
    (tmp_path / "recipes").mkdir()
    proc = run_cli("pretrain", "--workspace", str(tmp_path / "ws"), "--recipe", str(tmp_path / "recipes"))
    assert_clean_failure(proc, "recipes is a folder: pass a YAML file")


def test_recipe_that_is_binary(tmp_path):
    path = tmp_path / "r.yaml"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    proc = run_cli("pretrain", "--workspace", str(tmp_path / "ws"), "--recipe", str(path))
    assert_clean_failure(proc, "r.yaml is not a text file (not UTF-8)")


@pytest.mark.parametrize("alpha", [0, 1])
def test_alpha_init_zero_and_one(tmp_path, tiny_scene, alpha):
    recipe = make_recipe(tmp_path / "r.yaml", pretrain={"dvgo": {"alpha_init": alpha}})
    proc = run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "--workspace", str(tmp_path / "ws"),
                   "--device", "cpu")
    assert_clean_failure(proc, f"recipe key pretrain.dvgo.alpha_init = {float(alpha)}: must be in (0, 1)")
    assert not (tmp_path / "ws").exists()  # refused before anything was made


def test_log2_table_40(tmp_path, tiny_scene):
    recipe = make_recipe(tmp_path / "r.yaml", pretrain={"model": "ngp", "res": [2, 3], "dvgo": REMOVE,
                                                        "ngp": {"log2_table": 40}})
    proc = run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "--workspace",
                   str(tmp_path / "ws"), "--device", "cpu")
    assert_clean_failure(proc, "recipe key pretrain.ngp.log2_table = 40: must be in [1, 30]")


def test_flags_are_checked_like_recipe_values(tmp_path, trained_ws):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    proc = run_cli("build-moe", "--workspace", str(ws), "--threshold", "1.5", "--device", "cpu")
    assert_clean_failure(proc, "setting moe.density_threshold = 1.5: must be in [0, 1)")
    proc = run_cli("pretrain", "--workspace", str(ws), "--seed", "-3", "--device", "cpu")
    assert_clean_failure(proc, "setting pretrain.seed = -3: must be in [0, ")


def test_build_moe_topk_above_the_number_of_experts(tmp_path, trained_ws):
    """moe.topk above M was refused by build-moe (which has no --topk), though only the untrained mixture uses it."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    recipe = make_recipe(tmp_path / "top7.yaml", moe={"topk": 7})
    proc = run_cli("build-moe", "--workspace", str(ws), "--recipe", str(recipe), "--device", "cpu", check=True)
    # the untrained mixture's k only has to fit its experts (finetune --topk K sets each model's, and refuses K > M)
    assert "note: moe.topk = 7 but the mixture has 2 experts: moe/init routes to 2" in proc.stderr
    assert json.loads((ws / "moe" / "init.json").read_text())["experts"] == ["dvgo-12", "dvgo-16"]
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "3", "--device", "cpu")
    assert_clean_failure(proc, "--topk = 3 but the mixture has 2 experts")


def test_expert_file_with_the_wrong_structure(tmp_path, trained_ws):
    from boostnerf_cli.workspace import load_tensors, save_tensors

    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    path = ws / "experts" / "dvgo-12.safetensors"
    tensors, meta = load_tensors(path)
    del tensors["occupancy_bbox"]  # loads, digest and all, but lacks a tensor the loader needs
    meta.pop("digest"), meta.pop("format_version")
    save_tensors(path, tensors, meta)
    proc = run_cli("eval", "--workspace", str(ws), "--model", "dvgo-12", "--device", "cpu")
    assert_clean_failure(proc, "dvgo-12.safetensors does not hold a valid dvgo expert (KeyError: 'occupancy_bbox'")


def test_training_checkpoint_with_the_wrong_structure(tmp_path, trained_ws, tiny_scene, tiny_recipe):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    for suffix in (".safetensors", ".json"):
        (ws / "experts" / f"dvgo-16{suffix}").unlink()
    (ws / "checkpoints").mkdir(exist_ok=True)
    torch.save({"format_version": FORMAT_VERSION, "task": {"model": {}}, "step": 3},
               ws / "checkpoints" / "dvgo-16.pt")  # a dict of this file format, the wrong one
    proc = run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace", str(ws),
                   "--device", "cpu")
    assert_clean_failure(proc, "dvgo-16.pt does not hold this model's training state", "delete it")


def test_manifest_that_is_a_folder_and_a_lock_that_is_a_folder(tmp_path, trained_ws):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    (ws / ".lock").mkdir()
    proc = run_cli("eval", "--workspace", str(ws), "--report", "--device", "cpu")
    assert_clean_failure(proc, "cannot take the writer lock", ".lock (Is a directory)")
    proc = run_cli("eval", "--workspace", str(ws), "--device", "cpu")  # a reader (no --report)
    assert_clean_failure(proc, "cannot open the workspace lock", ".lock (Is a directory)", "remove it")
    (ws / ".lock").rmdir()
    (ws / "manifest.json").unlink()
    (ws / "manifest.json").mkdir()
    proc = run_cli("eval", "--workspace", str(ws), "--device", "cpu")
    assert_clean_failure(proc, "workspace manifest", "manifest.json is a folder")


@pytest.mark.parametrize("command", ["bench", "eval", "render", "count-params", "prune", "build-moe", "make-scene"])
def test_commands_that_run_as_one_process_are_refused_under_torchrun(tmp_path, command):
    """Under torchrun (WORLD_SIZE > 1) only pretrain and finetune run; any other command is refused in one line
    before it touches anything (bench ran: its ranks fought over the workspace lock and torchrun printed a
    ChildFailedError traceback)."""
    args = {"make-scene": [str(tmp_path / "scene")], "prune": ["-w", str(tmp_path / "ws"), "--model", "top1"],
            "bench": ["-w", str(tmp_path / "ws"), "--data", str(tmp_path / "none")]}
    proc = run_cli(command, *args.get(command, ["-w", str(tmp_path / "ws")]),
                   env_extra={"WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1"})
    assert_clean_failure(proc, "only pretrain and finetune run under torchrun")
    assert not list(tmp_path.iterdir())
