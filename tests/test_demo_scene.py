"""The quickstart's demonstration: the "detail" procedural scene, the mixture's gains on it, and its pictures."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from boostnerf_cli import images
from boostnerf_cli.stages.render import ROUTING_LEGEND

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def test_a_label_wider_than_its_panel_wraps_and_stays_off_the_next_panel():
    """The routing legend of `<view>_experts.png` is wider than its panel: every pixel of it must lie in its own
    panel's column, off the next panel's title, and all of its words must be drawn (on more lines, in a taller band)."""
    white = np.full((48, 48, 3), 255, np.uint8)
    grid = images.panel_grid([[(ROUTING_LEGEND, white), ("", white)], [("b", white), ("", white)]], min_width=192)
    pw, pad = 192, 4
    first = grid[:, : pad + pw]
    assert (grid[:, pad + pw:] == 255).all(), "a label's text reaches past its panel into the next column"
    band = first[: grid.shape[0] - 2 * (pw + pad) - pad - 18]  # the first row's label band, above its panel
    ink_rows = np.flatnonzero((band < 128).any(axis=(1, 2)))
    assert ink_rows.size and ink_rows[-1] - ink_rows[0] > images.LINE_H, "the long label is not on several lines"
    font = images._font(13)
    lines = images.wrap_text(ROUTING_LEGEND, font, pw - 4)
    assert " ".join(lines) == ROUTING_LEGEND and len(lines) > 1
    assert all(font.getlength(line) <= pw - 4 for line in lines)


def test_wrap_text_cuts_a_word_only_when_it_alone_is_too_wide():
    font = images._font(13)
    assert images.wrap_text("a b", font, 200) == ["a b"]
    assert images.wrap_text("", font, 50) == [""]
    long = "x" * 80
    lines = images.wrap_text(f"ab {long} cd", font, 60)
    assert lines[0] == "ab" and len(lines) > 3 and "".join(lines[1:]).replace(" ", "") == long + "cd"
    assert all(font.getlength(line) <= 60 for line in lines)


def test_the_eval_table_gives_each_models_gflops_over_the_baselines_and_says_what_the_baseline_is():
    from boostnerf_cli.stages.evaluate import markdown_table

    def row(name, kind, psnr, gflops):
        return {"name": name, "kind": kind, "psnr": psnr, "ssim": 0.9, "lpips": None, "params": 10, "w0": 5,
                "gflops_per_image": gflops, "seconds_per_image": gflops / 4}

    result = {"split": "test", "views": 8, "skips": {"empty": True, "terminated": True}, "lpips_note": None,
              "ssim_note": None,
              "models": [row("dvgo-32", "expert", 27.0, 0.25), row("baseline", "expert", 28.0, 0.2),
                         row("top1", "mixture", 27.5, 0.1), row("top2", "mixture", 28.5, 0.3)],
              "finetuned": {"baseline": {"from": "dvgo-32", "iterations": 200},
                            "top1": {"from": "init", "iterations": 200},
                            "top2": {"from": "init", "iterations": 200}}}
    table = markdown_table(result)
    assert "| GFLOPs/image | GFLOPs vs baseline | s/image | s vs baseline |" in table
    assert "| baseline | 28.000 |" in table and "| 0.200 | 1.00x | 0.050 | 1.00x |" in table
    assert "| 0.100 | 0.50x | 0.025 | 0.50x |" in table and "| 0.300 | 1.50x | 0.075 | 1.50x |" in table
    assert ("`baseline` is the largest expert, dvgo-32, trained alone for the same 200 finetuning steps as top1, "
            "top2") in table
    result["finetuned"]["top2"]["iterations"] = 100
    assert "for 200 finetuning steps (top1: 200, top2: 100)" in markdown_table(result)
    no_baseline = {**result, "models": result["models"][:1], "finetuned": {}}
    table = markdown_table(no_baseline)
    assert "How to read it" not in table and "| 0.250 | - | 0.062 | - |" in table


def test_the_eval_table_says_why_a_top1_below_its_baseline_is_below_it():
    """The note says what the table shows (the gap, the GFLOPs ratio) and points at the docs for why on lego; it
    makes no claim about lego in a report of another scene."""
    from boostnerf_cli.stages.evaluate import TOP1_POINTER, TOP1_WHY, markdown_table

    def row(name, psnr, gflops, k=None):
        return {"name": name, "kind": "mixture" if k else "expert", "psnr": psnr, "ssim": None, "lpips": None,
                "params": 1, "w0": 1, "gflops_per_image": gflops, "seconds_per_image": 0.1,
                **({"routing": {"topk": k, "renormalize": True}} if k else {})}

    result = {"split": "test", "views": 8, "skips": {"empty": True, "terminated": True}, "lpips_note": None,
              "ssim_note": None, "finetuned": {},
              "models": [row("baseline", 28.0, 0.2), row("top1", 26.5, 0.12, 1), row("top2", 28.3, 0.25, 2)]}
    table = markdown_table(result)
    assert "`top1` is 1.50 dB below `baseline`, at 0.60x its GFLOPs: it renders each sample with one expert" in table
    assert TOP1_WHY in table and table.count(TOP1_WHY) == 1  # top2 gets no such line
    assert "lego" not in table.replace(TOP1_POINTER, "")  # the scene of the docs is named in the pointer only
    above = {**result, "models": [row("baseline", 28.0, 0.2), row("top1", 28.1, 0.12, 1)]}
    assert TOP1_WHY not in markdown_table(above)
    no_costs = {**result, "models": [row("baseline", 28.0, None), row("top1", 26.5, None, 1)]}
    assert "`top1` is 1.50 dB below `baseline`: it renders" in markdown_table(no_costs)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_on_the_quickstart_scene_top2_beats_its_same_steps_baseline_and_top1_costs_less(tmp_path, seed):
    """What the quickstart shows, trained and evaluated at two seeds on its scene with its recipe (recipes/quickstart.sh
    with SEED=0 and 1, less the ensemble and the pictures): Top-2's PSNR above the baseline's (the largest expert
    trained alone for the same finetuning steps), Top-1's GFLOPs per image below the baseline's."""
    quickstart = (RECIPES / "quickstart.sh").read_text()
    assert 'make-scene "$WS/scene" --size 48 --content detail --seed "$SEED"' in quickstart
    assert ('boostnerf chain "$WS/scene" --workspace "$WS" --recipe "$HERE/demo-dvgo-cpu.yaml" --seed "$SEED"'
            in quickstart)
    scene, ws, recipe = tmp_path / "scene", str(tmp_path / "ws"), str(RECIPES / "demo-dvgo-cpu.yaml")
    def cli(*args):  # an hour a stage: on a loaded machine one takes over the default 10 minutes
        return run_cli(*args, "--device", "cpu", check=True, timeout=3600)

    run_cli("make-scene", str(scene), "--size", "48", "--content", "detail", "--seed", str(seed), check=True)
    cli("pretrain", "--workspace", ws, "--data", str(scene), "--recipe", recipe, "--seed", str(seed))
    cli("build-moe", "--workspace", ws, "--recipe", recipe)
    for flag in (["--baseline"], ["--topk", "1"], ["--topk", "2"]):
        cli("finetune", "--workspace", ws, "--recipe", recipe, *flag)
    cli("eval", "--workspace", ws, "--split", "test", "--report", "--model", "baseline", "--model", "top1", "--model",
        "top2")
    report = json.loads((tmp_path / "ws" / "reports" / "eval.json").read_text())
    rows = {r["name"]: r for r in report["models"]}
    base, top1, top2 = rows["baseline"], rows["top1"], rows["top2"]
    figures = {k: (round(r["psnr"], 3), round(r["gflops_per_image"], 3)) for k, r in rows.items()}
    assert top2["psnr"] > base["psnr"], figures
    assert top1["gflops_per_image"] < base["gflops_per_image"], figures
    steps = report["finetuned"]["baseline"]["iterations"]
    assert {r["iterations"] for r in report["finetuned"].values()} == {steps}, report["finetuned"]
    table = (tmp_path / "ws" / "reports" / "eval.md").read_text()
    assert f"trained alone for the same {steps} finetuning steps as top1, top2" in table
