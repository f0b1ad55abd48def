"""`boostnerf chain`: every stage in one process (pretrain to the video), its rerun, the recipe it picks for a scene,
and the inputs it refuses before it writes anything; recipes/chain.sh and quickstart.sh, its thin callers."""

from __future__ import annotations

import json
import os
import re
import signal
import stat
import subprocess
from pathlib import Path

import pytest
from conftest import cli_in_process, run_cli

from boostnerf_cli.faults import ENV as TEST_KILL_ENV
from boostnerf_cli.recipe import load_recipe
from boostnerf_cli.scenes import LAYOUTS, load_scene, make_scene
from boostnerf_cli.stages import chain

ROOT = Path(__file__).resolve().parents[1]
RECIPES = sorted((ROOT / "recipes").glob("*.yaml"))

# the quickstart's recipe cut down to seconds: two tiny experts, a few steps a stage, 16 px images
CUT = [f"--set={setting}" for setting in (
    "data.image_size=16", "pretrain.res=[8, 12]", "pretrain.iters=8", "pretrain.dvgo.hidden=8",
    "pretrain.train.batch_rays=128", "pretrain.geometry.res=8", "pretrain.geometry.iters=20",
    "pretrain.geometry.batch_rays=128", "pretrain.geometry.alpha_init=0.01", "moe.gate_res=4", "moe.bake_res=8",
    "moe.iters=4", "moe.train.batch_rays=128", "moe.train.checkpoint_every=2")]
MODELS = ("baseline", "top1", "top2", "ens")


def stage_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if re.fullmatch(r"\[\d+/\d+\] .+", line)]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_scene(tmp_path_factory.mktemp("chain") / "scene", size=16, n_train=6, n_test=2, seed=0)


@pytest.mark.slow
def test_chain_makes_every_artifact_resumes_after_an_interrupt_and_reruns_when_finished(tmp_path, scene):
    ws = tmp_path / "ws"
    args = ["chain", str(scene), "-w", str(ws), "--recipe", "demo-dvgo-cpu", *CUT, "--frames", "3", "--device", "cpu"]
    # killed as it writes top2: the experts, moe/init, the baseline and top1 are finished
    proc = run_cli(*args, env_extra={TEST_KILL_ENV: "write:top2.safetensors"})
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
    assert stage_lines(proc.stderr) == ["[1/10] pretrain", "[2/10] build-moe", "[3/10] finetune baseline",
                                        "[4/10] finetune top1", "[5/10] finetune top2"]
    kept = {m: ws.joinpath("moe", f"{m}.safetensors").stat().st_mtime_ns for m in ("baseline", "top1")}

    proc = run_cli(*args, check=True)
    assert len(stage_lines(proc.stderr)) == 10 and stage_lines(proc.stderr)[-1] == "[10/10] render --path"
    timed = re.search(r"chain: seconds by stage: (.+)", proc.stderr).group(1).split(", ")  # every stage, in order
    assert [t.rsplit(" ", 1)[0] for t in timed] == [line.split("] ")[1] for line in stage_lines(proc.stderr)]
    assert "already trained, skipping" in proc.stderr
    assert "baseline: already finetuned" in proc.stderr and "top1: already finetuned" in proc.stderr
    assert "top2: already finetuned" not in proc.stderr and "ens: already finetuned" not in proc.stderr
    assert kept == {m: ws.joinpath("moe", f"{m}.safetensors").stat().st_mtime_ns for m in kept}
    for name in ("dvgo-8", "dvgo-12"):
        assert (ws / "experts" / f"{name}.safetensors").is_file()
    for name in ("init", *MODELS):
        assert (ws / "moe" / f"{name}.safetensors").is_file()
    report = json.loads((ws / "reports" / "eval.json").read_text())
    assert [m["name"] for m in report["models"]] == ["dvgo-8", "dvgo-12", *MODELS] and report["views"] == 2
    counts = json.loads((ws / "reports" / "count-params.json").read_text())
    assert [m["name"] for m in counts["models"]] == ["dvgo-8", "dvgo-12", *MODELS]
    pictures = sorted((ws / "renders" / "compare" / "test").glob("*.png"))
    assert len(pictures) == 2
    psnr = {m["name"]: m["psnr"] for m in report["models"]}
    best = max(MODELS, key=psnr.get)
    videos = [ws / "renders" / best / "orbit.mp4", ws / "renders" / best / "orbit_depth.mp4"]  # a sphere of cameras
    assert all(v.is_file() and v.stat().st_size > 0 for v in videos)
    assert f"video: {best} (the highest held-out PSNR" in proc.stderr
    table = proc.stdout  # the eval table, at the end
    assert "PSNR" in table and all(name in table for name in MODELS)

    # a finished chain: nothing trained or drawn again; the reports made again
    files = [*ws.glob("experts/*.safetensors"), *ws.glob("moe/*.safetensors"), *pictures, *videos]
    before = {f: f.stat().st_mtime_ns for f in files}
    reports = (ws / "reports" / "eval.json").stat().st_mtime_ns
    proc = run_cli(*args, check=True)
    assert proc.stderr.count("already finetuned, skipping") == 4 and "kept as it is" in proc.stderr
    assert "compare: the 2 pictures" in proc.stderr and "is newer than" in proc.stderr
    assert before == {f: f.stat().st_mtime_ns for f in files}
    assert (ws / "reports" / "eval.json").stat().st_mtime_ns > reports


# --- the recipe picked ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def layouts(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("layouts")
    return {layout: make_scene(base / layout, size=16, n_train=6, n_test=2, seed=0, layout=layout)
            for layout in LAYOUTS}


def test_the_recipe_picked_is_the_cpu_recipe_of_the_scenes_layout(layouts):
    wanted = {"blender": "blender-dvgo-cpu", "nsvf": "nsvf-dvgo-cpu", "tanks": "tanks-dvgo-cpu",
              "llff": "llff-dvgo-cpu", "nerfstudio": "nerfstudio-dvgo-cpu", "colmap": "capture-dvgo-cpu"}
    assert set(wanted) == set(LAYOUTS)
    for layout, folder in layouts.items():
        pick = chain.pick_recipe(folder, "cpu")
        assert pick.name == wanted[layout] and pick.path == ROOT / "recipes" / f"{wanted[layout]}.yaml", layout
        assert "\n" not in pick.why and pick.why.startswith(f"recipe {pick.name}: {folder} is ")
        rec = load_recipe(pick.path)
        assert rec.data.scene == "auto" and rec.data.format == "auto", layout  # kind and layout told by the files
        on_gpu = chain.pick_recipe(folder, "cuda")
        assert on_gpu.name == pick.name  # the paper's recipe is named, never picked
        if layout != "colmap":
            paper = f"{layout}-dvgo-paper"
            assert f"--recipe {paper}" in on_gpu.why and (ROOT / "recipes" / f"{paper}.yaml").is_file()
            assert "paper" not in pick.why
    assert chain.pick_recipe(None).name == "demo-dvgo-cpu"  # `-`: the embedded procedural scene
    asked = chain.pick_recipe(layouts["blender"], "cpu", data_format="llff")  # --format: the layout asked for
    assert asked.name == "llff-dvgo-cpu" and "--format llff" in asked.why


@pytest.mark.parametrize("path", RECIPES, ids=[p.name for p in RECIPES])
def test_every_shipped_recipe_reads_a_folder_capture_wrote(path, layouts):
    """A COLMAP folder, as `boostnerf capture` writes it, is refused by no recipe (none forces another layout)."""
    rec = load_recipe(path)
    assert rec.data.format == "auto", f"{path.name} forces data.format: {rec.data.format}"
    # at the images' own size: a recipe's image_size asks for no more pixels than a photo has (never upscaled)
    scene = load_scene(layouts["colmap"], holdout_every=rec.data.holdout_every, format=rec.data.format,
                       bbox=rec.data.bbox, kind=rec.data.scene)
    assert scene.format == "colmap"


def test_the_video_path_suits_the_cameras(layouts):
    llff = load_scene(layouts["llff"])
    sphere = load_scene(layouts["blender"])
    assert chain.video_kind(llff) == "spiral" and chain.video_kind(sphere) == "orbit"


def test_models_are_read_in_order_once_and_a_typo_is_refused():
    assert chain.parse_models("baseline,top2, top1 ens,top2") == ["baseline", "top2", "top1", "ens"]
    assert chain.parse_models("top12") == ["top12"]
    typos = (("ensemble", "(the ensemble is ens)"), ("top0", "'top0'"), ("base", "'base'"), (",", "no model"))
    for bad, needle in typos:
        with pytest.raises(chain.BoostNerfError, match=re.escape(needle)):
            chain.parse_models(bad)


def test_the_best_model_has_the_highest_psnr_of_the_models_made():
    result = {"models": [{"name": "dvgo-32", "psnr": 30.0}, {"name": "baseline", "psnr": 25.0},
                         {"name": "top2", "psnr": 25.5}, {"name": "ens", "psnr": None}]}
    assert chain.best_model(result, ["baseline", "top2", "ens"]) == "top2"
    assert chain.best_model({"models": []}, ["baseline", "top2"]) == "top2"


# --- what is refused before anything is written -----------------------------------------------------------------------
def refused(monkeypatch, capsys, tmp_path: Path, *args: str) -> str:
    """`boostnerf chain ARGS -w tmp_path/ws`: exit 2, one line and no traceback, no stage run, no workspace made."""
    code, stderr = cli_in_process(monkeypatch, capsys, "chain", *args, "-w", str(tmp_path / "ws"), "--device", "cpu")
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert "Traceback" not in stderr and not stage_lines(stderr)
    assert not (tmp_path / "ws").exists()
    return lines[0]


def test_a_folder_chain_cannot_read_is_one_line_and_no_workspace(monkeypatch, capsys, tmp_path):
    assert "does not exist" in refused(monkeypatch, capsys, tmp_path, str(tmp_path / "missing"))
    (tmp_path / "empty").mkdir()
    assert "is empty" in refused(monkeypatch, capsys, tmp_path, str(tmp_path / "empty"))
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "a.txt").write_text("no scene")
    assert "cannot tell the dataset format" in refused(monkeypatch, capsys, tmp_path, str(tmp_path / "notes"))
    (tmp_path / "file.png").write_bytes(b"")
    assert "is a file, not a scene folder" in refused(monkeypatch, capsys, tmp_path, str(tmp_path / "file.png"))
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p).name == "notes" else real(p, mode, **kw))
    assert "cannot read scene folder" in refused(monkeypatch, capsys, tmp_path, str(tmp_path / "notes"))


def test_a_bad_model_recipe_or_option_is_refused_before_any_stage(monkeypatch, capsys, tmp_path, scene):
    line = refused(monkeypatch, capsys, tmp_path, str(scene), "--models", "baseline,ensemble")
    assert "unknown model 'ensemble'" in line
    line = refused(monkeypatch, capsys, tmp_path, "-", "--models", "baseline,top4")  # the demo recipe: 3 experts
    assert "top4" in line and "3 experts" in line and "dvgo-16, dvgo-24, dvgo-32" in line
    line = refused(monkeypatch, capsys, tmp_path, str(scene), "--recipe", "blender-dvgo-gpu")
    assert "recipe blender-dvgo-gpu not found" in line and all(p.stem in line for p in RECIPES)
    assert "--top1-weight" in refused(monkeypatch, capsys, tmp_path, "-", "--top1-weight", "probability")
    assert "--video-model" in refused(monkeypatch, capsys, tmp_path, "-", "--models", "top2", "--video-model", "ens")
    assert "pretrain.iters" in refused(monkeypatch, capsys, tmp_path, "-", "--set", "pretrain.iters=0")
    monkeypatch.setenv("WORLD_SIZE", "2")  # under torchrun: one process runs the chain
    assert "run this command as one process" in refused(monkeypatch, capsys, tmp_path, "-")


# --- the scripts, thin callers --------------------------------------------------------------------------------------
def fake_boostnerf(tmp_path: Path) -> dict[str, str]:
    """A `boostnerf` on PATH that logs its arguments, one call a line, to tmp_path/calls -> the environment."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "boostnerf"
    fake.write_text(f'#!/usr/bin/env bash\nprintf "%s|" "$@" >> {tmp_path / "calls"}\necho >> {tmp_path / "calls"}\n')
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    env = {k: v for k, v in os.environ.items() if k not in ("DEVICE", "MODELS", "TOP1_WEIGHT", "SEED")}
    return {**env, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}


def calls(tmp_path: Path) -> list[list[str]]:
    return [line.rstrip("|").split("|") for line in (tmp_path / "calls").read_text().splitlines()]


def test_chain_sh_passes_its_arguments_and_environment_to_boostnerf_chain(tmp_path):
    env = {**fake_boostnerf(tmp_path), "DEVICE": "cpu", "MODELS": "baseline top2", "TOP1_WEIGHT": "raw"}
    subprocess.run(["bash", str(ROOT / "recipes" / "chain.sh"), "llff-dvgo-cpu", "data/fern", "ws", "--format", "llff",
                    "--iters", "300", "--no-skip", "--holdout-every=4", "--res", "32,48", "--device", "cuda"],
                   env=env, check=True, cwd=tmp_path)
    assert calls(tmp_path) == [[
        "chain", "data/fern", "--workspace", "ws", "--recipe", str(ROOT / "recipes" / "llff-dvgo-cpu.yaml"),
        "--device", "cpu", "--models", "baseline top2", "--top1-weight", "raw", "--format", "llff",
        "--set", "pretrain.iters=300", "--set", "pretrain.skip=false", "--set", "data.holdout_every=4",
        "--res", "32,48", "--device", "cuda"]]
    defaults = tmp_path / "defaults"  # no environment: chain.sh's defaults
    defaults.mkdir()
    subprocess.run(["bash", str(ROOT / "recipes" / "chain.sh"), "mine.yaml", "-", "ws"], env=fake_boostnerf(defaults),
                   check=True, cwd=tmp_path)
    assert calls(defaults) == [[
        "chain", "-", "--workspace", "ws", "--recipe", "mine.yaml", "--device", "auto", "--models",
        "baseline top1 top2 ens", "--top1-weight", "renormalized"]]
    usage = subprocess.run(["bash", str(ROOT / "recipes" / "chain.sh")], capture_output=True, text=True)
    assert usage.returncode == 2 and "Usage: bash recipes/chain.sh RECIPE DATA WS" in usage.stderr


def test_quickstart_sh_is_chain_then_the_per_expert_pictures(tmp_path):
    env = {**fake_boostnerf(tmp_path), "SEED": "1", "DEVICE": "cpu"}
    subprocess.run(["bash", str(ROOT / "recipes" / "quickstart.sh"), "ws-demo"], env=env, check=True, cwd=tmp_path,
                   capture_output=True)
    made = calls(tmp_path)
    assert [c[0] for c in made] == ["make-scene", "chain", "render"]
    assert made[1] == ["chain", "ws-demo/scene", "--workspace", "ws-demo", "--recipe",
                       str(ROOT / "recipes" / "demo-dvgo-cpu.yaml"), "--seed", "1", "--device", "cpu",
                       "--video-model", "top2"]
    assert "--per-expert" in made[2] and "top2" in made[2]
