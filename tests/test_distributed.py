"""torchrun: experts shared out over ranks, data-parallel finetuning, failures (2 CPU processes, gloo on loopback).

Tolerances (docs/distributed.md): experts pretrained under torchrun are bitwise equal to one process's
(the same code with the same seed, whichever rank runs it); a data-parallel step's averaged gradient
equals the one-process gradient on the union of the shards within GRAD_RTOL of the largest gradient
entry (float32 sums in another order), and the logged loss within LOSS_RTOL.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import make_recipe, run_cli

from boostnerf_cli.workspace import is_temporary, load_tensors

GRAD_RTOL = 1e-5  # of max |gradient| of each parameter; observed: 1.8e-6 (top2), 9.4e-7 (baseline)
LOSS_RTOL = 1e-6  # logged loss, PSNR, aux, load; observed: 1e-7

# the tiny recipe's changes: three smaller experts (two ranks get work), smaller batches, frequent checkpoints
RECIPE_CHANGES = {
    "data": {"image_size": 24},
    "pretrain": {
        "res": [8, 10, 14],
        "iters": 16,
        "geometry": {"res": 10, "iters": 16, "batch_rays": 128},
        "train": {"batch_rays": 128, "log_every": 4, "checkpoint_every": 4, "occupancy_every": 8, "growth": [0.25]},
        "dvgo": {"hidden": 8},
    },
    "moe": {"gate_res": 6, "iters": 24, "train": {"batch_rays": 128, "log_every": 1, "checkpoint_every": 4}},
}
TESTS = Path(__file__).parent
LAM = 0.1  # the data-parallel step test's auxiliary-loss weight: strong, so that its gradient counts


def _env() -> dict:
    # one thread per rank on 2 cores; gloo on the loopback interface only
    return {**os.environ, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def torchrun(*args: str) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--nnodes=1", "--nproc_per_node=2",
            "--master_addr=127.0.0.1", f"--master_port={free_port()}", "-m", "boostnerf_cli", *args]


def run(cmd: list[str], check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return proc


def one_process(*args: str) -> subprocess.CompletedProcess:
    """`boostnerf ARGS` in one process (forked from the CLI server) with one thread, as each rank has."""
    return run_cli(*args, check=True, env_extra={"OMP_NUM_THREADS": "1"})


def files(ws: Path) -> dict[str, bytes]:
    return {str(p.relative_to(ws)): p.read_bytes() for p in sorted(ws.rglob("*")) if p.is_file()}


def assert_clean(ws: Path) -> None:
    assert not [p for p in ws.rglob("*") if is_temporary(p) or p.name == ".lock"]
    assert not list((ws / "checkpoints").glob("*"))


@pytest.fixture(scope="module")
def setup(tmp_path_factory, tiny_scene):
    """The recipe's experts trained by one process (`one`, then with moe/init) and by 2 ranks (`two`)."""
    root = tmp_path_factory.mktemp("dist")
    recipe = make_recipe(root / "dist.yaml", **RECIPE_CHANGES)
    args = ["pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "--device", "cpu"]
    one_process(*args, "--workspace", str(root / "one"))
    two = run(torchrun(*args, "--workspace", str(root / "two")))
    manifest = json.loads((root / "one" / "manifest.json").read_text())
    one_process("build-moe", "--workspace", str(root / "one"), "--device", "cpu")
    return root, recipe, two, manifest


def test_experts_are_shared_out_by_cost():
    from boostnerf_cli.stages.pretrain import assign

    assert assign([8, 10, 14], 2) == [[14], [8, 10]]
    assert assign([64, 80, 96, 128, 160], 3) == [[160], [64, 128], [80, 96]]
    assert assign([8, 10], 1) == [[8, 10]]  # one process: every expert, smallest first, as before
    assert assign([8], 2) == [[8], []]


@pytest.mark.slow
def test_pretrain_under_torchrun_equals_one_process(setup):
    root, _, proc, manifest = setup
    stderr = proc.stderr
    one, two = root / "one", root / "two"
    for name in ("geometry", "dvgo-8", "dvgo-10", "dvgo-14"):
        a, _ = load_tensors(one / "experts" / f"{name}.safetensors")
        b, _ = load_tensors(two / "experts" / f"{name}.safetensors")
        assert sorted(a) == sorted(b), name
        for k in a:
            assert torch.equal(a[k], b[k]), f"{name}: {k}"
    for name in ("dvgo-8", "dvgo-10", "dvgo-14"):
        got, want = (json.loads((ws / "experts" / f"{name}.json").read_text()) for ws in (two, one))
        assert got["history"][-1]["psnr"] == want["history"][-1]["psnr"]
        assert stderr.count(f"{name}: 16 steps in") == 1  # trained by exactly one rank
    assert stderr.count("geometry: training") == 1  # the shared stage ran once, on rank 0
    assert json.loads((two / "manifest.json").read_text()) == manifest
    assert proc.stdout.count("┃ expert") == 1  # one summary table, from rank 0
    assert_clean(two)


# --- one data-parallel step against one process on the union ----------------------------------
def _task(ws: Path, name: str):
    """The task `finetune` trains for `name` (top2 of 3 experts, or the baseline) and its rays."""
    import dataclasses

    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.models import load_expert, load_mixture
    from boostnerf_cli.moe.router import penalty_weights
    from boostnerf_cli.recipe import recipe_from_dict
    from boostnerf_cli.render.renderer import RenderSettings
    from boostnerf_cli.tasks import FieldTask, MixtureTask, train_rays
    from boostnerf_cli.workspace import Workspace

    w = Workspace(ws)
    rec = recipe_from_dict(w.manifest()["recipe"]).moe
    scene = Survey(w).scene()
    if name == "baseline":
        model, occ, meta = load_expert(w.expert_path("dvgo-14"))
        settings = RenderSettings(step=meta["step"], near=scene.near, far=scene.far, bbox=model.bbox,
                                  background=scene.background, color_threshold=rec.train.color_threshold,
                                  ndc=scene.ndc)
        task = FieldTask(model, settings, rec.train, skip=occ, base_mask=occ)
        return task, train_rays(scene, model.bbox, "cpu", rec.train), rec
    mix, _ = load_mixture(w.model_path("init"))
    mix.cfg = dataclasses.replace(mix.cfg, topk=2, renormalize=rec.renormalize, penalty=rec.penalty)
    mix.penalty = penalty_weights(mix.m, rec.penalty)
    mix.train()
    settings = RenderSettings(step=mix.cfg.step, near=scene.near, far=scene.far, bbox=mix.bbox,
                              background=scene.background, color_threshold=rec.train.color_threshold, ndc=scene.ndc)
    return MixtureTask(mix, settings, rec.train, rec), train_rays(scene, mix.bbox, "cpu", rec.train), rec


def first_step(ws: Path, name: str, parallel: bool, lam: float | None = None,
               official: bool = False) -> tuple[dict[str, torch.Tensor], dict]:
    """Step 1 of `finetune` for `name` as `train` runs it: the global batch of the seed, this process's share
    of it, the gradients (averaged over the ranks when `parallel`); -> (gradients by parameter name, logs).
    `lam`: the mixture's auxiliary-loss weight instead of the recipe's; `official`: the mixture trained with
    the official code's options (alpha mixing, auxiliary loss over (sum c_i)^2 and the visible samples)."""
    import dataclasses

    from boostnerf_cli import distributed as dist
    from boostnerf_cli.train import batch_gradients, make_optimizer

    task, rays, rec = _task(ws, name)
    if lam is not None:
        rec.lam = lam
    if official and name != "baseline":
        task.mix.cfg = dataclasses.replace(task.mix.cfg, mix="alpha", aux_norm="counts", aux_samples="visible")
    torch.manual_seed(rec.seed)
    gen = torch.Generator().manual_seed(rec.seed)
    idx = torch.randint(0, len(rays), (rec.train.batch_rays,), generator=gen)
    opt = make_optimizer(task)
    params = [p for g in opt.param_groups for p in g["params"]]
    learnable, loss_bad, logs = batch_gradients(task, rays, idx, 0, parallel)
    finite = not bool(loss_bad)
    if parallel:
        learnable, finite, logs = dist.average_gradients(params, learnable, finite, logs)
    assert learnable and finite
    module = task.mix if name != "baseline" else task.model
    grads = {k: p.grad.clone() for k, p in module.named_parameters() if p.grad is not None}
    return grads, logs


def dp_worker(ws: str, out: str, official: bool = False) -> None:
    """One rank of the data-parallel step (run with torchrun's environment variables)."""
    from boostnerf_cli import distributed as dist

    with dist.session("cpu"):
        result = {name: first_step(Path(ws), name, parallel=True, lam=LAM, official=official)
                  for name in ("top2", "baseline")}
        torch.save(result, Path(out) / f"rank{dist.rank()}.pt")


@pytest.mark.slow
@pytest.mark.parametrize("official", [False, True])
def test_a_data_parallel_step_equals_one_process_step_on_the_union(setup, tmp_path, official):
    ws = setup[0] / "one"
    # launched as users launch boostnerf, by torchrun: its agent holds the rendezvous store, so no rank is
    # the store's server and the ranks may leave in any order (docs/distributed.md)
    code = f"from test_distributed import dp_worker; dp_worker({str(ws)!r}, {str(tmp_path)!r}, {official})"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes=1", "--nproc_per_node=2", "--master_addr=127.0.0.1",
           f"--master_port={free_port()}", "--no-python", sys.executable, "-c", code]
    proc = subprocess.run(cmd, cwd=TESTS, capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ranks = [torch.load(tmp_path / f"rank{r}.pt") for r in range(2)]
    torch.set_num_threads(1)
    for name in ("top2", "baseline"):
        want_grads, want_logs = first_step(ws, name, parallel=False, lam=LAM, official=official)
        (g0, logs0), (g1, logs1) = ranks[0][name], ranks[1][name]
        assert logs0 == logs1 and sorted(g0) == sorted(g1) == sorted(want_grads), name
        for k, want in want_grads.items():
            assert torch.equal(g0[k], g1[k]), f"{name} {k}: the ranks hold different gradients"
            scale = float(want.abs().max())
            assert scale > 0, f"{name} {k}"
            assert float((g0[k] - want).abs().max()) <= GRAD_RTOL * scale, f"{name} {k}"
        assert logs0.keys() == want_logs.keys()
        for k, v in want_logs.items():
            assert v == pytest.approx(logs0[k], rel=LOSS_RTOL), f"{name} {k}"
        if name == "top2":
            assert want_logs["aux"] > 0 and 0 < want_logs["load0"] < 1  # a sparse top-2 of 3 experts


# --- resume with another number of processes, failures --------------------------------------------
@pytest.mark.slow
def test_finetune_checkpointed_by_two_ranks_resumes_in_one_process(setup, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(setup[0] / "one", ws)
    args = ["finetune", "--workspace", str(ws), "--topk", "2", "--device", "cpu"]
    proc = subprocess.Popen(torchrun(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=_env())
    assert proc.stderr is not None
    for line in proc.stderr:  # rank 0 alone prints progress; the step-8 checkpoint is written by now
        if line.startswith("[top2] step 10/24"):
            proc.send_signal(signal.SIGTERM)  # as a job scheduler stops a job: torchrun stops every rank
            break
    rest = proc.stderr.read()
    assert proc.wait(timeout=120) != 0
    assert "interrupted: finished files are kept" in rest, rest[-3000:]
    state = torch.load(ws / "checkpoints" / "top2.pt", weights_only=True)
    assert 8 <= state["step"] < 24
    resumed = one_process(*args)
    assert f"resuming from {ws / 'checkpoints' / 'top2.pt'} at step {state['step']}/24" in resumed.stderr
    report = json.loads((ws / "moe" / "top2.json").read_text())
    assert [h["step"] for h in report["history"]] == list(range(1, 25)) and report["skipped_steps"] == 0
    _, want = first_step(ws, "top2", parallel=False)  # step 1 ran on 2 ranks: the loss of the union
    for k in ("loss", "psnr", "aux"):
        assert report["history"][0][k] == pytest.approx(float(want[k]), rel=LOSS_RTOL), k  # a 0-d tensor
    assert_clean(ws)


@pytest.mark.slow
def test_a_failing_rank_stops_every_rank_with_its_message_and_keeps_finished_files(setup, tmp_path):
    root, recipe = setup[0], setup[1]
    ws = tmp_path / "ws"
    shutil.copytree(root / "two", ws)
    for p in (ws / "experts").glob("dvgo-8.*"):
        p.unlink()
    (ws / "experts" / "dvgo-8.safetensors" / "blocked").mkdir(parents=True)  # its rank cannot write it
    before = files(ws)
    # experts left: dvgo-12 (rank 0) and dvgo-8 (rank 1, fails when it writes its result)
    proc = run(torchrun("pretrain", "--data", json.loads((root / "one" / "manifest.json").read_text())["data"]["path"],
                        "--recipe", str(recipe), "--res", "8,10,12,14", "--workspace", str(ws), "--device", "cpu"),
               check=False)
    assert proc.returncode != 0
    assert "error: rank 1 of 2 failed: could not write" in proc.stderr  # rank 0, with rank 1's reason
    assert "dvgo-8.safetensors (Is a directory)" in proc.stderr
    assert proc.stderr.count("dvgo-12: 16 steps in") == 1
    after = files(ws)
    for name, data in before.items():  # the earlier files are untouched (the manifest's expert list too)
        if name != "manifest.json":
            assert after[name] == data, name
    assert json.loads(after["manifest.json"])["experts"] == json.loads(before["manifest.json"])["experts"]
    load_tensors(ws / "experts" / "dvgo-12.safetensors")  # rank 0's expert is complete
    assert (ws / "experts" / "dvgo-12.json").exists()
    assert not [p for p in ws.rglob("*") if is_temporary(p) or p.name == ".lock"]
