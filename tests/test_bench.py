"""`boostnerf bench`: the suites' rows, and the quick suite end to end on a tiny generated scene."""

import csv
import json
import math
import shutil
from pathlib import Path

import imageio.v3 as iio
import pytest
from conftest import assert_clean_failure, make_recipe, run_cli

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import CONFIGS
from boostnerf_cli.recipe import Recipe, load_recipe
from boostnerf_cli.stages import bench

# the tiny recipe with fewer steps: the bench trains 5 experts and 4 mixtures.
BENCH_CHANGES = {"pretrain": {"iters": 16, "geometry": {"iters": 60}}, "moe": {"iters": 8}}


@pytest.fixture(scope="module")
def bench_recipe(tmp_path_factory):
    return make_recipe(tmp_path_factory.mktemp("bench-recipe") / "bench.yaml", **BENCH_CHANGES)


def test_ladder_and_suites():
    assert bench.ladder(16, 32, 5) == [16, 20, 24, 28, 32]
    assert bench.ladder(64, 96, 4) == [64, 75, 85, 96]
    rec = Recipe()
    rec.pretrain.res = [64, 80, 96]
    rec.pretrain.dvgo = {"hidden": {64: 64, 80: 96, 96: 128}, "layers": 2}
    setups, quick = bench.catalogue(rec, "quick")
    assert [r.name for r in quick] == ["dvgo-64", "dvgo-80", "dvgo-96", "baseline", "top1", "top2", "ens",
                                       "naive-res", "naive-step", "naive-wide"]
    assert setups["naive-res"].recipe.pretrain.res == [120]
    assert setups["naive-res"].recipe.pretrain.iters == rec.pretrain.iters + rec.moe.iters
    assert setups["naive-step"].recipe.pretrain.train.step_ratio == rec.pretrain.train.step_ratio / 2
    assert setups["naive-wide"].recipe.pretrain.dvgo["hidden"] == {96: 256}
    setups, full = bench.catalogue(rec, "full")
    names = [r.name for r in full]
    assert len(names) == len(set(names)) and names[: len(quick)] == [r.name for r in quick]
    assert all(r.setup in setups for r in full)
    assert [r.name for r in full if r.group == "topk"] == (
        ["M3-top3"] + [f"M4-top{k}" for k in range(1, 5)] + [f"M5-top{k}" for k in range(1, 6)])
    assert setups["m4"].recipe.pretrain.res == [64, 75, 85, 96]
    assert setups["m4"].recipe.pretrain.dvgo["hidden"] == {64: 64, 75: 96, 85: 96, 96: 128}  # nearest
    assert {r.name for r in full if r.group == "gate-res"} == {"gate-res-16", "gate-res-64"}
    switch = next(r for r in full if r.name == "gate-switch")
    assert switch.topk == 1 and setups["gate-switch"].recipe.moe.gate_type == "switch"
    penalties = {r.name for r in full if r.group == "penalty"}
    assert penalties == {f"penalty-{p}-top{k}" for p in ("linear", "quadratic", "none") for k in (1, 2)}
    assert setups["penalty-none"].link_init
    assert [r.name for r in bench.select(full, ["naive", "top1"], "full")] == ["top1", "naive-res", "naive-step",
                                                                                 "naive-wide"]
    with pytest.raises(BoostNerfError, match="no row or group 'nope'"):
        bench.select(quick, ["nope"], "quick")
    with pytest.raises(BoostNerfError, match="unknown suite"):
        bench.catalogue(rec, "medium")


def test_every_family_gets_its_own_wider_mlp_and_the_experts_pretrain_would_train():
    """naive-wide of a TensoRF or Instant-NGP recipe wrote the doubled width into an unused `dvgo` section: the row was
    the plain largest expert, labelled and plotted as a 2x wider one. And a resolution between two listed ones took
    the smaller's options in the bench, the larger's in `pretrain` (its tie rule): the same name, another expert."""
    from boostnerf_cli.stages.pretrain import expert_options

    for family, key, section in (("tensorf", "hidden", {"hidden": 32}), ("ngp", "color_hidden", {}),
                                 ("dvgo", "hidden", {"hidden": {64: 64, 72: 96, 80: 128}})):
        rec = Recipe()
        rec.pretrain.model, rec.pretrain.res = family, [64, 72, 80]
        setattr(rec.pretrain, family, section)
        setups, full = bench.catalogue(rec, "full")
        wide = getattr(setups["naive-wide"].recipe.pretrain, family)
        base = expert_options(rec.pretrain, 80)[key] if key in section else getattr(CONFIGS[family](), key)
        assert wide[key] == {80: 2 * base}, (family, wide)
        assert not setups["naive-wide"].recipe.pretrain.dvgo or family == "dvgo"
        for name in ("m4", "m5"):  # the ladders' experts get exactly pretrain's options
            variant = setups[name].recipe.pretrain
            for r in variant.res:
                assert expert_options(variant, r) == expert_options(rec.pretrain, r), (family, name, r)


def test_bench_recipe_is_a_valid_recipe(bench_recipe):
    rec = load_recipe(bench_recipe)
    assert rec.pretrain.iters == 16 and rec.moe.iters == 8 and rec.pretrain.geometry.iters == 60


@pytest.fixture(scope="module")
def quick_bench(tiny_scene, bench_recipe, tmp_path_factory):
    root = tmp_path_factory.mktemp("bench") / "b"
    proc = run_cli("bench", "--data", str(tiny_scene), "--recipe", str(bench_recipe), "--workspace", str(root),
                   "--device", "cpu", check=True)
    return root, proc


# each row's PSNR on the tiny scene, measured (the same with 1 and 2 threads); a row must stay within 0.25 dB
# of it: these 16-step models are close to the image mean, so a broken model is only tenths of a dB lower
BENCH_PSNR = {"dvgo-12": 12.02, "dvgo-16": 12.97, "baseline": 13.20, "top1": 12.23, "top2": 12.76, "ens": 12.73,
              "naive-res": 13.87, "naive-step": 13.62, "naive-wide": 13.82}


def test_quick_suite_writes_a_finite_table(quick_bench):
    root, proc = quick_bench
    with open(root / "reports" / "bench.csv") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == bench.COLUMNS
    names = [r[0] for r in rows[1:]]
    assert names == ["dvgo-12", "dvgo-16", "baseline", "top1", "top2", "ens", "naive-res", "naive-step", "naive-wide"]
    for r in rows[1:]:
        values = [float(v) for v in r[2:]]
        assert all(math.isfinite(v) for v in values), r
        psnr, ssim, train_s, s_img, gflops, params, w0 = values
        assert psnr > BENCH_PSNR[r[0]] - 0.25, (r[0], psnr)
        assert 0 < ssim <= 1 and train_s > 0 and s_img > 0 and gflops > 0 and 0 < w0 <= params
    table = json.loads((root / "reports" / "bench.json").read_text())
    assert table["suite"] == "quick" and table["missing"] == [] and len(table["rows"]) == 9
    by_name = {r["name"]: r for r in table["rows"]}
    assert by_name["top2"]["experts"] == 2 and by_name["top2"]["topk"] == 2
    experts = {n: json.loads((root / "variants" / "main" / "experts" / f"{n}.json").read_text())["seconds"]
               for n in ("dvgo-12", "dvgo-16")}
    finetune = json.loads((root / "variants" / "main" / "moe" / "top1.json").read_text())["seconds"]
    assert by_name["top1"]["train_seconds"] == pytest.approx(sum(experts.values()) + finetune, abs=0.02)
    naive = json.loads((root / "variants" / "naive-res" / "experts" / "dvgo-20.json").read_text())
    assert naive["iterations"] == 16 + 8  # the mixture's total steps
    geometry = [(root / "variants" / v / "experts" / "geometry.safetensors").stat().st_ino
                for v in ("main", "naive-res", "naive-step", "naive-wide")]
    assert len(set(geometry)) == 1  # trained once, hard-linked
    plots = sorted(p.name for p in (root / "reports").glob("*.png"))
    assert plots == ["bench-psnr-gflops.png", "bench-psnr-time.png"]  # matplotlib is in the test extra
    for p in plots:
        img = iio.imread(root / "reports" / p)
        assert img.shape[:2] == (600, 840) and img[..., :3].std() > 10  # 7x5 in at 120 dpi, not blank


def test_bench_plots_leave_out_rows_whose_psnr_was_not_finite(tmp_path):
    """A bench row read back holds null for a PSNR of inf (a pixel-perfect render): the plots leave it out."""
    rows = [{"name": "top1", "group": "moe", "psnr": 20.0, "gflops_per_image": 1.0, "seconds_per_image": 0.1},
            {"name": "sky", "group": "expert", "psnr": None, "gflops_per_image": 0.0, "seconds_per_image": 0.1}]
    assert [Path(p).name for p in bench.plot(rows, tmp_path)] == ["bench-psnr-gflops.png", "bench-psnr-time.png"]


def test_bench_plots_are_skipped_with_one_line_without_matplotlib(tmp_path, monkeypatch, caplog):
    import logging
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    caplog.set_level(logging.INFO, logger="boostnerf_cli")
    rows = [{"name": "top1", "group": "moe", "psnr": 20.0, "gflops_per_image": 1.0, "seconds_per_image": 0.1}]
    assert bench.plot(rows, tmp_path) == []
    said = caplog.messages
    assert len(said) == 1 and "matplotlib is not installed" in said[0]
    assert list(tmp_path.iterdir()) == []


def test_bench_resumes_and_reuses_experts_for_ablations(quick_bench, tiny_scene, bench_recipe):
    root, _ = quick_bench
    stamp = (root / "rows" / "top1.json").stat().st_mtime_ns
    proc = run_cli("bench", "--data", str(tiny_scene), "--recipe", str(bench_recipe), "--workspace", str(root),
                   "--device", "cpu", check=True)
    assert proc.stderr.count("finished, skipping") == 9
    assert (root / "rows" / "top1.json").stat().st_mtime_ns == stamp
    proc = run_cli("bench", "--data", str(tiny_scene), "--recipe", str(bench_recipe), "--workspace", str(root),
                   "--suite", "full", "--only", "M3-top1,penalty-none-top1", "--device", "cpu", check=True)
    main = root / "variants" / "main"
    m3 = root / "variants" / "m3" / "experts"
    assert sorted(p.name for p in m3.glob("dvgo-*.safetensors")) == ["dvgo-12.safetensors", "dvgo-14.safetensors",
                                                                   "dvgo-16.safetensors"]
    assert (m3 / "dvgo-16.safetensors").stat().st_ino == (main / "experts" / "dvgo-16.safetensors").stat().st_ino
    penalty = root / "variants" / "penalty-none" / "moe"
    assert (penalty / "init.safetensors").stat().st_ino == (main / "moe" / "init.safetensors").stat().st_ino
    assert json.loads((penalty / "top1.json").read_text())["penalty"] == "none"
    table = json.loads((root / "reports" / "bench.json").read_text())
    assert table["suite"] == "full" and {"M3-top1", "penalty-none-top1", "top1"} <= {r["name"] for r in table["rows"]}
    assert "M3-top2" in table["missing"]


def test_bench_refuses_bad_input(quick_bench, tiny_scene, bench_recipe, tmp_path):
    root, _ = quick_bench
    proc = run_cli("bench", "--data", str(tiny_scene), "--recipe", str(bench_recipe), "--workspace", str(root),
                   "--views", "1", "--device", "cpu")
    assert_clean_failure(proc, "made with another views")
    proc = run_cli("bench", "--data", str(tiny_scene), "--workspace", str(tmp_path / "b"), "--only", "top9")
    assert_clean_failure(proc, "no row or group 'top9'")
    proc = run_cli("bench", "--data", str(tmp_path / "missing"), "--workspace", str(tmp_path / "c"))
    assert_clean_failure(proc, "does not exist")
    proc = run_cli("bench", "--workspace", str(tmp_path / "d"), "--suite", "huge")
    assert_clean_failure(proc, "unknown suite")
    proc = run_cli("bench", "--workspace", str(root), "--recipe", str(bench_recipe), "--list", "--only", "naive")
    assert proc.returncode == 0 and "naive-step" in proc.stdout and "top1" not in proc.stdout
    # --list under another recipe: refused as the run is, not "finished: yes" for rows of the other recipe
    proc = run_cli("bench", "--workspace", str(root), "--list", "--views", "1")
    assert_clean_failure(proc, "made with another")


def test_a_moved_bench_folder_or_scene_keeps_its_finished_rows(quick_bench, tiny_scene, bench_recipe, tmp_path):
    """A bench folder moved, or its scene moved (a symbolic link repointed): the same command at the new places
    skipped nothing and refused with "made with another data" (the scene's resolved absolute path was recorded), and
    only deleting the folder got past it. The same images and cameras now keep every finished row; other ones are
    refused. The generated scene inside the folder is recorded relative to it, so it travels with the folder."""
    root = tmp_path / "moved"
    shutil.copytree(quick_bench[0], root)
    scene = tmp_path / "scene-moved"
    shutil.copytree(tiny_scene, scene)
    proc = run_cli("bench", "--data", str(scene), "--recipe", str(bench_recipe), "--workspace", str(root),
                   "--device", "cpu", check=True)
    assert proc.stderr.count("finished, skipping") == len(
        json.loads((root / "reports" / "bench.json").read_text())["rows"])
    assert json.loads((root / "bench-config.json").read_text())["data"] == str(scene)
    other = tmp_path / "scene-edited"
    shutil.copytree(tiny_scene, other)
    img = iio.imread(other / "train" / "r_0.png")
    img[5, 5] = [255, 0, 0, 255]
    iio.imwrite(other / "train" / "r_0.png", img)
    proc = run_cli("bench", "--data", str(other), "--recipe", str(bench_recipe), "--workspace", str(root),
                   "--device", "cpu")
    assert_clean_failure(proc, "is not the one the bench", str(scene))
    assert bench.bench_config(root / "scene", None, Recipe(), root)["data"] == "scene"
    # no --recipe: the bench's own recipe, as a workspace's later stages take its recorded one (it was the default
    # recipe, whose suite has other rows: "no row or group 'dvgo-12' in the quick suite")
    proc = run_cli("bench", "--data", str(scene), "--workspace", str(root), "--only", "dvgo-12", "--device", "cpu",
                   check=True)
    assert "finished, skipping" in proc.stderr


def test_bench_config_of_a_recipe_with_per_resolution_options_reads_back_equal(tmp_path):
    """A recipe with `hidden: {64: 64, 80: 128}` (int keys) must not look like another recipe on rerun."""
    from boostnerf_cli.workspace import read_json, write_json

    rec = Recipe()
    rec.pretrain.dvgo = {"hidden": {64: 64, 80: 128}}
    config = bench.bench_config(tmp_path, None, rec, tmp_path)
    write_json(tmp_path / "bench-config.json", config)
    assert (read_json(tmp_path / "bench-config.json", "bench config")
            == bench.bench_config(tmp_path, None, rec, tmp_path))


def test_tables_written_to_a_file_or_pipe_keep_every_name_whole(bench_recipe, tmp_path):
    """Out of a terminal (a log, a pipe) Rich laid tables out at 80 columns and cut what did not fit:
    `variants/penalty-l…`. They are now as wide as their cells."""
    proc = run_cli("bench", "--workspace", str(tmp_path / "b"), "--recipe", str(bench_recipe), "--list", "--suite",
                   "full")
    assert proc.returncode == 0, proc.stderr
    assert "…" not in proc.stdout and "variants/penalty-quadratic " in proc.stdout, proc.stdout


def test_rows_that_could_only_repeat_another_are_left_out_with_a_note():
    """At moe.lam 0 (blender-tensorf-cpu.yaml's) the six penalty rows were bit-identical
    retrainings of top1 and top2, labelled as ablations; with one expert the gate rows too repeated top1; and a
    moe.topk above M was clamped for the gate rows without a word."""
    rec = Recipe()
    rec.pretrain.res = [64, 80, 96]
    rec.moe.lam = 0.0
    _, full = bench.catalogue(rec, "full")
    assert not [r for r in full if r.group == "penalty"] and [r for r in full if r.group == "gate-res"]
    assert any("moe.lam = 0: the penalty rows are left out" in n for n in bench.catalogue_notes(rec, "full"))
    assert bench.catalogue_notes(rec, "quick") == []
    rec.moe.lam, rec.pretrain.res, rec.moe.topk = 1e-3, [64], 3
    _, full = bench.catalogue(rec, "full")
    assert not [r for r in full if r.group in ("gate-res", "gate-type", "penalty")]
    assert bench.catalogue_notes(rec, "full") == [
        "one expert: the gate-res, gate-type and penalty rows are left out (every gate routes to it, so they would "
        "repeat top1)"]  # and no word of a k for rows that are not there
    rec.pretrain.res = [64, 80]
    _, full = bench.catalogue(rec, "full")
    assert {r.topk for r in full if r.group == "gate-res"} == {2}
    assert any("moe.topk = 3 but the recipe has 2 experts" in n for n in bench.catalogue_notes(rec, "full"))
    assert bench.catalogue_notes(rec, "quick") == []  # the quick suite has no row with the recipe's k
    rec.pretrain.res, rec.moe.topk = [64, 80, 96], 2  # the default: every row, no note
    _, full = bench.catalogue(rec, "full")
    assert len([r for r in full if r.group == "penalty"]) == 6 and bench.catalogue_notes(rec, "full") == []


def test_an_interrupted_bench_leaves_the_table_of_what_it_finished(quick_bench, tiny_scene, bench_recipe, tmp_path,
                                                                    monkeypatch):
    """The table was written only when the whole run ended: a bench stopped after 8 rows left no bench.json or
    bench.csv (or the previous run's, stale), though docs/reports.md calls it the table of every finished row."""
    import shutil

    from boostnerf_cli.recipe import load_recipe

    root = tmp_path / "b"
    shutil.copytree(quick_bench[0], root, symlinks=True)
    shutil.rmtree(root / "reports")
    for name in ("naive-step", "naive-wide"):
        (root / "rows" / f"{name}.json").unlink()
    real, ran = bench.Bench.run_row, []

    def stop_at_the_second(self, row):
        ran.append(row.name)
        if len(ran) == 2:
            raise KeyboardInterrupt
        return real(self, row)

    monkeypatch.setattr(bench.Bench, "run_row", stop_at_the_second)
    with pytest.raises(KeyboardInterrupt):
        bench.run(root, tiny_scene, load_recipe(bench_recipe), "quick", None, "cpu", None)
    table = json.loads((root / "reports" / "bench.json").read_text())
    assert len(table["rows"]) == 8 and table["missing"] == ["naive-wide"]
    assert len((root / "reports" / "bench.csv").read_text().splitlines()) == 1 + 8
