"""kill -9 at random moments, rerun the same command: the result equals an uninterrupted run.

The real CLI runs in a subprocess and is SIGKILLed at seeded random points of its progress output
(plus a random delay, so some kills land inside checkpoint and artifact writes). Rerunning the same
command resumes from the last checkpoint; the final artifacts must match an uninterrupted run with
the same seed within RESUME_ATOL (docs/reliability.md), and the killed runs must leave no partial
file, checkpoint or lock behind once the command has completed.
"""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import run_cli

from boostnerf_cli.workspace import load_tensors

RESUME_ATOL = 1e-5  # documented in docs/reliability.md; observed difference: exactly 0

RECIPE = """
data: {image_size: 24, holdout_every: 8}
pretrain:
  model: dvgo
  res: [10, 14]
  iters: 24
  geometry: {res: 10, iters: 24, batch_rays: 128, alpha_init: 0.01}
  train: {batch_rays: 128, log_every: 1, checkpoint_every: 4, occupancy_every: 8, growth: [0.25]}
  dvgo: {hidden: 8, layers: 1}
moe:
  gate_res: 6
  iters: 24
  train: {batch_rays: 128, log_every: 1, checkpoint_every: 4}
"""

STEP_LINE = re.compile(r"^\[[\w.-]+\] step \d+/\d+")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "boostnerf_cli", *args]


def run_and_kill(args: list[str], after_lines: int, delay: float) -> int | None:
    """Start the CLI, SIGKILL it `delay` s after its `after_lines`-th progress line; -> its return code.

    A tiny step takes a few milliseconds on a quiet machine, so the delay stays short (tens of ms): enough to
    land some kills inside checkpoint and artifact writes, not so long that the run finishes first."""
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    proc = subprocess.Popen(_cli(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    seen = 0
    assert proc.stderr is not None
    for line in proc.stderr:
        if STEP_LINE.match(line):
            seen += 1
            if seen == after_lines:
                time.sleep(delay)
                proc.send_signal(signal.SIGKILL)
                break
    proc.stderr.close()
    return proc.wait(timeout=600)


def kill_repeatedly(args: list[str], seed: int, max_lines: int, kills: int = 3) -> int:
    """Kill the command at `kills` seeded random points (each on a rerun), then let it finish; -> kills landed."""
    rng = random.Random(seed)
    landed = 0
    for _ in range(kills):
        code = run_and_kill(args, after_lines=rng.randint(1, max_lines), delay=rng.uniform(0.0, 0.03))
        landed += code == -signal.SIGKILL
    proc = run_cli(*args, check=True)
    assert "error" not in proc.stderr.lower(), proc.stderr[-2000:]
    return landed


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
    out = {k: v for k, v in report.items() if k != "seconds"}
    out["history"] = [{k: v for k, v in h.items() if k != "seconds"} for h in report.get("history", [])]
    return out


def assert_clean(ws: Path) -> None:
    """No temporary file, leftover training checkpoint or lock after the command completed."""
    leftovers = [p for p in ws.rglob("*") if p.name.endswith(".tmp") or p.name == ".lock"]
    assert not leftovers, leftovers
    ckpts = ws / "checkpoints"
    assert not ckpts.exists() or not list(ckpts.iterdir())


@pytest.fixture(scope="module")
def setup(tmp_path_factory, tiny_scene):
    root = tmp_path_factory.mktemp("resume")
    recipe = root / "resume.yaml"
    recipe.write_text(RECIPE)
    ref = root / "ref"
    args = ["pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "--workspace", str(ref), "--device", "cpu"]
    run_cli(*args, check=True)
    return root, recipe, ref, args


def test_pretrain_killed_at_random_points_resumes_to_the_uninterrupted_result(setup):
    root, _, ref, args = setup
    ws = root / "killed-pretrain"
    args = [a if a != str(ref) else str(ws) for a in args]
    landed = kill_repeatedly(args, seed=14, max_lines=20)  # in geometry, dvgo-10, then later
    assert landed >= 2  # most seeded kill points land inside the run
    for p in sorted((ref / "experts").glob("*.safetensors")):
        assert_same_tensors(p, ws / "experts" / p.name)
    for p in sorted((ref / "experts").glob("dvgo-*.json")):
        got, want = json.loads((ws / "experts" / p.name).read_text()), json.loads(p.read_text())
        assert _without_timing(got) == _without_timing(want), p.name
        assert got["skipped_steps"] == 0
    assert_clean(ws)


@pytest.mark.parametrize("how", [["--topk", "2"]], ids=["top2"])
def test_finetune_killed_at_random_points_resumes_to_the_uninterrupted_result(setup, how):
    root, _, ref, _ = setup
    run_cli("build-moe", "--workspace", str(ref), "--device", "cpu", check=True)
    ws = root / "killed-finetune"
    shutil.copytree(ref, ws)
    run_cli("finetune", "--workspace", str(ref), *how, "--device", "cpu", check=True)
    name = "top" + how[1]
    landed = kill_repeatedly(["finetune", "--workspace", str(ws), *how, "--device", "cpu"], seed=11, max_lines=8)
    assert landed >= 2
    assert_same_tensors(ref / "moe" / f"{name}.safetensors", ws / "moe" / f"{name}.safetensors")
    got = json.loads((ws / "moe" / f"{name}.json").read_text())
    want = json.loads((ref / "moe" / f"{name}.json").read_text())
    assert _without_timing(got) == _without_timing(want)
    assert_clean(ws)
