"""The staged pipeline through the real CLI: artifacts, reports, resumable stages, bad input."""

import json
import logging
import shutil

import pytest
import torch
from conftest import PSNR_MARGIN, TINY_PSNR, assert_clean_failure, cli_in_process, make_recipe, no_temp_files, run_cli
from helpers import write_lpips_weights
from safetensors import safe_open

from boostnerf_cli.lineage import Survey
from boostnerf_cli.metrics import ALEXNET_ENV, LPIPS_ENV
from boostnerf_cli.scenes import make_scene
from boostnerf_cli.workspace import FORMAT_VERSION, read_meta


def test_pretrain_writes_experts_reports_and_manifest(trained_ws):
    for name in ("dvgo-12", "dvgo-16"):
        path = trained_ws / "experts" / f"{name}.safetensors"
        with safe_open(str(path), framework="pt") as f:
            meta = json.loads(f.metadata()["boostnerf"])
        assert meta["family"] == "dvgo" and meta["config"]["res"] == int(name.split("-")[1])
        report = json.loads((trained_ws / "experts" / f"{name}.json").read_text())
        # the seed, in the report too
        assert report["name"] == name and report["iterations"] == 30 and report["seed"] == 0
        assert report["seconds"] > 0 and report["params"] > 0
        assert report["test_psnr"] >= TINY_PSNR[name] - PSNR_MARGIN, (name, report["test_psnr"])
    manifest = json.loads((trained_ws / "manifest.json").read_text())
    assert manifest["scene"]["splits"]["train"]["views"] == 12
    assert manifest["recipe"]["pretrain"]["res"] == [12, 16]
    assert not (trained_ws / "checkpoints").exists() or not list((trained_ws / "checkpoints").iterdir())
    assert no_temp_files(trained_ws)


def test_the_psnr_references_fail_broken_models(trained_ws):
    """The whole-run PSNR check can fail: the trained dvgo-16 passes it, the same model with its colour MLP
    zeroed fails it, and so does the model scored against the test images in the wrong order."""
    import dataclasses

    import torch

    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.models import load_model
    from boostnerf_cli.stages.evaluate import evaluate_model
    from boostnerf_cli.workspace import Workspace

    ws = Workspace(trained_ws)
    scene = Survey(ws).scene()
    test = scene.split("test")
    floor = TINY_PSNR["dvgo-16"] - PSNR_MARGIN
    model = load_model(ws, "dvgo-16", "cpu")
    assert evaluate_model(model, scene, test, "cpu", None)["psnr"] >= floor
    shuffled = dataclasses.replace(test, images=test.images.roll(1, 0))
    assert evaluate_model(model, scene, shuffled, "cpu", None)["psnr"] < floor
    with torch.no_grad():
        for p in model.field.rgbnet.parameters():
            p.zero_()
    assert evaluate_model(model, scene, test, "cpu", None)["psnr"] < floor


def test_pretrain_skips_finished_experts(trained_ws, tiny_scene, tiny_recipe, tmp_path):
    ws = tmp_path / "ws"  # a copy: a rerun records its recipe (--res 12), which later copies of trained_ws would reuse
    shutil.copytree(trained_ws, ws)
    before = (ws / "experts" / "dvgo-12.safetensors").stat().st_mtime_ns
    proc = run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace",
                   str(ws), "--device", "cpu", "--res", "12", check=True)
    assert "already trained" in proc.stderr
    assert (ws / "experts" / "dvgo-12.safetensors").stat().st_mtime_ns == before
    # another holdout_every: the refusal names it ("another scene, image size or box")
    assert_clean_failure(run_cli("pretrain", "--workspace", str(ws), "--holdout-every", "4", "--device", "cpu"),
                         "held-out views (holdout_every) 8, now 4")


def test_a_finished_expert_is_not_skipped_under_other_training_settings(tmp_path, tiny_scene, tiny_recipe):
    """pretrain skips a finished expert only when the recipe would train it the same way; otherwise one line says
    which setting differs (it said "already trained, skipping" and recorded the new recipe in the manifest, which
    later stages reuse, beside experts trained with the old one). A setting that trains nothing the same way
    (log_every) still skips."""
    ws = tmp_path / "ws"
    args = ["pretrain", "--data", str(tiny_scene), "--workspace", str(ws), "--device", "cpu", "--res", "12"]
    run_cli(*args, "--recipe", str(tiny_recipe), check=True)
    manifest = (ws / "manifest.json").read_text()
    more = make_recipe(tmp_path / "more.yaml", pretrain={"iters": 50})
    assert_clean_failure(run_cli(*args, "--recipe", str(more)), "dvgo-12 was trained with other settings",
                         "iters: 30, now 50", "--force")
    assert (ws / "manifest.json").read_text() == manifest
    quiet = make_recipe(tmp_path / "quiet.yaml", pretrain={"train": {"log_every": 7}})
    assert "already trained" in run_cli(*args, "--recipe", str(quiet), check=True).stderr
    # every setting that shapes the expert is compared, named by its recipe key: its seed, its architecture (the
    # family's options, defaults filled in)
    manifest = (ws / "manifest.json").read_text()
    assert_clean_failure(run_cli(*args, "--recipe", str(quiet), "--seed", "5"), "pretrain.seed: 0, now 5")
    wider = make_recipe(tmp_path / "wider.yaml", pretrain={"dvgo": {"hidden": 32}})
    assert_clean_failure(run_cli(*args, "--recipe", str(wider)), "pretrain.dvgo.hidden: 16, now 32")
    assert (ws / "manifest.json").read_text() == manifest
    assert "already trained" in run_cli(*args, "--recipe", str(quiet), check=True).stderr


@pytest.mark.slow
def test_a_changed_geometry_setting_is_refused_and_its_experts_are_then_stale(trained_ws, tiny_scene, tmp_path):
    """The geometry is an artifact like the experts: its file keeps its signature, a changed geometry setting is
    refused in one line naming it (pretrain kept the old geometry, said "already trained" of the experts built on it,
    and said nothing), --force retrains it, and an expert still built on the old one is stale: pretrain, build-moe
    and eval say so, with the command that trains it again."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    geometry = ws / "experts" / "geometry.safetensors"
    before = read_meta(geometry)["digest"]
    assert read_meta(geometry)["signature"]["settings"]["iters"] == 100
    shorter = make_recipe(tmp_path / "shorter.yaml", pretrain={"geometry": {"iters": 60}})
    args = ["pretrain", "--data", str(tiny_scene), "--workspace", str(ws), "--device", "cpu", "--recipe", str(shorter)]
    assert_clean_failure(run_cli(*args), "geometry was trained with other settings",
                         "pretrain.geometry.iters: 100, now 60", "--force")
    assert read_meta(geometry)["digest"] == before
    proc = run_cli(*args, "--res", "12", "--force", check=True)
    assert "geometry: training a 12^3 coarse grid for 60 steps" in proc.stderr
    assert read_meta(geometry)["digest"] != before
    assert "dvgo-16 is stale" in proc.stderr and "--res 16 --force" in proc.stderr  # said when it goes stale
    remedy = f"`boostnerf pretrain -w {ws} --model dvgo --res 16 --force`"
    for again in (run_cli(*args), run_cli("build-moe", "-w", str(ws), "--device", "cpu"),
                  run_cli("eval", "-w", str(ws), "--device", "cpu", "--no-costs")):
        assert_clean_failure(again, "dvgo-16 is stale: the geometry was retrained after dvgo-16 was trained on it",
                             remedy)
    run_cli(*args, "--res", "16", "--force", check=True)
    assert "already trained" in run_cli(*args, check=True).stderr  # both experts on the new geometry: current


def test_an_expert_copied_from_another_scene_s_workspace_is_said_to_be_of_another_scene(trained_ws, tmp_path,
                                                                                        tiny_recipe):
    """An expert file copied in from a workspace of another scene was said to be stale because "the geometry was
    retrained after it was trained on it", which sends the user looking for a retraining that never happened."""
    from boostnerf_cli.scenes import make_scene

    other = make_scene(tmp_path / "other-scene", size=32, n_train=12, n_test=3, seed=5)
    ws = tmp_path / "ws"
    run_cli("pretrain", "--data", str(other), "--recipe", str(tiny_recipe), "--workspace", str(ws), "--res", "12",
            "--device", "cpu", check=True)
    for suffix in (".safetensors", ".json"):
        shutil.copy(trained_ws / "experts" / f"dvgo-16{suffix}", ws / "experts" / f"dvgo-16{suffix}")
    proc = run_cli("eval", "-w", str(ws), "--model", "dvgo-16", "--device", "cpu", "--no-costs")
    assert_clean_failure(proc, "dvgo-16 is stale: it was trained on another scene than this workspace's",
                         f"`boostnerf pretrain -w {ws} --model dvgo --res 16 --force`")


def test_an_unknown_model_among_several_is_refused_before_any_is_rendered(mixture_ws):
    """eval, render and count-params with `--model top2 --model nosuch` rendered top2 through, then failed."""
    for command in ("eval", "render", "count-params"):
        proc = run_cli(command, "-w", str(mixture_ws), "--model", "top2", "--model", "nosuch", "--device", "cpu")
        assert_clean_failure(proc, "no model named 'nosuch'")
        assert "top2:" not in proc.stderr, proc.stderr  # nothing said of top2's work: none was done


def test_eval_report_schema_and_render_outputs(trained_ws, tmp_path):
    missing = {ALEXNET_ENV: str(tmp_path / "none" / "alexnet-owt-7be5be79.pth"), LPIPS_ENV: str(tmp_path / "alex.pth")}
    run_cli("eval", "--workspace", str(trained_ws), "--split", "test", "--report", "--device", "cpu", check=True,
            env_extra=missing)
    report = json.loads((trained_ws / "reports" / "eval.json").read_text())
    assert report["split"] == "test"
    names = [m["name"] for m in report["models"]]
    assert names == ["dvgo-12", "dvgo-16"]
    for m in report["models"]:
        assert set(m) >= {"name", "psnr", "ssim", "lpips", "seconds_per_image"}
        assert 0 < m["ssim"] <= 1 and m["seconds_per_image"] > 0
        assert m["psnr"] >= TINY_PSNR[m["name"]] - PSNR_MARGIN, (m["name"], m["psnr"])
        assert m["lpips"] is None
    assert ALEXNET_ENV in report["lpips_note"] and missing[ALEXNET_ENV] in report["lpips_note"]

    proc = run_cli("render", "--workspace", str(trained_ws), "--model", "dvgo-16", "--views", "2", "--device", "cpu",
                   check=True)
    import imageio.v3 as iio

    pngs = sorted((trained_ws / "renders" / "dvgo-16" / "test").glob("*.png"))
    assert len(pngs) == 4  # 2 colour + 2 depth
    # stdout lists the colour images written, one per line, for a script (nothing was on stdout)
    assert sorted(proc.stdout.splitlines()) == [str(p) for p in pngs if "depth" not in p.name], proc.stdout
    rgb = iio.imread([p for p in pngs if "depth" not in p.name][0])
    depth = iio.imread([p for p in pngs if "depth" in p.name][0])
    assert rgb.shape == (32, 32, 3) and depth.dtype.name == "uint16"
    # a path with two models: the refusal names them (it said "add --model NAME" to a user who had given two)
    proc = run_cli("render", "--workspace", str(trained_ws), "--path", "orbit", "--model", "dvgo-12", "--model",
                   "dvgo-16", "--device", "cpu")
    assert_clean_failure(proc, "--path renders one model: keep one of dvgo-12, dvgo-16")


def test_eval_reports_lpips_when_its_weights_are_on_disk(trained_ws, tmp_path):
    """The LPIPS branch of eval, with a random LPIPS model's weights in the reference file layouts: the report holds
    the mean distance over the views, computed with the model the files hold (the same figure as the in-memory
    model gives, and not the distance of a model with other weights)."""
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.metrics import LPIPSModel, lpips
    from boostnerf_cli.models import load_model, render_split
    from boostnerf_cli.workspace import Workspace

    env = write_lpips_weights(tmp_path, seed=3)
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    run_cli("eval", "--workspace", str(ws), "--model", "dvgo-16", "--views", "2", "--report", "--device", "cpu",
            check=True, env_extra=env)
    report = json.loads((ws / "reports" / "eval.json").read_text())
    assert report["lpips_note"] is None
    (row,) = report["models"]
    assert isinstance(row["lpips"], float) and row["lpips"] > 0
    scene = Survey(Workspace(ws)).scene()
    test = scene.split("test")
    model = load_model(Workspace(ws), "dvgo-16", "cpu")
    renders = [r["rgb"] for r in render_split(model.for_rendering(), scene, test, "cpu", views=2)]
    models = {seed: LPIPSModel.random(seed=seed) for seed in (3, 4)}
    direct = {seed: sum(lpips(r, test.images[i], m) for i, r in enumerate(renders)) / 2 for seed, m in models.items()}
    assert row["lpips"] == pytest.approx(direct[3], abs=2e-5)
    assert abs(direct[4] - direct[3]) > 1e-3  # another model's distance differs: the figure is the files' model's



def test_images_too_small_for_ssim_leave_it_out_with_a_note(tmp_path, tiny_scene,
                                                                                                 tiny_recipe):
    """SSIM's window is 11 px: at --image-size 8 (which pretrain accepts) eval stopped with `error: ssim: image 8x8 is
    smaller than the 11x11 window` after rendering, and wrote no report. Now SSIM is null with a note, as LPIPS under
    31 px, and the tables print `-` for it."""
    from boostnerf_cli.stages.evaluate import markdown_table

    ws = tmp_path / "ws"
    run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace", str(ws),
            "--device", "cpu", "--res", "12", "--image-size", "8", check=True)
    proc = run_cli("eval", "--workspace", str(ws), "--report", "--no-costs", "--device", "cpu", check=True)
    report = json.loads((ws / "reports" / "eval.json").read_text())
    (row,) = report["models"]
    assert row["ssim"] is None and row["psnr"] > 5
    assert "11 px" in report["ssim_note"] and "8 x 8" in report["ssim_note"] and "8 x 8" in proc.stderr
    assert "SSIM left out" in (ws / "reports" / "eval.md").read_text()
    table = markdown_table(report)
    assert f"| dvgo-12 | {row['psnr']:.3f} | - |" in table and "LPIPS: LPIPS" not in table


def test_images_too_small_for_lpips_leave_it_out_with_a_note_not_the_whole_table(tmp_path, tiny_scene, tiny_recipe):
    """AlexNet needs 31 px a side: at --image-size 24 eval reports PSNR and SSIM, LPIPS null and why (it stopped
    with `error: lpips: need ... H, W >= 31` after the first model's costs, and wrote no table)."""
    ws = tmp_path / "ws"
    run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace", str(ws),
            "--device", "cpu", "--res", "12", "--image-size", "24", check=True)
    proc = run_cli("eval", "--workspace", str(ws), "--report", "--no-costs", "--device", "cpu", check=True,
                   env_extra=write_lpips_weights(tmp_path))
    report = json.loads((ws / "reports" / "eval.json").read_text())
    (row,) = report["models"]
    assert row["lpips"] is None and row["psnr"] > 5
    assert "31" in report["lpips_note"] and "24 x 24" in report["lpips_note"] and "24 x 24" in proc.stderr


def test_pretrain_without_data_reruns_on_the_workspace_s_own_scene_and_never_generates_one(trained_ws, tmp_path,
                                                                                          tiny_scene, tiny_recipe):
    """`--data` left out on a workspace made for a real scene: the rerun uses that scene, as it reuses the recorded
    recipe (it was refused as "made for another scene"; earlier still, a procedural scene was generated into WS/scene
    first). That scene gone: one line saying so and how to point to it, and still nothing generated."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    proc = run_cli("pretrain", "--workspace", str(ws), "--recipe", str(tiny_recipe), "--device", "cpu", check=True)
    assert ("already trained, skipping" in proc.stderr and "] step " not in proc.stderr
            and "generating" not in proc.stderr)
    manifest = json.loads((ws / "manifest.json").read_text())
    assert manifest["data"]["path"] == str(tiny_scene)
    manifest["data"]["path"] = str(tmp_path / "gone")
    (ws / "manifest.json").write_text(json.dumps(manifest))
    proc = run_cli("pretrain", "--workspace", str(ws), "--device", "cpu")
    assert_clean_failure(proc, f"the workspace's scene {tmp_path / 'gone'} is gone", "--data NEW_PLACE")
    assert not (ws / "scene").exists() and "generating" not in proc.stderr


def test_a_moved_scene_or_workspace_is_followed_not_retrained(trained_ws, tmp_path, tiny_scene):
    """A scene inside the workspace (the generated default one) is recorded relative to it, so a renamed or copied
    workspace keeps working; a scene that moved is pointed to once with `pretrain --data NEW` (the same images and
    cameras: nothing retrains). Before: the resolved absolute path was part of the scene's identity, so a renamed
    demo workspace said its scene "is gone" while it sat inside it, and `--data NEW` was refused as another scene."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    shutil.copytree(tiny_scene, ws / "scene")
    digests = {p.name: read_meta(p)["digest"] for p in (ws / "experts").glob("*.safetensors")}
    proc = run_cli("pretrain", "--workspace", str(ws), "--data", str(ws / "scene"), "--device", "cpu", check=True)
    assert f"note: the workspace's scene is now {ws / 'scene'} (it was {tiny_scene}; " in proc.stderr, proc.stderr
    assert "already trained, skipping" in proc.stderr and "step" not in proc.stderr
    assert json.loads((ws / "manifest.json").read_text())["data"]["path"] == "scene"
    moved = tmp_path / "renamed"
    ws.rename(moved)
    run_cli("count-params", "--workspace", str(moved), "--device", "cpu", check=True)  # the scene travelled with it
    away = tmp_path / "elsewhere"
    (moved / "scene").rename(away)
    assert_clean_failure(run_cli("eval", "--workspace", str(moved), "--no-costs", "--device", "cpu"),
                         "is gone", f"pretrain --workspace {moved} --data NEW_PLACE")
    run_cli("pretrain", "--workspace", str(moved), "--data", str(away), "--device", "cpu", check=True)
    run_cli("eval", "--workspace", str(moved), "--no-costs", "--device", "cpu", check=True)
    assert {p.name: read_meta(p)["digest"] for p in (moved / "experts").glob("*.safetensors")} == digests
    # a `scene` folder of another scene left inside, the recorded one moved again (the leftover
    # was blamed, "changed since pretrain: retrain ... --data WS/scene --force")
    make_scene(moved / "scene", size=32, n_train=12, n_test=3, seed=1)
    away.rename(tmp_path / "elsewhere-2")
    assert_clean_failure(run_cli("eval", "--workspace", str(moved), "--no-costs", "--device", "cpu"),
                         f"the workspace's scene {away} is gone", "--data NEW_PLACE")
    (tmp_path / "elsewhere-2").rename(away)
    shutil.rmtree(moved / "scene")
    other = make_scene(tmp_path / "other", size=32, n_train=12, n_test=3, seed=1)  # another scene: still refused
    assert_clean_failure(run_cli("pretrain", "--workspace", str(moved), "--data", str(other), "--device", "cpu"),
                         "is not the one this workspace was trained on", "--force")


def test_a_rerun_of_pretrain_keeps_the_recorded_recipe_and_names_it_when_it_is_damaged(trained_ws, tmp_path):
    """pretrain without --recipe reuses the workspace's recorded recipe, flags included: --no-skip given once stays,
    and --skip (new: --no-skip had no opposite) turns it back on; a recorded recipe that no longer loads is named with
    its file and the way around it (it said `unknown recipe key ...` about no file the user gave)."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    run_cli("pretrain", "--workspace", str(ws), "--res", "8", "--iters", "2", "--no-skip", "--device", "cpu",
            check=True)  # no --data either: the workspace's scene
    proc = run_cli("pretrain", "--workspace", str(ws), "--res", "10", "--iters", "2", "--device", "cpu", check=True)
    assert "pretrain.skip is off (--no-skip)" in proc.stderr
    assert json.loads((ws / "experts" / "dvgo-10.json").read_text())["skip"] is False
    proc = run_cli("pretrain", "--workspace", str(ws), "--res", "12", "--iters", "30", "--skip", "--device", "cpu",
                   check=True)  # --iters 2 was recorded too
    assert "skip is off" not in proc.stderr and "dvgo-12: already trained, skipping" in proc.stderr  # as trained
    manifest = json.loads((ws / "manifest.json").read_text())
    manifest["recipe"]["pretrain"]["old_key"] = 1
    (ws / "manifest.json").write_text(json.dumps(manifest))
    proc = run_cli("pretrain", "--workspace", str(ws), "--device", "cpu")
    assert_clean_failure(proc, f"the recipe recorded in {ws / 'manifest.json'}", "old_key", "--recipe FILE")


def test_views_of_one_name_in_different_folders_render_to_different_files(tmp_path, tiny_scene, tiny_recipe):
    """Frames `test/a/r_0` and `test/b/r_0` (a capture with one folder per camera) render to two files each, not
    one file written twice: render, --compare and --per-expert name files by the shortest unique path suffix."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    meta = json.loads((scene / "transforms_test.json").read_text())
    for i, frame in enumerate(meta["frames"]):  # 3 views: test/a/r_0, test/b/r_0, test/a/r_1
        sub = "ab"[i % 2]
        (scene / "test" / sub).mkdir(exist_ok=True)
        old = scene / (frame["file_path"] + ("" if frame["file_path"].endswith(".png") else ".png"))
        old.rename(scene / "test" / sub / f"r_{i // 2}.png")
        frame["file_path"] = f"./test/{sub}/r_{i // 2}.png"
    (scene / "transforms_test.json").write_text(json.dumps(meta))
    ws = tmp_path / "ws"
    run_cli("pretrain", "--data", str(scene), "--recipe", str(tiny_recipe), "--workspace", str(ws), "--device", "cpu",
            "--res", "12", check=True)
    proc = run_cli("render", "--workspace", str(ws), "--device", "cpu", check=True)
    assert "wrote 3 views" in proc.stderr
    names = sorted(p.name for p in (ws / "renders" / "dvgo-12" / "test").glob("*.png") if "depth" not in p.name)
    assert names == ["a_r_0.png", "a_r_1.png", "b_r_0.png"], names


def test_a_view_of_empty_sky_scores_an_infinite_psnr_that_the_reports_write_as_null(tmp_path, tiny_scene, tiny_recipe):
    """Every test camera turned round to look away from the scene, with a transparent image: each render is the
    white background, exactly as its image, so the PSNR is inf. The reports held Python's `Infinity`, which is not
    JSON (jq 1.6 read it as 1.8e308); now they hold null, and the tables print "-"."""
    import imageio.v3 as iio
    import numpy as np

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    meta = json.loads((scene / "transforms_test.json").read_text())
    for frame in meta["frames"]:
        for row in frame["transform_matrix"][:3]:  # half a turn about the camera's up axis, in place
            row[0], row[2] = -row[0], -row[2]
        iio.imwrite(scene / f"{frame['file_path']}.png", np.zeros((32, 32, 4), np.uint8))
    (scene / "transforms_test.json").write_text(json.dumps(meta))

    def strict(path):
        return json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{path} holds {c}: not JSON"))

    ws = tmp_path / "ws"
    run_cli("pretrain", "--data", str(scene), "--recipe", str(tiny_recipe), "--workspace", str(ws), "--device", "cpu",
            check=True)
    for name in ("dvgo-12", "dvgo-16"):
        report = strict(ws / "experts" / f"{name}.json")
        assert report["test_psnr"] is None and report["train_psnr"] > 10
    proc = run_cli("eval", "--workspace", str(ws), "--report", "--device", "cpu", check=True)
    rows = {r["name"]: r for r in strict(ws / "reports" / "eval.json")["models"]}
    assert rows["dvgo-16"]["psnr"] is None and rows["dvgo-16"]["ssim"] == pytest.approx(1.0)
    assert "| dvgo-16 | inf | 1.0000 |" in (ws / "reports" / "eval.md").read_text()  # what this run computed
    assert "inf" in proc.stdout
    rerun = run_cli("pretrain", "--data", str(scene), "--recipe", str(tiny_recipe), "--workspace", str(ws),
                    "--device", "cpu", check=True)  # finished: its table is read back from the reports
    assert "inf" not in rerun.stdout and [line for line in rerun.stdout.splitlines()
                                          if "dvgo-16" in line and " - " in line]


def test_missing_data_path(tmp_path):
    proc = run_cli("pretrain", "--data", str(tmp_path / "nope"), "--workspace", str(tmp_path / "ws"))
    assert_clean_failure(proc, "does not exist")
    assert not (tmp_path / "ws" / "experts").exists()


def test_transforms_naming_a_missing_image(tmp_path, tiny_scene, tiny_recipe):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    victim = sorted((scene / "train").glob("*.png"))[0]
    victim.unlink()
    proc = run_cli("pretrain", "--data", str(scene), "--recipe", str(tiny_recipe), "--workspace", str(tmp_path / "ws"))
    assert_clean_failure(proc, "not found", victim.stem)
    assert not (tmp_path / "ws" / "experts").exists() and no_temp_files(tmp_path)


def test_corrupt_png(tmp_path, tiny_scene, tiny_recipe):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    victim = sorted((scene / "train").glob("*.png"))[3]
    victim.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    proc = run_cli("pretrain", "--data", str(scene), "--recipe", str(tiny_recipe), "--workspace", str(tmp_path / "ws"))
    assert_clean_failure(proc, victim.name)
    assert not (tmp_path / "ws" / "experts").exists()


def test_a_scene_that_shows_only_its_background_is_one_line_and_writes_nothing(tmp_path, tiny_recipe):
    """`make-scene --content empty`: every training pixel is the background (as with an all-transparent alpha
    channel). Before the check the geometry stage found no surface, said "too few geometry.iters?", marked the
    whole box occupied and trained experts to an infinite PSNR; now pretrain refuses before writing anything."""
    from boostnerf_cli.scenes import make_scene

    scene = make_scene(tmp_path / "scene", size=32, n_train=6, n_test=1, content="empty")
    ws = tmp_path / "ws"
    proc = run_cli("pretrain", "--data", str(scene), "--recipe", str(tiny_recipe), "--workspace", str(ws),
                   "--device", "cpu")
    assert_clean_failure(proc, "6 training views", "nothing but the background", "alpha")
    assert not ws.exists() and no_temp_files(tmp_path)  # not even the scene's cache (it was left)
    # the COLMAP layout too: it crashed writing its model without points
    colmap = make_scene(tmp_path / "colmap", size=32, n_train=6, n_test=1, content="empty", layout="colmap")
    proc = run_cli("pretrain", "--data", str(colmap), "--recipe", str(tiny_recipe), "--workspace", str(ws),
                   "--device", "cpu")
    assert_clean_failure(proc, "nothing but the background")
    assert not ws.exists()


def test_one_foreground_pixel_in_one_view_is_enough_to_train(tmp_path):
    """The refusal above is for no foreground at all: a scene with one differing pixel (a small or distant
    object) passes, and so does a forward-facing one, where a white wall or sky is content."""
    from boostnerf_cli.errors import BoostNerfError
    from boostnerf_cli.scenes import load_scene, make_scene
    from boostnerf_cli.stages.pretrain import check_foreground

    scene = load_scene(make_scene(tmp_path / "scene", size=16, n_train=3, n_test=1, content="empty"))
    with pytest.raises(BoostNerfError, match="nothing but the background"):
        check_foreground(scene, tmp_path / "scene")
    scene.splits["train"].images[2, 7, 9] = torch.tensor([1.0, 1.0, 0.9])  # 0.1 from white in one channel
    check_foreground(scene, tmp_path / "scene")
    forward = load_scene(make_scene(tmp_path / "llff", size=16, n_train=3, n_test=1, content="empty", layout="llff"))
    assert forward.ndc is not None and bool((forward.splits["train"].images == 1).all())  # all white
    check_foreground(forward, tmp_path / "llff")


def test_unknown_recipe_key(tmp_path, tiny_scene):
    recipe = tmp_path / "bad.yaml"
    recipe.write_text("pretrain:\n  iters: 5\n  learning_rate: 3\n")
    proc = run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "--workspace", str(tmp_path / "ws"))
    assert_clean_failure(proc, "pretrain.learning_rate")
    assert not (tmp_path / "ws").exists()


def test_truncated_checkpoint_is_refused_and_kept(tmp_path, trained_ws):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    path = ws / "experts" / "dvgo-12.safetensors"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    proc = run_cli("eval", "--workspace", str(ws), "--model", "dvgo-12", "--device", "cpu")
    assert_clean_failure(proc, "dvgo-12.safetensors", "damaged")
    assert path.stat().st_size == len(data) // 2  # not silently replaced
    assert no_temp_files(ws)


def test_bad_res_flag_and_unknown_model(tmp_path, trained_ws):
    proc = run_cli("pretrain", "--workspace", str(tmp_path / "ws"), "--res", "64,abc")
    assert_clean_failure(proc, "--res")
    # the flag's range is the recipe's (it said "each >= 2" where a recipe allows 1, an NGP expert of one level)
    proc = run_cli("pretrain", "--workspace", str(tmp_path / "ws"), "--res", "64,0")
    assert_clean_failure(proc, "setting pretrain.res = 0: must be in [1, 1024]")
    assert not (tmp_path / "ws").exists()
    proc = run_cli("eval", "--workspace", str(trained_ws), "--model", "top7", "--device", "cpu")
    assert_clean_failure(proc, "top7", "dvgo-12")


def test_an_empty_argument_is_refused_not_taken_for_the_current_folder(tmp_path):
    """`pretrain -w "$WS"` with WS unset wrote manifest.json and experts/ into the current folder."""
    for args, needle in ((["pretrain", "-w", "", "--data", "scene"], "an empty argument after -w"),
                         (["eval", "--workspace="], "an empty value for --workspace"),
                         (["make-scene", ""], "an empty argument after make-scene")):
        proc = run_cli(*args, cwd=tmp_path)
        assert_clean_failure(proc, needle, "unset shell variable", "or '.' for the current folder")
    # a number list is no folder: no '.' hint; a list with an entry lost is refused, not shortened (8,,12 was [8, 12])
    for args, after in ((["--res", ""], "--res"), (["--res", "8", ""], "8")):
        proc = run_cli("pretrain", "-w", "ws", *args, cwd=tmp_path)
        assert_clean_failure(proc, f"an empty argument after {after}", "unset shell variable")
        assert "current folder" not in proc.stderr
    for res in ("8,,12", ",8"):
        proc = run_cli("pretrain", "-w", "ws", "--res", res, cwd=tmp_path)
        assert_clean_failure(proc, f"--res has an empty entry (got '{res}')")
    # a list of names likewise: "," was taken for every expert (build-moe) or every row (bench ran the whole suite)
    for args, needle in ((["build-moe", "-w", "ws", "--experts", ","], "--experts has an empty entry"),
                         (["build-moe", "-w", "ws", "--experts", "dvgo-8,,dvgo-12"], "--experts has an empty entry"),
                         (["bench", "-w", "b", "--only", ","], "--only has an empty entry")):
        assert_clean_failure(run_cli(*args, cwd=tmp_path), needle)
    assert list(tmp_path.iterdir()) == []


def test_eval_on_an_empty_folder_says_what_to_run(tmp_path):
    proc = run_cli("eval", "--workspace", str(tmp_path), "--device", "cpu")
    assert_clean_failure(proc, "boostnerf pretrain")


def test_render_writes_each_view_as_it_comes(trained_ws, tmp_path, monkeypatch):
    """render_split rendered every view of the split before its caller saw one: render wrote no PNG until the end
    (a crash or Ctrl-C at the last view kept nothing), and eval / render held the whole split in memory (200
    Blender test views at 800 px: 2.6 GB per model)."""
    import shutil

    import boostnerf_cli.models as models
    from boostnerf_cli.models import Viewing
    from boostnerf_cli.stages import render as stage
    from boostnerf_cli.workspace import Workspace

    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("renders"))
    real, calls = models.render_view, []

    def failing_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("stopped at the second view")
        return real(*args, **kwargs)

    monkeypatch.setattr(models, "render_view", failing_second)
    with pytest.raises(RuntimeError, match="second view"):
        stage.run(Survey(Workspace(ws)), ["dvgo-12"], Viewing("test"), "cpu")
    written = sorted(p.name for p in (ws / "renders" / "dvgo-12" / "test").glob("*.png"))
    assert len(written) == 2 and sum(n.endswith("_depth.png") for n in written) == 1, written  # view 1: colour, depth


def test_a_slow_stage_says_what_it_is_doing_and_a_fast_one_stays_quiet(caplog):
    """Reading 120 JPEGs at 4000 x 3000 (53 s) and scoring 200 held-out views (122 s) printed nothing; a line printed
    up front, though, made every one-line refusal of a bad scene two lines. The notice comes only when it is slow."""
    import time

    from boostnerf_cli.stages.common import slow_notice

    caplog.set_level(logging.INFO, logger="boostnerf_cli")
    with slow_notice("reading the scene", after=0.05):
        time.sleep(0.3)
    assert caplog.messages == ["reading the scene"]
    with slow_notice("scoring", after=0.5):
        pass
    with pytest.raises(ValueError), slow_notice("failing", after=0.05):
        raise ValueError("at once")
    time.sleep(0.2)
    assert caplog.messages == ["reading the scene"]


def test_log_lines_print_brackets_as_written(capsys):
    """Progress lines are plain text: Rich took "[0.34, 0.66]" or "[dvgo-8]" for a markup tag and dropped it, so
    `render --per-expert` printed "on detailed pixels , on smooth pixels " and a path like ws[2] lost its part."""
    from boostnerf_cli.cli import log, say_messages

    say_messages()  # as every command does first
    text = "on detailed pixels [0.34, 0.66], [nan, nan], [dvgo-8] and ws[x]/scene [bold]"
    log(text)
    assert capsys.readouterr().err.strip() == text


def test_warnings_go_through_logging_warning_and_say_so(capsys):
    """A warning is a `logging.warning` record, said as a line starting `warning:` (they were INFO lines that began
    with the word, so no level could keep them and drop the rest); -q keeps warnings and drops the other messages."""
    import logging as logging_module

    from boostnerf_cli.cli import say_messages

    stage = logging_module.getLogger("boostnerf_cli.stages.anything")
    try:
        say_messages(logging_module.WARNING)  # -q
        stage.info("dvgo-8: already trained, skipping")
        stage.warning("geometry: 3 of 9 foreground training rays miss the scene box")
        assert capsys.readouterr().err == "warning: geometry: 3 of 9 foreground training rays miss the scene box\n"
    finally:
        say_messages()


def test_quiet_and_verbose_work_on_any_command(trained_ws, tiny_scene, tmp_path):
    """-q: nothing on stderr but warnings and errors (results still on stdout); -v: the recipe read and what the stage
    decides about each artifact it finds; both at once is refused in one line."""
    scene = tmp_path / "scene"
    quiet = run_cli("-q", "make-scene", str(scene), "--size", "16", "--train-views", "2", "--test-views", "1",
                    check=True)
    assert quiet.stderr == "" and (scene / "transforms_train.json").exists()
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    args = ["pretrain", "-w", str(ws), "--data", str(tiny_scene), "--res", "12", "--device", "cpu"]
    said = run_cli(*args, check=True)
    assert "already trained" in said.stderr and "expert" in said.stdout
    quiet = run_cli("-q", *args, check=True)
    assert quiet.stderr == "" and quiet.stdout == said.stdout
    verbose = run_cli("-v", *args, check=True).stderr
    assert f"recipe tiny (from {ws / 'manifest.json'}); pretrain.res = [12]" in verbose
    assert "geometry: skip" in verbose and "dvgo-12: skip" in verbose and "already trained" in verbose
    assert_clean_failure(run_cli("-q", "-v", *args), "--quiet and --verbose")


def test_set_sets_any_recipe_key_checked_as_a_recipe_file_is(trained_ws, tiny_scene, tmp_path):
    """--set KEY=VALUE beside the named options: the key and the value's type are checked as in a recipe file, the
    range with the recipe; a key it sets is one a recipe sets (here a geometry setting, refused as changed)."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    args = ["pretrain", "-w", str(ws), "--data", str(tiny_scene), "--device", "cpu"]
    assert_clean_failure(run_cli(*args, "--set", "pretrain.geometry.iters=60"), "pretrain.geometry.iters: 100, now 60")
    assert_clean_failure(run_cli(*args, "--set", "pretrain.geometry.iterz=60"),
                         "unknown recipe key pretrain.geometry.iterz", "known keys here are")
    assert_clean_failure(run_cli(*args, "--set", "pretrain.iters=many"), "pretrain.iters must be int, got 'many'")
    assert_clean_failure(run_cli(*args, "--set", "pretrain.iters=0"), "pretrain.iters = 0: must be >= 1")
    assert_clean_failure(run_cli(*args, "--set", "pretrain.iters"), "give KEY=VALUE")
    assert_clean_failure(run_cli(*args, "--set", "moe.train.growth=[0.5]"), "moe.train.growth", "finetuning does not")
    assert_clean_failure(run_cli(*args, "--set", "pretrain.dvgo.hidden=32"), "pretrain.dvgo.hidden: 16, now 32")
    # a named option wins over --set for the same key
    assert "already trained" in run_cli(*args, "--set", "pretrain.iters=31", "--iters", "30", check=True).stderr


@pytest.mark.parametrize("args, needle", [
    (["finetune", "-w", "ws", "--topk=x"], "'--topk'"),
    (["eval", "--wokspace", "ws"], "--wokspace"),
    (["eval"], "'--workspace'"),
    (["render", "-w", "ws", "--views", "0"], "'--views'"),
    (["eval", "-w"], "'-w' requires an argument"),  # Click gives this one no context
], ids=["type", "unknown", "missing", "range", "no-value"])
def test_a_command_line_mistake_is_one_error_line(monkeypatch, capsys, args, needle):
    """Click's own refusals (a value of the wrong type, an unknown or missing option) were a
    box of 6+ lines around `Usage:`, the message wrapped mid-word on a narrow terminal, with no `error:` line to grep
    for; every other refusal is one line."""
    code, err = cli_in_process(monkeypatch, capsys, *args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], err
    assert lines[0].endswith(f"{args[0]} --help`)"), err  # where to read what is accepted


def test_a_short_option_written_with_an_equals_sign_is_refused(monkeypatch, capsys, tmp_path):
    """`pretrain -w=wsX` made a folder named `=wsX` (Click's reading of a short option), and
    `eval -w=ws` said `=ws is not a boostnerf workspace`."""
    monkeypatch.chdir(tmp_path)
    code, err = cli_in_process(monkeypatch, capsys, "eval", "-w=wsX", "--device", "cpu")
    assert code == 2 and err.strip() == ("error: -w=wsX names the folder '=wsX' (a short option takes no '='): "
                                         "write -w wsX")
    assert list(tmp_path.iterdir()) == []


def test_version(monkeypatch, capsys):
    from boostnerf_cli import __version__
    from boostnerf_cli.cli import main

    monkeypatch.setattr("sys.argv", ["boostnerf", "--version"])
    with pytest.raises(SystemExit) as exit_info:
        main()
    assert exit_info.value.code == 0 and capsys.readouterr().out == f"boostnerf {__version__}\n"


def test_a_result_table_on_a_narrow_terminal_folds_its_cells_and_cuts_no_digit(monkeypatch):
    """At 60 columns eval's table showed a PSNR as `11.…` and a GFLOPs figure as `0.01…`."""
    import io

    from rich.table import Table

    from boostnerf_cli import cli

    table = Table("model", "PSNR", "SSIM", "LPIPS", "params", "w0", "GFLOPs/image", "s/image")
    table.add_row("top1-pruned", "11.873", "0.4567", "0.1234", "1,234,567", "15,234", "0.0123", "0.456")
    monkeypatch.setattr(cli, "out", cli.Console(file=io.StringIO(), width=40, force_terminal=True, color_system=None))
    cli.show(table)
    text = "".join(c for c in cli.out.file.getvalue() if c.isalnum() or c in ".,-")
    assert "…" not in cli.out.file.getvalue()
    for cell in ("11.873", "0.0123", "1,234,567", "15,234"):  # each digit is there, in order, across folded lines
        it = iter(text)
        assert all(ch in it for ch in cell), cell


def test_a_workspace_of_another_file_format_is_refused_in_one_line(trained_ws, tmp_path):
    """A workspace an earlier boostnerf made (its manifest of another file format) is read by no command: one line
    says to make it again in a new workspace, before anything is read or written (its figures and files could differ
    from what this boostnerf makes)."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    manifest = json.loads((ws / "manifest.json").read_text())
    assert manifest["format_version"] == FORMAT_VERSION
    manifest["format_version"] = "1"
    (ws / "manifest.json").write_text(json.dumps(manifest))
    before = {p: p.stat().st_mtime_ns for p in ws.rglob("*")}
    for args in (["eval", "--no-costs"], ["pretrain"], ["build-moe"], ["render", "--views", "1"]):
        proc = run_cli(*args, "--workspace", str(ws), "--device", "cpu")
        assert_clean_failure(proc, f"workspace {ws} has file format '1', and this boostnerf reads format "
                                   f"{FORMAT_VERSION!r}: make it again in a new workspace")
    assert {p: p.stat().st_mtime_ns for p in ws.rglob("*")} == before


def test_an_experts_reported_held_out_psnr_is_what_eval_measures(tmp_path, tiny_scene):
    """With train.color_threshold 0.999999 pretrain's report scored the expert 14.77 dB, eval
    12.83: the report rendered with the training threshold, eval as every model is rendered (1e-4)."""
    recipe = make_recipe(tmp_path / "r.yaml", pretrain={"res": [10], "train": {"color_threshold": 0.3}})
    ws = tmp_path / "ws"
    run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "-w", str(ws), "--device", "cpu",
            check=True)
    reported = json.loads((ws / "experts" / "dvgo-10.json").read_text())["test_psnr"]
    run_cli("eval", "-w", str(ws), "--no-costs", "--report", "--device", "cpu", check=True)
    measured = json.loads((ws / "reports" / "eval.json").read_text())["models"][0]["psnr"]
    assert reported == pytest.approx(measured, abs=2e-3)
