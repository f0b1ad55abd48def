"""Every stage runs with `--device cuda`, checked on a CPU-only machine with a simulated GPU.

`simdevice.simulated_gpu()` makes tensors on the "GPU" wrappers around CPU data that every operator
checks for device mismatches as a GPU does (module docstring there). Each of the three faults found on
a real H100 has its own small test, and the whole pipeline, every family, a resumed run and bench run
on the simulated GPU. The simulated run computes with the CPU's kernels and the CPU's random numbers,
so it must give the very numbers of a CPU run: a test checks that too, so a stage that silently fell
back to the CPU for part of its work, or moved the wrong thing, would show.
"""

from __future__ import annotations

import json
from contextlib import nullcontext
from pathlib import Path

import pytest
import torch
from conftest import REMOVE, make_recipe
from helpers import budgets_hold_every_sample
from simdevice import SimTensor, simulated_gpu
from typer.testing import CliRunner

from boostnerf_cli.cli import app


def _invoke(*args: str) -> None:
    result = CliRunner().invoke(app, list(args))
    if result.exit_code != 0:
        raise AssertionError(f"boostnerf {' '.join(args)} failed on the simulated GPU") from result.exception


@pytest.fixture(autouse=True)
def budgets_that_hold_the_tiny_scenes(monkeypatch):
    """On a GPU every filter packs into a static budget and a step that overflows one is skipped (test_syncs.py
    tests that). Here every budget holds every sample (`helpers.budgets_hold_every_sample`)."""
    budgets_hold_every_sample(monkeypatch)


def test_the_simulator_catches_a_cpu_tensor_next_to_a_gpu_one():
    with simulated_gpu() as dev:
        a = torch.randn(4, 3).to(dev)
        assert isinstance(a, SimTensor) and a.device.type == dev
        assert torch.equal((a + torch.ones(4, 3, device=dev)).cpu(), a.cpu() + 1)  # real data
        assert (a * torch.tensor(2.0)).device.type == dev  # a CPU scalar is accepted, as on CUDA
        with pytest.raises(RuntimeError, match="same device"):
            a + torch.randn(4, 3)
        with pytest.raises(RuntimeError, match="same device"):
            torch.nn.functional.embedding_bag(torch.zeros(2, 1, dtype=torch.long, device=dev), torch.randn(5, 2),
                                              mode="sum")


def test_training_rays_are_cut_to_a_box_on_the_gpu(tiny_scene):
    """Fault 1: RayData.from_split intersected CPU rays with the GPU box."""
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.train import RayData

    scene = load_scene(tiny_scene)
    cpu = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    with simulated_gpu() as dev:
        rays = RayData.from_split(scene.splits["train"], scene.bbox.to(dev), scene.near, scene.far).to(dev)
        assert rays.origins.device.type == dev
        assert torch.equal(rays.rgb.cpu(), cpu.rgb)


@pytest.mark.parametrize("grid", ["dense", "tensorf", "hash"])
def test_a_gate_is_built_for_a_box_on_the_gpu_and_baked_there(grid):
    """Faults 2 and 3: Gate.__init__ built its table on the CPU next to a GPU box, and Gate.baked sampled its
    lattice on the wrong device."""
    from boostnerf_cli.moe.gate import Gate, GateConfig

    bbox = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    cfg = GateConfig(gate_res=8, gate_grid=grid, log2_table=10)
    torch.manual_seed(0)
    ref = Gate(cfg, 3, bbox)
    pts = torch.rand(64, 3) * 2 - 1
    with simulated_gpu() as dev:
        torch.manual_seed(0)
        gate = Gate(cfg, 3, bbox.to(dev)).to(dev)
        assert all(isinstance(t, SimTensor) for t in [*gate.parameters(), *gate.buffers()])
        assert torch.allclose(gate.logits(pts.to(dev)).cpu(), ref.logits(pts))
        baked = gate.baked(8)
        assert baked.logit_table.device.type == dev
        assert torch.allclose(baked.logits(pts.to(dev)).cpu(), ref.baked(8).logits(pts))


# the tiny recipe's changes for each family (dvgo: none)
FAMILY_CHANGES = {
    "dvgo": {},
    "tensorf": {"model": "tensorf", "dvgo": REMOVE,
                "tensorf": {"hidden": 16, "layers": 1, "density_rank": 4, "app_rank": 4, "app_dim": 8,
                            "fit_steps": 20}},
    "ngp": {"model": "ngp", "res": [4, 6], "dvgo": REMOVE,
            "ngp": {"hidden": 16, "log2_table": 10, "base_res": 4, "max_res": 32, "grid_res": 16, "fit_steps": 20}},
}
# Fewer steps than the tiny recipe's (the simulator makes each ~4x slower): every code path still runs, from the first
# step (warm start, 3 grid growths, an occupancy refresh, checkpoints every 4 steps of every stage, finetuning too).
SHORT = {"pretrain": {"iters": 12, "geometry": {"iters": 30},
                      "train": {"log_every": 4, "checkpoint_every": 4, "occupancy_every": 8}},
         "moe": {"iters": 8, "train": {"log_every": 4, "checkpoint_every": 4}}}


def _recipe(tmp_path: Path, family: str = "dvgo") -> Path:
    return make_recipe(tmp_path / f"{family}.yaml", pretrain={**FAMILY_CHANGES[family], **SHORT["pretrain"]},
                       moe=SHORT["moe"])


@pytest.mark.slow
def test_every_stage_on_the_simulated_gpu_gives_the_cpu_numbers(tmp_path, tiny_scene):
    """The reference is a plain CPU run, outside the simulator (whose dispatch mode makes a run ~4x slower)."""
    recipe = _recipe(tmp_path)
    for where in ("cpu", "gpu"):
        ws = str(tmp_path / where)
        device = "cpu" if where == "cpu" else "cuda"
        with simulated_gpu() if where == "gpu" else nullcontext():
            _invoke("pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "-w", ws, "--device", device)
            _invoke("build-moe", "-w", ws, "--device", device)
            for flags in (["--topk", "1"], ["--topk", "2"], ["--baseline"], ["--ensemble"]):
                _invoke("finetune", "-w", ws, *flags, "--device", device)
            _invoke("eval", "-w", ws, "--report", "--device", "auto" if where == "gpu" else "cpu")
            if where == "gpu":
                _invoke("count-params", "-w", ws, "--device", device)
                _invoke("render", "-w", ws, "--model", "top2", "--device", device)
                _invoke("render", "-w", ws, "--compare", "--views", "1", "--device", device)
                _invoke("render", "-w", ws, "--model", "top2", "--per-expert", "--views", "1", "--device", device)
                _invoke("render", "-w", ws, "--model", "top2", "--path", "orbit", "--frames", "2", "--video",
                        str(tmp_path / "orbit.gif"), "--device", device)
                _invoke("prune", "-w", ws, "--model", "top1", "--device", device)
                _invoke("eval", "-w", ws, "--model", "top1-pruned", "--no-costs", "--device", device)
    cpu, gpu = ({r["name"]: r for r in json.loads((tmp_path / w / "reports" / "eval.json").read_text())["models"]}
                for w in ("cpu", "gpu"))
    assert set(cpu) == set(gpu) and {"baseline", "top1", "top2", "ens"} <= set(cpu)
    for name in ("baseline", "top1", "top2", "ens"):
        assert json.loads((tmp_path / "gpu" / "moe" / f"{name}.json").read_text())["skipped_steps"] == 0, name
    for name in cpu:
        assert gpu[name]["psnr"] == pytest.approx(cpu[name]["psnr"], abs=1e-4), name
        assert gpu[name]["gflops_per_image"] == pytest.approx(cpu[name]["gflops_per_image"], rel=1e-6), name
    assert (tmp_path / "orbit.gif").exists()
    assert (tmp_path / "gpu" / "moe" / "top1-pruned.safetensors").exists()


@pytest.mark.slow
@pytest.mark.parametrize("family", ["tensorf", "ngp"])
def test_other_families_on_the_simulated_gpu(tmp_path, tiny_scene, family):
    """Placement only (no figure is compared), with the SHORT steps."""
    ws = str(tmp_path / "ws")
    with simulated_gpu():
        _invoke("pretrain", "--data", str(tiny_scene), "--recipe", str(_recipe(tmp_path, family)), "-w", ws,
                "--device", "cuda")
        _invoke("build-moe", "-w", ws, "--device", "cuda")
        _invoke("finetune", "-w", ws, "--topk", "2", "--iters", "10", "--device", "cuda")
        _invoke("eval", "-w", ws, "--model", "top2", "--device", "cuda")
        # the official code's V_D (the largest expert's density, the visible filter) and explicit penalty weights,
        # which read the largest expert of any family inside the filter
        official = make_recipe(tmp_path / f"{family}-vd.yaml", pretrain=FAMILY_CHANGES[family],
                               moe={"vd_source": "largest", "vd_filter": "visible", "penalty": "1, 1.5"})
        _invoke("finetune", "-w", ws, "--recipe", str(official), "--topk", "1", "--iters", "10", "--device", "cuda")
        _invoke("eval", "-w", ws, "--model", "top1", "--device", "cuda")
    report = json.loads((tmp_path / "ws" / "moe" / "top1.json").read_text())
    assert (report["vd_source"], report["vd_filter"], report["penalty"]) == ("largest", "visible", "1, 1.5")


@pytest.mark.slow
def test_a_run_interrupted_on_the_gpu_resumes_there(tmp_path, tiny_scene, monkeypatch):
    """A checkpoint written from the GPU (read back with map_location=cpu) resumes on the GPU: model, Adam
    state and random state go back to the device, and the result equals an uninterrupted run. That run is on
    the CPU, outside the simulator (~4x faster): the simulated GPU gives the CPU's numbers (the test above)."""
    from boostnerf_cli import train as train_mod

    recipe = _recipe(tmp_path)
    _invoke("pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "-w", str(tmp_path / "whole"),
            "--device", "cpu")
    with simulated_gpu():
        real_save, saves = train_mod.TrainCheckpoint.save, []

        def save_then_stop(self, *args, **kwargs):
            real_save(self, *args, **kwargs)
            saves.append(self.path)
            if self.path.name.startswith("dvgo-16") and len([p for p in saves if p == self.path]) == 2:
                raise KeyboardInterrupt  # as if stopped right after the second checkpoint

        monkeypatch.setattr(train_mod.TrainCheckpoint, "save", save_then_stop)
        result = CliRunner().invoke(app, ["pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "-w",
                                          str(tmp_path / "cut"), "--device", "cuda"])
        assert result.exit_code != 0 and (tmp_path / "cut" / "checkpoints" / "dvgo-16.pt").exists()
        monkeypatch.setattr(train_mod.TrainCheckpoint, "save", real_save)
        _invoke("pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "-w", str(tmp_path / "cut"),
                "--device", "cuda")
    whole, cut = (json.loads((tmp_path / w / "experts" / "dvgo-16.json").read_text()) for w in ("whole", "cut"))
    assert cut["test_psnr"] == pytest.approx(whole["test_psnr"], abs=1e-4)


@pytest.mark.slow
def test_bench_on_the_simulated_gpu(tmp_path, tiny_scene):
    with simulated_gpu():
        _invoke("bench", "--data", str(tiny_scene), "--recipe", str(_recipe(tmp_path)), "-w", str(tmp_path / "b"),
                "--only", "dvgo-12,top1", "--views", "1", "--device", "cuda")
    rows = json.loads((tmp_path / "b" / "reports" / "bench.json").read_text())["rows"]
    assert {r["name"] for r in rows} == {"dvgo-12", "top1"}


@pytest.mark.slow
def test_the_viewer_renders_on_the_simulated_gpu_what_it_renders_on_the_cpu(mixture_ws):
    """`boostnerf view --device cuda`: the maps of a dataset view (routing renders every gate map; depth is colour's
    render), their GFLOPs and the routed cells, as on the CPU."""
    import numpy as np

    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.stages import view
    from boostnerf_cli.viewpoint.frame import Look

    MAPS = ("colour", "routing", "share")
    from boostnerf_cli.workspace import Workspace

    ws = Workspace(mixture_ws)
    scene = Survey(ws).scene()
    shots = {}
    for device in ("cpu", "gpu"):
        with simulated_gpu() if device == "gpu" else nullcontext() as dev:
            viewer = view.Viewer(ws, scene, view.Models(ws, dev or "cpu"), model="top2")
            assert viewer.model.bbox.device.type == (dev or "cpu")
            for mode in MAPS:
                viewer.show(Look(mode, 1))
                shots[device, mode] = viewer.go_to("test", 0).shot
            shots[device, "cells"] = viewer.model_parts()[1]
    for mode in MAPS:
        cpu, gpu = shots["cpu", mode], shots["gpu", mode]
        assert np.abs(cpu.image.astype(int) - gpu.image.astype(int)).max() <= 1, mode
        assert gpu.gflops == pytest.approx(cpu.gflops, rel=1e-6), mode
    assert np.array_equal(shots["cpu", "cells"][1], shots["gpu", "cells"][1])
