"""Workspace safety: atomic writes keep the previous artifact, one writer at a time, recipes strict."""

import errno
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.recipe import load_recipe
from boostnerf_cli.workspace import Workspace, atomic_path, load_tensors, save_tensors, write_json

ROOT = Path(__file__).parent.parent
RECIPES = sorted((ROOT / "recipes").glob("*.yaml"))
SHELL_SCRIPTS = sorted((ROOT / "recipes").glob("*.sh")) + sorted((ROOT / "scripts").glob("*.sh"))


def test_failed_write_keeps_the_previous_file(tmp_path):
    target = tmp_path / "r.json"
    write_json(target, {"v": 1})
    with pytest.raises(BoostNerfError, match=r"could not write .*r\.json \(No space left on device\); the previous"):
        with atomic_path(target) as tmp:
            tmp.write_text('{"v": 2')  # half written, then the disk "fills up"
            raise OSError(errno.ENOSPC, "No space left on device")
    assert json.loads(target.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_reports_are_strict_json_with_null_for_values_that_are_not_finite(tmp_path):
    """JSON has no inf or nan: write_json writes null for them, at any depth, and never Python's `Infinity`."""
    data = {"psnr": float("inf"), "rows": [{"a": float("-inf"), "b": (1.5, float("nan"))}], "n": 3, "s": "inf"}
    write_json(tmp_path / "r.json", data)
    text = (tmp_path / "r.json").read_text()
    assert json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} is not JSON")) == {
        "psnr": None, "rows": [{"a": None, "b": [1.5, None]}], "n": 3, "s": "inf"}
    assert data["psnr"] == float("inf")  # the caller's values are left as they were


def test_non_finite_tensors_are_never_written(tmp_path):
    with pytest.raises(BoostNerfError, match="non-finite"):
        save_tensors(tmp_path / "x.safetensors", {"a": torch.tensor([1.0, float("nan")])}, {})
    assert not list(tmp_path.iterdir())
    save_tensors(tmp_path / "x.safetensors", {"a": torch.ones(3)}, {"k": 1})
    tensors, meta = load_tensors(tmp_path / "x.safetensors")
    assert meta["k"] == 1 and torch.equal(tensors["a"], torch.ones(3))


def test_a_model_file_whose_bytes_changed_is_refused_as_damaged(tmp_path):
    """A file whose tensors' bytes changed after writing (a flipped bit, a partial overwrite) loads as before only if
    its digest still matches: else one line, not NaNs in every report (the digest was written but never checked)."""
    path = tmp_path / "m.safetensors"
    save_tensors(path, {"a": torch.arange(4096, dtype=torch.float32), "b": torch.ones(3, 2)}, {"kind": "test"})
    tensors, meta = load_tensors(path)
    assert torch.equal(tensors["a"], torch.arange(4096, dtype=torch.float32)) and meta["kind"] == "test"
    data = bytearray(path.read_bytes())
    data[-4000:-3936] = b"\xff" * 64  # inside the tensors, past the header
    path.write_bytes(bytes(data))
    with pytest.raises(BoostNerfError, match=r"is damaged: its tensors are not those written with it") as e:
        load_tensors(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_second_writer_is_refused_and_the_lock_is_released(tmp_path):
    ws = Workspace(tmp_path / "ws")
    with ws.lock():
        with pytest.raises(BoostNerfError, match="in use by another boostnerf process"):
            with ws.lock():
                pass
    assert not (tmp_path / "ws" / ".lock").exists()
    with ws.lock():
        pass


def test_a_refused_command_leaves_no_empty_workspace_behind(tmp_path):
    """A first command that fails before writing anything (a folder that is not a dataset) leaves no empty
    workspace folder (or the parents it made); a workspace that existed before is kept, even empty."""
    from conftest import assert_clean_failure, run_cli

    (tmp_path / "notdata").mkdir()
    new = tmp_path / "runs" / "scene" / "ws"
    assert_clean_failure(run_cli("pretrain", "--data", str(tmp_path / "notdata"), "--workspace", str(new)),
                         "cannot tell the dataset format")
    assert not (tmp_path / "runs").exists()
    (tmp_path / "kept").mkdir()
    assert_clean_failure(run_cli("pretrain", "--data", str(tmp_path / "notdata"), "--workspace",
                                 str(tmp_path / "kept")), "cannot tell the dataset format")
    assert (tmp_path / "kept").is_dir() and not list((tmp_path / "kept").iterdir())
    ws = Workspace(tmp_path / "made")
    with ws.lock():
        (ws.root / "experts").mkdir()  # an empty folder a stage made before it failed
    assert not ws.root.exists()
    with ws.lock():
        (ws.root / "manifest.json").write_text("{}")
    assert (ws.root / "manifest.json").exists()  # written: kept
    # a scene refused after it was read (all background) left the workspace holding only the scene's cache
    from boostnerf_cli.scenes import make_scene

    empty = make_scene(tmp_path / "empty", size=16, n_train=4, n_test=1, seed=0, content="empty")
    assert_clean_failure(run_cli("pretrain", "--data", str(empty), "--workspace", str(new)),
                         "nothing but the background")
    assert not (tmp_path / "runs").exists()
    (tmp_path / "afile").write_text("")  # a workspace that cannot be made: its own line, not the cache's
    assert_clean_failure(run_cli("pretrain", "--data", str(empty), "--workspace", str(tmp_path / "afile" / "ws")),
                         "cannot create workspace")


def test_a_killed_writer_s_temporary_scene_cache_is_found(tmp_path):
    """The scene cache is written through atomic_path like any artifact: a writer killed mid-write left
    `cache/.scene.safetensors.XXXXXXXX.tmp` (12 bytes a pixel and view) through every later command."""
    from boostnerf_cli.workspace import stale_temporaries

    (tmp_path / "cache").mkdir()
    left = tmp_path / "cache" / ".scene.safetensors._gt7dqzp.tmp"
    left.write_bytes(b"partial")
    (tmp_path / "cache" / "scene.safetensors").write_bytes(b"kept")
    assert stale_temporaries(tmp_path) == [left]


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / ".lock").write_text(f"{socket.gethostname()} {int(dead.stdout)}")
    with Workspace(tmp_path).lock():
        assert (tmp_path / ".lock").read_text() == f"{socket.gethostname()} {os.getpid()}"


@pytest.mark.parametrize("path", RECIPES, ids=[p.name for p in RECIPES])
def test_every_recipe_loads(path):
    from boostnerf_cli.fields.registry import CONFIGS

    rec = load_recipe(path)
    assert rec.pretrain.res and rec.pretrain.iters > 0
    CONFIGS[rec.pretrain.model](**{**rec.pretrain.family_config(), "res": rec.pretrain.res[0]})  # known keys only


@pytest.mark.parametrize("script", SHELL_SCRIPTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_shell_script_parses(script):
    proc = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_recipes_follow_the_naming_contract():
    names = {p.stem for p in RECIPES}
    families = ("dvgo", "tensorf", "ngp")
    assert {f"blender-{f}-{size}" for f in families for size in ("cpu", "paper")} <= names
    for n in names:  # DATASET-FAMILY-SIZE, optionally -VARIANT (blender-dvgo-cpu-official)
        parts = n.split("-")
        model, size = parts[1], parts[2]
        assert size in ("cpu", "paper") and model in families and len(parts) <= 4, n
        assert load_recipe(RECIPES[0].parent / f"{n}.yaml").pretrain.model == model


def test_recipe_type_errors_are_one_clear_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("pretrain:\n  iters: ten\n")
    with pytest.raises(BoostNerfError, match="pretrain.iters must be int"):
        load_recipe(bad)
    bad.write_text("pretrain: [1, 2\n")
    with pytest.raises(BoostNerfError, match="not valid YAML"):
        load_recipe(bad)


def test_family_options_may_be_given_per_expert():
    from boostnerf_cli.recipe import PretrainRecipe
    from boostnerf_cli.stages.pretrain import expert_options

    rec = PretrainRecipe(res=[96, 32, 64], dvgo={"hidden": {32: 16, 64: 32, 96: 64}, "feat_dim": 6})
    assert expert_options(rec, 32) == {"hidden": 16, "feat_dim": 6, "res": 32}
    assert expert_options(rec, 96)["hidden"] == 64
    assert expert_options(PretrainRecipe(res=[32], dvgo={"hidden": {"32": 8}}), 32)["hidden"] == 8  # from JSON
    # a resolution the mapping does not list: the nearest listed one's value (tests/test_training_checks.py)
    assert expert_options(PretrainRecipe(res=[32, 128], dvgo={"hidden": {32: 16, 64: 32}}), 128)["hidden"] == 32
