"""kill -9, rerun the same command: the result equals an uninterrupted run.

The real CLI runs in a process of its own (conftest.run_cli) and SIGKILLs itself at known points
(boostnerf_cli/faults.py, `BOOSTNERF_TEST_KILL`): right after its N-th training checkpoint, or inside the atomic write
of a named artifact (temporary file written, not yet renamed). Rerunning the same command resumes from the last
checkpoint; the final artifacts must match an uninterrupted run with the same seed within RESUME_ATOL
(docs/reliability.md), and the killed runs must leave no partial file, checkpoint or lock behind once the command has
completed.
"""

from __future__ import annotations

import json
import shutil
import signal
from pathlib import Path

import pytest
import torch
from conftest import assert_clean_failure, make_recipe, merge, run_cli

from boostnerf_cli.faults import ENV as TEST_KILL_ENV
from boostnerf_cli.workspace import FORMAT_VERSION, is_temporary, load_tensors

RESUME_ATOL = 1e-5  # documented in docs/reliability.md; observed difference: exactly 0

# the tiny recipe's changes: smaller experts and batches, a checkpoint every 4 steps to kill the run at
RECIPE_CHANGES = {
    "data": {"image_size": 24},
    "pretrain": {
        "res": [10, 14],
        "iters": 24,
        "geometry": {"res": 10, "iters": 24, "batch_rays": 128},
        # log_every 3: a logging interval spans each kill at a checkpoint (its psnr_mean must survive the resume)
        "train": {"batch_rays": 128, "log_every": 3, "checkpoint_every": 4, "occupancy_every": 8, "growth": [0.25]},
        "dvgo": {"hidden": 8},
    },
    "moe": {"gate_res": 6, "iters": 24, "train": {"batch_rays": 128, "log_every": 3, "checkpoint_every": 4}},
}

def run_killed(args: list[str], point: str) -> None:
    """Run the CLI until it SIGKILLs itself at `point` (faults.ENV: "checkpoint:N", "write:NAME")."""
    proc = run_cli(*args, env_extra={TEST_KILL_ENV: point})
    assert proc.returncode == -signal.SIGKILL, f"{point}: not killed ({proc.returncode}):\n{proc.stderr[-2000:]}"


def kill_at(args: list[str], points: list[str], ws: Path) -> None:
    """Kill the command at each point in turn (each on a rerun), then rerun it to the end."""
    for point in points:
        run_killed(args, point)
        if point.startswith("write:"):  # killed mid-write: the temporary file is there, the artifact is not
            name = point.split(":", 1)[1]
            assert list(ws.rglob(f".{name}.*.tmp")) and not list(ws.rglob(name)), point
    proc = run_cli(*args, check=True)
    assert "error" not in proc.stderr.lower(), proc.stderr[-2000:]
    assert "resuming from" in proc.stderr


def assert_same_tensors(a: Path, b: Path) -> None:
    ta, _ = load_tensors(a)
    tb, _ = load_tensors(b)
    assert sorted(ta) == sorted(tb), a.name
    for k in ta:
        if ta[k].is_floating_point():
            assert torch.allclose(ta[k], tb[k], atol=RESUME_ATOL, rtol=0), f"{a.name}: {k}"
        else:
            assert torch.equal(ta[k], tb[k]), f"{a.name}: {k}"


def _without_timing(report: dict) -> dict:
    out = {k: v for k, v in report.items() if k not in ("seconds", "startup_seconds")}  # wall times
    out["history"] = [{k: v for k, v in h.items() if k != "seconds"} for h in report.get("history", [])]
    return out


def assert_clean(ws: Path) -> None:
    """No temporary file, leftover training checkpoint or lock after the command completed."""
    leftovers = [p for p in ws.rglob("*") if is_temporary(p) or p.name == ".lock"]
    assert not leftovers, leftovers
    ckpts = ws / "checkpoints"
    assert not ckpts.exists() or not list(ckpts.iterdir())


@pytest.fixture(scope="module")
def setup(tmp_path_factory, tiny_scene):
    root = tmp_path_factory.mktemp("resume")
    recipe = make_recipe(root / "resume.yaml", **RECIPE_CHANGES)
    ref = root / "ref"
    args = ["pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "--workspace", str(ref), "--device", "cpu"]
    run_cli(*args, check=True)
    return root, recipe, ref, args


@pytest.mark.slow
def test_pretrain_killed_at_checkpoints_and_mid_write_resumes_to_the_uninterrupted_result(setup):
    root, _, ref, args = setup
    ws = root / "killed-pretrain"
    args = [a if a != str(ref) else str(ws) for a in args]
    # after the geometry stage's 2nd checkpoint (step 8/24); on the rerun, 4 more of its first round and 6 of its
    # second, then dvgo-10's first (step 4/24: before its first growth and refresh, its mask still the geometry's
    # grid over the geometry's box, which a resume stretched over the expert's box before 1e7832b); then 2 more
    # (step 12/24); then inside the write of dvgo-10's weights, after its last checkpoint
    kill_at(args, ["checkpoint:2", "checkpoint:11", "checkpoint:2", "write:dvgo-10.safetensors"], ws)
    for p in sorted((ref / "experts").glob("*.safetensors")):
        assert_same_tensors(p, ws / "experts" / p.name)
    for p in sorted((ref / "experts").glob("dvgo-*.json")):
        got, want = json.loads((ws / "experts" / p.name).read_text()), json.loads(p.read_text())
        assert _without_timing(got) == _without_timing(want), p.name
        assert got["skipped_steps"] == 0
    assert_clean(ws)


@pytest.mark.slow
@pytest.mark.parametrize("how", [["--topk", "2"]], ids=["top2"])
def test_finetune_killed_at_checkpoints_and_mid_write_resumes_to_the_uninterrupted_result(setup, how):
    root, _, ref, _ = setup
    run_cli("build-moe", "--workspace", str(ref), "--device", "cpu", check=True)
    ws = root / "killed-finetune"
    shutil.copytree(ref, ws)
    run_cli("finetune", "--workspace", str(ref), *how, "--device", "cpu", check=True)
    name = "top" + how[1]
    # after step 4/24; after step 16 (3 checkpoints on the rerun); inside the write of the finished mixture
    kill_at(["finetune", "--workspace", str(ws), *how, "--device", "cpu"],
            ["checkpoint:1", "checkpoint:3", f"write:{name}.safetensors"], ws)
    assert_same_tensors(ref / "moe" / f"{name}.safetensors", ws / "moe" / f"{name}.safetensors")
    got = json.loads((ws / "moe" / f"{name}.json").read_text())
    want = json.loads((ref / "moe" / f"{name}.json").read_text())
    assert _without_timing(got) == _without_timing(want)
    assert_clean(ws)


@pytest.mark.slow
def test_a_checkpoint_is_not_resumed_with_other_training_settings(setup, tmp_path):
    """A checkpoint resumes only with the settings that shape what is trained: a finetune killed at --lambda 0.5
    resumed at --lambda 0 (its report said 0 for a model half trained at 0.5), and a pretrain resumed with another
    pretrain.train.batch_rays, silently, before. log_every and checkpoint_every change nothing and may differ, and
    the learning rates may (a diverged run resumes from its last good checkpoint with lower ones)."""
    root, recipe, ref, args = setup
    ws = tmp_path / "ws"
    args = [a if a != str(ref) else str(ws) for a in args]
    run_killed(args, "checkpoint:14")  # inside dvgo-10 (step 8), after both geometry rounds (6 checkpoints each)
    changed = make_recipe(tmp_path / "changed.yaml",
                          **merge(RECIPE_CHANGES, {"pretrain": {"train": {"batch_rays": 96}}}))
    assert_clean_failure(run_cli(*[a if a != str(recipe) else str(changed) for a in args]),
                         "other settings", "batch_rays")
    quiet = make_recipe(tmp_path / "quiet.yaml",
                        **merge(RECIPE_CHANGES, {"pretrain": {"train": {"log_every": 5, "lr_grid": 0.05}}}))
    proc = run_cli(*[a if a != str(recipe) else str(quiet) for a in args], check=True)
    assert "resuming from" in proc.stderr
    # with the new rate (the checkpoint's optimiser state brought the old rates back, so a
    # diverged run resumed with lower ones, as its error advises, trained on exactly as before)
    grids, _ = load_tensors(ws / "experts" / "dvgo-10.safetensors")
    before, _ = load_tensors(ref / "experts" / "dvgo-10.safetensors")
    assert not torch.equal(grids["feature_table"], before["feature_table"])
    run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    finetune = ["finetune", "--workspace", str(ws), "--topk", "2", "--device", "cpu"]
    run_killed([*finetune, "--lambda", "0.5"], "checkpoint:1")
    assert_clean_failure(run_cli(*finetune, "--lambda", "0"), "other settings", "lam")
    run_cli(*finetune, "--lambda", "0.5", check=True)
    assert json.loads((ws / "moe" / "top2.json").read_text())["lambda"] == 0.5


def test_a_checkpoint_of_an_earlier_file_format_is_refused_in_one_line(setup, tmp_path):
    """A training checkpoint written by a boostnerf of another file format is not resumed with settings it may not
    have recorded: one line says to delete it, which restarts the model; the same command then finishes."""
    root, recipe, ref, args = setup
    ws = tmp_path / "ws"
    args = [a if a != str(ref) else str(ws) for a in args]
    run_killed(args, "checkpoint:14")  # inside dvgo-10 (step 8)
    ckpt = ws / "checkpoints" / "dvgo-10.pt"
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    assert state["format_version"] == FORMAT_VERSION
    state["format_version"] = "1"  # as an earlier boostnerf wrote it
    torch.save(state, ckpt)
    assert_clean_failure(run_cli(*args), f"training checkpoint {ckpt} has file format '1'",
                         f"reads format {FORMAT_VERSION!r}: delete it to restart this model")
    ckpt.unlink()
    proc = run_cli(*args, check=True)
    assert "resuming from" not in proc.stderr and "dvgo-10" in proc.stderr
    assert_clean(ws)


@pytest.mark.slow
def test_an_interrupted_pretrain_force_run_does_not_retrain_the_experts_it_finished(setup, tmp_path):
    """`pretrain --force` interrupted in its second expert, rerun as the interrupt line says (the same command): the
    first expert, already retrained by this run, was trained a third time. It is kept now, the second resumes, and
    once the run ends a new --force retrains everything again."""
    _, _, ref, args = setup
    ws = tmp_path / "ws"
    shutil.copytree(ref, ws)
    forced = [*(a if a != str(ref) else str(ws) for a in args), "--iters", "28", "--force"]
    run_killed(forced, "write:dvgo-14.pt")  # dvgo-10 retrained (28 steps), killed at dvgo-14's first checkpoint
    first = (ws / "experts" / "dvgo-10.safetensors").read_bytes()
    proc = run_cli(*forced, check=True)
    assert "dvgo-10: already retrained by this --force run, skipping" in proc.stderr, proc.stderr
    assert (ws / "experts" / "dvgo-10.safetensors").read_bytes() == first
    assert json.loads((ws / "experts" / "dvgo-14.json").read_text())["iterations"] == 28
    assert "forced" not in json.loads((ws / "manifest.json").read_text())  # the run is over
    proc = run_cli(*forced, check=True)  # a new --force run: both retrained
    assert "already retrained" not in proc.stderr and proc.stderr.count("steps in") == 2, proc.stderr
    assert_clean(ws)


def test_an_interrupted_force_run_resumes_and_force_drops_a_checkpoint_of_other_settings(setup, tmp_path):
    """`finetune --force` (and `pretrain --force`) deleted the model's training checkpoint
    before training, so an interrupted --force run restarted from step 0 on every rerun of the same command, though
    the interrupt line says "rerun the same command to go on". A checkpoint of the same settings is resumed now;
    --force drops one of other settings instead of refusing it."""
    root, _, ref, _ = setup
    ws = tmp_path / "ws"
    shutil.copytree(ref, ws)
    if not (ws / "moe" / "init.safetensors").exists():
        run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    finetune = ["finetune", "--workspace", str(ws), "--topk", "2", "--device", "cpu"]
    run_cli(*finetune, check=True)
    forced = [*finetune, "--lambda", "0.5", "--force"]
    run_killed(forced, "checkpoint:1")  # the forced run, killed after its first checkpoint (step 4/24)
    proc = run_cli(*forced, check=True)
    assert "resuming from" in proc.stderr and "at step 4/24" in proc.stderr
    assert json.loads((ws / "moe" / "top2.json").read_text())["lambda"] == 0.5
    run_killed(forced, "checkpoint:1")
    proc = run_cli(*finetune, "--lambda", "0", "--force", check=True)  # other settings: starts over, no refusal
    assert "resuming from" not in proc.stderr
    assert json.loads((ws / "moe" / "top2.json").read_text())["lambda"] == 0.0
    assert_clean(ws)
