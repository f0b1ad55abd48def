"""The mixture-of-experts stages through the real CLI, on the tiny workspace."""

import json
import os
import shutil

import pytest
import torch
from conftest import (
    PSNR_MARGIN,
    TINY_MOE_PSNR_2_VIEWS,
    assert_clean_failure,
    cli_in_process,
    make_recipe,
    no_temp_files,
    run_cli,
    run_script,
)
from safetensors.torch import save_file

from boostnerf_cli.workspace import load_tensors, save_tensors


@pytest.fixture(scope="module")
def moe_ws(trained_ws, tmp_path_factory):
    ws = tmp_path_factory.mktemp("moe") / "ws"
    shutil.copytree(trained_ws, ws)
    run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    for flag in (["--topk", "1"], ["--topk", "2"], ["--ensemble"], ["--baseline"]):
        run_cli("finetune", "--workspace", str(ws), *flag, "--device", "cpu", check=True)
    return ws


def test_a_density_volume_that_keeps_no_cell_is_refused(trained_ws, tmp_path):
    """A V_D threshold no cell passes (or experts that learnt no density) filters every sample: such a mixture could
    never train (it was built, then finetuned with the load [0, 0] and evaluated at 0 GFLOPs, without a word)."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("moe", "reports", "renders"))
    assert_clean_failure(run_cli("build-moe", "--workspace", str(ws), "--threshold", "0.99999", "--device", "cpu"),
                         "keeps no cell", "--threshold")
    assert not (ws / "moe").exists() or not list((ws / "moe").iterdir())
    # one an earlier boostnerf wrote (another file format): not finetuned, but made again by this build-moe
    run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    path = ws / "moe" / "init.safetensors"
    tensors, meta = load_tensors(path)
    tensors["occupancy"] = torch.zeros_like(tensors["occupancy"])
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(path),
              metadata={"boostnerf": json.dumps({**meta, "format_version": "1"})})
    assert_clean_failure(run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--device", "cpu"),
                         f"{path} has file format '1', and this boostnerf reads format", "rerun `boostnerf build-moe`")
    assert not (ws / "moe" / "top1.safetensors").exists()


def test_models_made_from_a_retrained_expert_are_refused_until_made_again(moe_ws, tmp_path, tiny_scene, tiny_recipe,
                                                                         monkeypatch, capsys):
    """eval, render, count-params and prune refuse a model made from what changed since (an expert retrained after
    build-moe, a mixture finetuned again after prune), naming it and what to run; the current models still go.
    They evaluated and tabulated such stale models beside the new experts, without a word."""
    ws = tmp_path / "ws"
    shutil.copytree(moe_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    run_cli("prune", "--workspace", str(ws), "--model", "top1", "--device", "cpu", check=True)
    w = ["--workspace", str(ws), "--device", "cpu"]
    for f in (ws / "experts").glob("dvgo-16.*"):  # dvgo-16 retrained (with one more step: other weights)
        f.unlink()
    run_cli("pretrain", *w, "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--res", "16", "--iters", "31",
            check=True)
    for args in (["eval"], ["eval", "--model", "top2"], ["render", "--views", "1"], ["render", "--compare"],
                 ["render", "--model", "baseline", "--path", "orbit", "--frames", "2"], ["count-params"],
                 ["prune", "--model", "top2"], ["eval", "--model", "top1-pruned"]):
        code, err = cli_in_process(monkeypatch, capsys, *args, *w)
        assert code == 2 and err.startswith("error: ") and "stale" in err and "dvgo-16 was retrained" in err, err
    for name, needle in (("top2", "build-moe"), ("baseline", "--baseline --force")):
        code, err = cli_in_process(monkeypatch, capsys, "eval", "--model", name, *w)
        assert code == 2 and f"{name} is stale" in err and needle in err, err
    # every stale model at once: each way of making them again is named, not only the first model's (the
    # baseline's `--baseline --force` came up only after the mixtures had been remade)
    code, err = cli_in_process(monkeypatch, capsys, "eval", *w)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"make baseline again with `boostnerf finetune -w {ws} --baseline --force`; top1, top2, top1-pruned, " \
           f"ens with `boostnerf build-moe -w {ws}`, then finetune" in err, err
    proc = run_cli("eval", "--model", "dvgo-12", "--model", "dvgo-16", "--views", "1", "--no-costs", *w, check=True)
    assert "PSNR" in proc.stderr
    run_cli("build-moe", *w, check=True)
    run_cli("finetune", "--topk", "1", "--force", *w, check=True)
    proc = run_cli("eval", "--model", "top1-pruned", *w)
    assert_clean_failure(proc, "top1-pruned is stale", "boostnerf prune", "--model top1 --force")
    assert_clean_failure(run_cli("eval", "--model", "top2", *w), "top2 is stale", "finetune", "--topk 2 --force")


def test_build_moe_writes_an_untrained_mixture(moe_ws):
    report = json.loads((moe_ws / "moe" / "init.json").read_text())
    assert report["experts"] == ["dvgo-12", "dvgo-16"]  # ordered by size
    assert report["density_volume"]["from"] == "dvgo-12"
    assert (moe_ws / "moe" / "init.safetensors").exists()


def test_finetune_adds_every_comparison_model_with_load_reports(moe_ws):
    for name in ("top1", "top2", "ens", "baseline"):
        report = json.loads((moe_ws / "moe" / f"{name}.json").read_text())
        assert report["name"] == name and report["iterations"] == 20 and report["seconds"] > 0
    top1 = json.loads((moe_ws / "moe" / "top1.json").read_text())
    assert abs(sum(top1["load"]) - 1.0) < 1e-6  # top-1: loads are fractions of samples summing to 1
    top2 = json.loads((moe_ws / "moe" / "top2.json").read_text())
    assert abs(sum(top2["load"]) - 2.0) < 1e-6
    assert any("load0" in h for h in top2["history"])
    assert json.loads((moe_ws / "moe" / "baseline.json").read_text())["from"] == "dvgo-16"
    assert no_temp_files(moe_ws) and not list((moe_ws / "checkpoints").glob("*"))


def test_eval_and_count_params_list_every_model(moe_ws):
    run_cli("eval", "--workspace", str(moe_ws), "--report", "--device", "cpu", "--views", "2", check=True)
    report = json.loads((moe_ws / "reports" / "eval.json").read_text())
    names = [m["name"] for m in report["models"]]
    assert names == ["dvgo-12", "dvgo-16", "baseline", "top1", "top2", "ens"]
    for m in report["models"]:
        assert m["w0"] > 0 and m["gflops_per_image"] > 0 and m["w0"] <= m["params"]
        assert m["psnr"] >= TINY_MOE_PSNR_2_VIEWS[m["name"]] - PSNR_MARGIN, (m["name"], m["psnr"])
    # a mixture's row says how it routes (a top1 finetuned with --no-renormalize is another model of the same name)
    routing = {m["name"]: m.get("routing") for m in report["models"]}
    assert routing == {"dvgo-12": None, "dvgo-16": None, "baseline": None, "top1": {"topk": 1, "renormalize": True},
                       "top2": {"topk": 2, "renormalize": True}, "ens": {"topk": 2, "renormalize": True}}
    table = (moe_ws / "reports" / "eval.md").read_text().splitlines()
    assert sum(1 for line in table if line.startswith("| top")) == 2
    run_cli("count-params", "--workspace", str(moe_ws), "--device", "cpu", "--views", "1", check=True)
    counts = json.loads((moe_ws / "reports" / "count-params.json").read_text())
    rows = {m["name"]: m for m in counts["models"]}
    assert set(rows) == set(names)
    for m in rows.values():
        assert {"name", "params", "w0", "gflops_per_image"} <= set(m)
    top1 = rows["top1"]
    assert len(top1["experts"]) == 2 and sum(e["w0"] for e in top1["experts"]) + top1["gate"]["w0"] == top1["w0"]


def test_finetune_before_build_moe_says_what_to_run(trained_ws, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--device", "cpu")
    assert_clean_failure(proc, "boostnerf build-moe")


def test_finetune_flag_misuse(moe_ws):
    proc = run_cli("finetune", "--workspace", str(moe_ws), "--topk", "1", "--ensemble")
    assert_clean_failure(proc, "exactly one")
    proc = run_cli("finetune", "--workspace", str(moe_ws), "--topk", "5", "--device", "cpu", "--force")
    assert_clean_failure(proc, "--topk")


def test_build_moe_refuses_experts_of_different_scenes(trained_ws, tmp_path, tiny_scene, tiny_recipe):
    other = tmp_path / "other"
    run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace", str(other),
            "--image-size", "24", "--res", "12", "--device", "cpu", check=True)
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    shutil.copy(other / "experts" / "dvgo-12.safetensors", ws / "experts" / "dvgo-12.safetensors")
    proc = run_cli("build-moe", "--workspace", str(ws), "--device", "cpu")
    assert_clean_failure(proc, "different scenes")
    proc = run_cli("build-moe", "--workspace", str(ws), "--experts", "dvgo-99", "--device", "cpu")
    assert_clean_failure(proc, "dvgo-99")
    # nor a gate copied from an expert of another scene that the mixture leaves out (moe.gate_from)
    recipe = make_recipe(tmp_path / "gate-from.yaml", moe={"gate_init": "expert", "gate_from": "dvgo-12", "topk": 1})
    proc = run_cli("build-moe", "--workspace", str(ws), "--recipe", str(recipe), "--experts", "dvgo-16",
                   "--device", "cpu")
    assert_clean_failure(proc, "different scenes")


def test_build_moe_refuses_an_expert_named_twice(trained_ws, tmp_path):
    """`--experts dvgo-12,dvgo-12` was a traceback from safetensors (two experts sharing their tensors)."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    proc = run_cli("build-moe", "--workspace", str(ws), "--experts", "dvgo-12,dvgo-16,dvgo-12", "--device", "cpu")
    assert_clean_failure(proc, "--experts names dvgo-12 more than once")
    assert not (ws / "moe").exists() and no_temp_files(ws)


def test_a_model_named_twice_counts_once_and_each_model_says_its_own_image_count(moe_ws):
    """`render --model dvgo-12 --model top1 --model dvgo-12` rendered dvgo-12 twice, and the second model's line
    counted the first one's images too ("top1: wrote 2 images" for one view)."""
    proc = run_cli("render", "--workspace", str(moe_ws), "--model", "dvgo-12", "--model", "top1", "--model", "dvgo-12",
                   "--views", "1", "--device", "cpu", check=True)
    said = [line.split(" (")[0] for line in proc.stderr.splitlines() if "wrote" in line]
    assert said == ["dvgo-12: wrote 1 view", "top1: wrote 1 view"], proc.stderr


def test_build_moe_names_an_expert_it_leaves_out_for_want_of_its_report(trained_ws, tmp_path):
    """An expert whose report is missing (pretrain stopped between its two files) was left out without a word, and
    build-moe's next line blamed moe.topk."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    (ws / "experts" / "dvgo-12.json").unlink()
    proc = run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    assert "leaving out dvgo-12: weights without a training report" in proc.stderr
    # one expert left: the untrained mixture routes to it (moe.topk = 2 was refused, and build-moe has no --topk)
    assert "note: moe.topk = 2 but the mixture has 1 expert: moe/init routes to 1" in proc.stderr
    assert json.loads((ws / "moe" / "init.json").read_text())["experts"] == ["dvgo-16"]
    # an expert still in training (pretrain interrupted: its checkpoint, no weights yet) is named too; it was not
    (ws / "checkpoints").mkdir(exist_ok=True)
    (ws / "checkpoints" / "dvgo-20.pt").write_bytes(b"a training state")
    proc = run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    assert "leaving out dvgo-20: still in training (checkpoints/dvgo-20.pt; rerun pretrain to finish it)" in \
        proc.stderr, proc.stderr


def test_a_file_in_the_way_of_the_checkpoints_folder_is_one_line(moe_ws, tmp_path):
    """WS/checkpoints made a file: `finetune --force` ended in a NotADirectoryError traceback, and a first finetune
    said "free disk space or fix the folder's permissions"."""
    ws = tmp_path / "ws"
    shutil.copytree(moe_ws, ws)
    shutil.rmtree(ws / "checkpoints", ignore_errors=True)
    (ws / "checkpoints").write_text("not a folder")
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--force", "--iters", "2", "--device", "cpu")
    assert_clean_failure(proc, "could not write", "a file or folder is in the way (at ", "move it")
    for f in (ws / "moe").glob("top2.*"):  # a model not finetuned yet: the first checkpoint cannot be written
        f.unlink()
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "2", "--iters", "2", "--device", "cpu")
    assert_clean_failure(proc, "could not write", "a file or folder is in the way (at ", "move it")
    # a folder where the finished model goes: named, not the temporary file the rename came from (gone by then)
    (ws / "checkpoints").unlink()
    (ws / "moe" / "top2.safetensors").mkdir()
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "2", "--iters", "2", "--device", "cpu")
    assert_clean_failure(proc, f"a file or folder is in the way (at {ws / 'moe' / 'top2.safetensors'}): move it")


def test_render_per_expert_and_gate_maps(moe_ws):
    import imageio.v3 as iio

    proc = run_cli("render", "--workspace", str(moe_ws), "--model", "top2", "--views", "1", "--per-expert",
                   "--device", "cpu", check=True)
    folder = moe_ws / "renders" / "top2" / "test"
    names = sorted(p.name for p in folder.glob("*.png"))
    # one line says what was written: the view's colour and depth, and 2 x 2 expert / gate images and a montage
    # (before: "top2: wrote 6 images", which counted neither the depth image nor apart the extra pictures)
    assert "top2: wrote 1 view (a colour and a 16-bit depth PNG each; and 5 per-expert and gate images)" in proc.stderr
    assert len(names) == 7
    stem = names[0].split(".")[0]
    for expected in (f"{stem}_expert0-dvgo-12.png", f"{stem}_expert1-dvgo-16.png", f"{stem}_gate0-dvgo-12.png",
                     f"{stem}_gate1-dvgo-16.png"):
        assert expected in names
    g0 = iio.imread(folder / f"{stem}_gate0-dvgo-12.png").astype(int)
    g1 = iio.imread(folder / f"{stem}_gate1-dvgo-16.png").astype(int)
    assert g0.shape == (32, 32, 3) and (g0[..., 0] == g0[..., 1]).all()  # greyscale
    acc_like = g0[..., 0] + g1[..., 0]  # probabilities sum to the pixel's opacity (<= 255 up to rounding)
    assert acc_like.max() <= 256
    # an earlier mixture's third expert (build-moe --experts changed them since): its images go (they
    # stayed beside the new mixture's)
    for kind in ("expert2", "gate2"):
        (folder / f"{stem}_{kind}-dvgo-20.png").write_bytes((folder / f"{stem}_gate1-dvgo-16.png").read_bytes())
    run_cli("render", "--workspace", str(moe_ws), "--model", "top2", "--views", "1", "--per-expert", "--device", "cpu",
            check=True)
    assert sorted(p.name for p in folder.glob("*.png")) == names


def test_render_expert_montage_and_comparison(moe_ws):
    import imageio.v3 as iio

    run_cli("render", "--workspace", str(moe_ws), "--model", "top1", "--views", "1", "--per-expert",
            "--device", "cpu", check=True)
    montages = list((moe_ws / "renders" / "top1" / "test").glob("*_experts.png"))
    assert len(montages) == 1 and iio.imread(montages[0]).shape[2] == 3
    # an expert has no shares or gate: said, not silently only its views (before: "wrote 1 images" and nothing else)
    proc = run_cli("render", "--workspace", str(moe_ws), "--model", "dvgo-12", "--views", "1", "--per-expert",
                   "--device", "cpu", check=True)
    assert "dvgo-12 is not a mixture, so --per-expert draws nothing more" in proc.stderr
    run_cli("render", "--workspace", str(moe_ws), "--compare", "--views", "2", "--device", "cpu", check=True)
    compared = sorted((moe_ws / "renders" / "compare" / "test").glob("*.png"))
    assert len(compared) == 2
    img = iio.imread(compared[0])
    # ground truth + baseline, top1, top2, ens: 5 panels of 32 px enlarged 6x (>= 192 px), 4 px gaps
    assert img.shape[1] == 5 * (32 * 6 + 4) + 4
    proc = run_cli("render", "--workspace", str(moe_ws), "--compare", "--per-expert")
    assert_clean_failure(proc, "one per command")


def test_render_orbit_video(moe_ws, tmp_path):
    import imageio.v3 as iio

    out = tmp_path / "orbit.mp4"
    run_cli("render", "--workspace", str(moe_ws), "--model", "top2", "--path", "orbit", "--frames", "3",
            "--video", str(out), "--device", "cpu", check=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["orbit.mp4", "orbit_depth.mp4"]  # the MP4 asked for
    for name in ("orbit.mp4", "orbit_depth.mp4"):
        frames = list(iio.imiter(tmp_path / name))
        assert len(frames) == 3 and frames[0].shape[:2] == (32, 32)
    proc = run_cli("render", "--workspace", str(moe_ws), "--path", "orbit", "--frames", "3")
    assert_clean_failure(proc, "--model NAME")
    proc = run_cli("render", "--workspace", str(moe_ws), "--video", str(out))
    assert_clean_failure(proc, "--path")


def test_a_video_killed_mid_write_leaves_no_temporary_file_once_the_workspace_is_used_again(moe_ws, tmp_path):
    """A render --path killed while writing its video leaves its temporary file (never the video); the next command
    on the workspace removes it, as it removes every killed writer's (it was left there for good)."""
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(moe_ws, ws, ignore=shutil.ignore_patterns("renders", "reports"))
    args = ["render", "--workspace", str(ws), "--model", "dvgo-12", "--path", "orbit", "--frames", "2",
            "--device", "cpu"]
    killed = run_cli(*args, env_extra={"BOOSTNERF_TEST_KILL": "write:orbit.mp4"})
    folder = ws / "renders" / "dvgo-12"
    assert killed.returncode == -9 and [p.name for p in folder.iterdir() if p.name.startswith(".orbit")], killed.stderr
    assert not (folder / "orbit.mp4").exists()
    run_cli(*args, check=True)
    assert sorted(p.name for p in folder.iterdir()) == ["orbit.mp4", "orbit_depth.mp4"]


def test_render_mp4_without_the_ffmpeg_backend_fails_in_one_line_and_writes_nothing(moe_ws, tmp_path, monkeypatch):
    """A user who asks for NAME.mp4 gets that file or an error, never a GIF under another name."""
    fake = tmp_path / "site"
    (fake / "imageio_ffmpeg").mkdir(parents=True)
    (fake / "imageio_ffmpeg" / "__init__.py").write_text('raise ImportError("simulated: imageio-ffmpeg missing")\n')
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(fake), *filter(None, [os.environ.get("PYTHONPATH")])]))
    out = tmp_path / "videos"
    out.mkdir()
    renders = sorted(p for p in (moe_ws / "renders").rglob("*")) if (moe_ws / "renders").exists() else []
    for video in ([ "--video", str(out / "o.mp4")], []):  # asked for, and the default WS/renders/top2/orbit.mp4
        proc = run_cli("render", "--workspace", str(moe_ws), "--model", "top2", "--path", "orbit", "--frames", "3",
                       *video, "--device", "cpu")
        assert_clean_failure(proc, "imageio-ffmpeg")
        assert len([ln for ln in proc.stderr.splitlines() if ln.strip()]) == 1, proc.stderr
    assert list(out.iterdir()) == []
    assert (sorted(p for p in (moe_ws / "renders").rglob("*")) if (moe_ws / "renders").exists() else []) == renders


@pytest.mark.parametrize("name", ["dvgo-16", "top1", "top2"])
def test_each_render_skip_only_drops_work_and_changes_pixels_by_at_most_its_threshold(moe_ws, name):
    """Skips on, each one off, all off: the same image (up to the colour threshold's dropped weights) from
    more and more evaluated samples."""
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.models import Skips, load_model, render_split
    from boostnerf_cli.workspace import Workspace

    ws = Workspace(moe_ws)
    scene = Survey(ws).scene()
    model = load_model(ws, name, "cpu")
    split = scene.split("test")
    out = {s: next(render_split(model, scene, split, "cpu", s, views=1))
           for s in (Skips(), Skips(empty=False), Skips(terminated=False), Skips.from_flags(no_skip=True))}
    on, no_empty, no_term, off = out.values()
    assert on["n_samples"] < no_empty["n_samples"] == off["n_samples"]  # the empty-space filter drops samples
    # (a barely trained tiny model may give every kept sample a weight above the threshold: <=, not <)
    assert on["n_color"] <= no_term["n_color"] <= off["n_color"] == off["n_samples"]  # all off: every sample
    samples_per_ray = off["n_samples"] / on["rgb"][..., 0].numel()
    # a dropped colour sample has weight <= 1e-4 and colour in [0, 1]: the pixel moves by at most their sum
    assert float((no_term["rgb"] - on["rgb"]).abs().max()) <= 1e-4 * samples_per_ray + 1e-6
    for other in (no_empty, off):
        # an expert's empty cell has alpha < 1e-4 per step; a mixture's V_D (the smallest expert's density, not
        # the mixture's) has alpha < T = 1e-3 there: small, not strictly bounded, on a barely trained model
        diff = (other["rgb"] - on["rgb"]).abs()
        assert float(diff.mean()) < 5e-3 and float(diff.max()) < 3e-2


def test_skip_flags_through_the_cli(moe_ws):
    run_cli("eval", "--workspace", str(moe_ws), "--model", "top1", "--views", "1", "--no-costs", "--skip-off",
            "terminated", "--report", "--device", "cpu", check=True)
    report = json.loads((moe_ws / "reports" / "eval.json").read_text())
    assert report["skips"] == {"empty": True, "terminated": False} and report["skip"] is False
    assert "skips only empty on" in (moe_ws / "reports" / "eval.md").read_text()
    proc = run_cli("render", "--workspace", str(moe_ws), "--skip-off", "floaters", "--device", "cpu")
    assert_clean_failure(proc, "empty, terminated")


def test_eval_costs_are_those_of_the_render_it_ran(moe_ws):
    """`eval --no-skip` renders every sample of the box through density and colour; its GFLOPs per image were those
    of the skipping render all the same (a probe's expert: 4.8x the samples, the same GFLOPs), while the row said
    skips all off. This tiny mixture's V_D keeps most of its box: 8% more samples."""
    rows = {}
    for flags in ((), ("--no-skip",)):
        run_cli("eval", "--workspace", str(moe_ws), "--model", "top1", "--views", "1", "--report", *flags,
                "--device", "cpu", check=True)
        rows[flags] = json.loads((moe_ws / "reports" / "eval.json").read_text())["models"][0]
    on, off = rows[()], rows[("--no-skip",)]
    assert off["samples_per_image"] > 1.05 * on["samples_per_image"], (on, off)
    assert off["gflops_per_image"] > 1.02 * on["gflops_per_image"], (on, off)
    assert off["params"] == on["params"]


def test_measure_costs_script_reports_every_measurement(moe_ws):
    """scripts/measure_costs.py (docs/benchmarks.md's cost targets) runs on a workspace and writes reports/costs.json;
    its timings are for docs/benchmarks.md, so only their presence and consistency are checked here."""
    from pathlib import Path

    root = Path(__file__).parent.parent
    script = root / "scripts" / "measure_costs.py"
    proc = run_script(script, "--workspace", str(moe_ws), "--views", "1", "--steps", "1", "--threads", "1",
                      timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    costs = json.loads((moe_ws / "reports" / "costs.json").read_text())
    rows = costs["skips"]["rows"]
    assert [(r["model"], r["skips"]) for r in rows] == [("dvgo-16", "on"), ("baseline", "on"), ("top1", "on"),
                                                        ("dvgo-16", "off")]
    assert costs["skips"]["speedup"] == pytest.approx(rows[-1]["seconds_per_image"] / rows[0]["seconds_per_image"])
    step = costs["step"]
    assert step["expert"] == "dvgo-16" and 0 < step["color_samples"] <= step["density_samples"]
    assert step["throughput_ratio"] == pytest.approx(step["bare_seconds"] / step["step_seconds"])
    assert costs["view"] is None  # a DVGO expert has no per-batch view to compare against the bare protocol
    mix = costs["mixture"]
    assert mix["mixture"] == "top1" and mix["topk"] == 1 and 0 < mix["color_samples"] <= mix["density_samples"]
    assert mix["overhead_seconds"] == pytest.approx(mix["gate_topk_aux_seconds"] + mix["dispatch_gather_seconds"])


def test_the_seconds_scripts_time_each_model_side_by_side(moe_ws, tmp_path):
    """scripts/render_profile.py (seconds per image and per part) and scripts/train_step_bench.py (seconds per
    finetuning step) run on a workspace and report every model asked for, the first the reference; their timings are
    for docs/performance.md, so only their presence and consistency are checked here."""
    from pathlib import Path

    scripts = Path(__file__).parent.parent / "scripts"
    out = tmp_path / "render.json"
    proc = run_script(scripts / "render_profile.py", "-w", str(moe_ws), "--model", "baseline", "--model", "top1",
                      "--views", "1", "--repeats", "1", "--json", str(out), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    assert [r["model"] for r in rows] == ["baseline", "top1"] and rows[0]["seconds_ratio"] == 1.0
    assert all(r["seconds"] > 0 and r["gflops"] > 0 for r in rows)
    assert {"routing", "dispatch", "expert 0"} <= set(rows[1]["ms"]) and "routing" not in rows[0]["ms"]
    out = tmp_path / "steps.json"
    proc = run_script(scripts / "train_step_bench.py", "-w", str(moe_ws), "--model", "baseline", "--model", "top1",
                      "--steps", "1", "--rounds", "2", "--warmup", "1", "--json", str(out), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    assert [r["model"] for r in rows] == ["baseline", "top1"] and rows[0]["vs"] == 1.0
    assert all(r["seconds_per_step"] > 0 and r["cpu_seconds_per_step"] > 0 and r["samples_per_ray"] > 0 for r in rows)


def _without_top1(moe_ws, folder):
    """A copy of the built workspace at folder/ws with no top1 model in it."""
    ws = folder / "ws"
    shutil.copytree(moe_ws, ws)
    for p in (ws / "moe").glob("top1.*"):
        p.unlink()
    return ws


def _finetune_top1(moe_ws, folder, *flags):
    ws = _without_top1(moe_ws, folder)
    run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--iters", "200", *flags, "--device", "cpu", check=True)
    return json.loads((ws / "moe" / "top1.json").read_text())


@pytest.mark.slow
def test_finetuning_learns_and_the_resolution_penalty_moves_load_to_the_small_expert(moe_ws, tmp_path):
    """Measured: loss 0.028 over steps 10-50 -> 0.016 over steps 160-200 with the geometric penalty,
    0.024 -> 0.013 with none (one batch a logged step, so five are averaged; over 100 steps and three batches the
    fall, 0.84x, was inside the batches' spread once near / far came from the cameras); the smallest expert's share
    of samples 0.68 with the geometric penalty against 0.51 with none (same lambda 1). Without the auxiliary loss
    (lambda 0) this tiny Top-1 collapses onto one expert (the smallest here, share 1.0), so the share is compared
    between penalties at equal lambda: the weighting w_i, not lambda alone, is what prefers the cheap expert."""
    weighted = _finetune_top1(moe_ws, tmp_path / "geometric", "--lambda", "1", "--penalty", "geometric")
    flat = _finetune_top1(moe_ws, tmp_path / "none", "--lambda", "1", "--penalty", "none")
    for report in (weighted, flat):
        losses = [h["loss"] for h in report["history"]]
        assert len(losses) == 20 and sum(losses[-5:]) < 0.75 * sum(losses[:5]), losses  # training lowers the loss
    assert weighted["penalty"] == "geometric" and flat["penalty"] == "none"
    assert weighted["load"][0] > flat["load"][0] + 0.05, (weighted["load"], flat["load"])


def test_a_finished_model_asked_for_with_other_settings_is_refused_not_skipped(moe_ws, tmp_path):
    """`finetune --topk 2 --no-renormalize` (or another --lambda, --iters, --seed) over a finished top2 said "already
    finetuned, skipping" and exited 0: a script got the old model, whose report still said renormalize true. pretrain
    refuses the same case; so does finetune now, for every model. The same settings still skip."""
    ws = tmp_path / "ws"
    shutil.copytree(moe_ws, ws)
    for model, flags, key in ((["--topk", "1"], ["--no-renormalize"], "(moe.renormalize: True, now False)"),
                              (["--topk", "2"], ["--lambda", "0.5"], "(moe.lam: 0.001, now 0.5)"),
                              (["--topk", "1"], ["--iters", "3"], "(moe.iters: 20, now 3)"),
                              (["--ensemble"], ["--seed", "5"], "(moe.seed: 0, now 5)"),
                              (["--baseline"], ["--iters", "3"], "(moe.iters: 20, now 3)")):
        proc = run_cli("finetune", "--workspace", str(ws), *model, *flags, "--device", "cpu")
        assert_clean_failure(proc, "was finetuned with other settings", key, "--force")
    before = {p.name: p.stat().st_mtime_ns for p in (ws / "moe").iterdir()}
    # the same settings skip, and so do settings that cannot change the model (ignored, so not refused: the
    # ensemble's lambda and penalty, renormalising at k = M, which is top2 here)
    for model in (["--topk", "1"], ["--topk", "2"], ["--ensemble"], ["--baseline"], ["--ensemble", "--lambda", "0.5"],
                  ["--ensemble", "--penalty", "linear"], ["--topk", "2", "--no-renormalize"]):
        proc = run_cli("finetune", "--workspace", str(ws), *model, "--device", "cpu", check=True)
        assert "already finetuned, skipping" in proc.stderr, (model, proc.stderr)
    assert {p.name: p.stat().st_mtime_ns for p in (ws / "moe").iterdir()} == before
    # with --force the new settings train, and a rerun with them skips
    run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--no-renormalize", "--iters", "2", "--force",
            "--device", "cpu", check=True)
    assert json.loads((ws / "moe" / "top1.json").read_text())["renormalize"] is False
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--no-renormalize", "--iters", "2",
                   "--device", "cpu", check=True)
    assert "already finetuned, skipping" in proc.stderr


def test_options_that_cannot_change_a_model_are_named(moe_ws, tmp_path):
    """--penalty or --lambda on the ensemble or the baseline, or --no-renormalize at k = M, were dropped without a word
    (the report recorded the defaults)."""
    ws = tmp_path / "ws"
    shutil.copytree(moe_ws, ws, ignore=shutil.ignore_patterns("top*", "ens*", "baseline*"))
    proc = run_cli("finetune", "--workspace", str(ws), "--ensemble", "--lambda", "2", "--penalty", "1,2",
                   "--iters", "2", "--device", "cpu", check=True)
    assert "note: --lambda, --penalty cannot change ens (every expert is used with equal weights)" in proc.stderr
    proc = run_cli("finetune", "--workspace", str(ws), "--baseline", "--lambda", "3", "--no-renormalize",
                   "--iters", "2", "--device", "cpu", check=True)
    assert "note: --lambda, --no-renormalize cannot change the baseline" in proc.stderr
    # a finished model skipped says it too (docs/stages.md): it only said "already finetuned, skipping"
    proc = run_cli("finetune", "--workspace", str(ws), "--baseline", "--lambda", "3", "--no-renormalize",
                   "--iters", "2", "--device", "cpu", check=True)
    assert "already finetuned, skipping" in proc.stderr
    assert "note: --lambda, --no-renormalize cannot change the baseline" in proc.stderr
    proc = run_cli("finetune", "--workspace", str(ws), "--ensemble", "--penalty", "1,2", "--iters", "2",
                   "--device", "cpu", check=True)
    assert "already finetuned, skipping" in proc.stderr and "note: --penalty cannot change ens" in proc.stderr
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "2", "--lambda", "0.5", "--no-renormalize",
                   "--iters", "2", "--device", "cpu", check=True)  # two experts: k = M
    assert "note: --no-renormalize cannot change top2 (at k = M every expert is used)" in proc.stderr
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--no-renormalize", "--lambda", "0.1",
                   "--iters", "2", "--device", "cpu", check=True)
    assert "note:" not in proc.stderr


def test_a_density_volume_too_coarse_to_keep_a_cell_names_moe_vd_res(trained_ws, tmp_path):
    """With moe.vd_res 1 the V_D error blamed the threshold and the experts' training only; the cause was the
    volume's two vertices per axis, which read the expert's density at the box's corners."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("moe", "reports", "renders"))
    recipe = make_recipe(tmp_path / "vd1.yaml", moe={"vd_res": 1})
    proc = run_cli("build-moe", "--workspace", str(ws), "--recipe", str(recipe), "--device", "cpu")
    assert_clean_failure(proc, "keeps no cell", "raise moe.vd_res (= 1")


def test_a_damaged_moe_init_is_one_line_when_a_finished_model_is_checked(moe_ws, tmp_path):
    """The check of a finished model's settings read moe/init's mixture settings without a guard: an init whose
    metadata a hand edit or another boostnerf left without a known field ended in a TypeError traceback."""
    from boostnerf_cli.workspace import load_tensors

    ws = tmp_path / "ws"
    shutil.copytree(moe_ws, ws)
    path = ws / "moe" / "init.safetensors"
    tensors, meta = load_tensors(path)
    meta = {k: v for k, v in meta.items() if k not in ("format_version", "digest")}
    meta["mixture"] = {**meta["mixture"], "an_unknown_field": 1}
    save_tensors(path, tensors, meta)  # the same tensors: the same digest, so the models made from it are current
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "2", "--device", "cpu")
    assert_clean_failure(proc, "does not hold a valid mixture", "build-moe")


def test_build_moe_keeps_a_mixture_of_the_same_settings_and_says_what_a_rebuild_leaves_stale(mixture_ws, tmp_path):
    """build-moe decides through `decide`: the same experts and settings keep moe/init as it is (its file untouched,
    the mixtures finetuned from it current); other settings build it again, saying what changed and which finetuned
    models that leaves stale."""
    ws = tmp_path / "ws"
    shutil.copytree(mixture_ws, ws)
    init = ws / "moe" / "init.safetensors"
    before = init.stat().st_mtime_ns
    w = ["--workspace", str(ws), "--device", "cpu"]
    proc = run_cli("build-moe", *w, check=True)
    assert "moe/init: already built from these experts with these settings, kept as it is" in proc.stderr
    assert init.stat().st_mtime_ns == before
    run_cli("eval", "--model", "top2", "--views", "1", "--no-costs", *w, check=True)  # still current
    proc = run_cli("build-moe", "--gate-res", "6", *w, check=True)
    assert "moe/init: building it again (moe.gate_res: 8, now 6)" in proc.stderr, proc.stderr
    assert "top2, finetuned from the old one, will be stale: finetune it again with --force" in proc.stderr
    assert_clean_failure(run_cli("eval", "--model", "top2", *w), "top2 is stale", "--topk 2 --force")
