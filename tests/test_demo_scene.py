"""The quickstart's demonstration: the "detail" procedural scene, the mixture's gains on it, and its pictures."""

import numpy as np

from boostnerf_cli import images
from boostnerf_cli.stages.render import ROUTING_LEGEND


def test_a_label_wider_than_its_panel_wraps_and_stays_off_the_next_panel():
    """The routing legend of `<view>_experts.png` ran across the next panel's title: every pixel of a long label
    must lie in its own panel's column, and all of its words must be drawn (on more lines, in a taller band)."""
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

    row = lambda name, kind, psnr, gflops: {"name": name, "kind": kind, "psnr": psnr, "ssim": 0.9, "lpips": None,  # noqa: E731
                                            "params": 10, "w0": 5, "gflops_per_image": gflops, "seconds_per_image": 0.1}
    result = {"split": "test", "views": 8, "skips": {"empty": True, "terminated": True}, "lpips_note": None,
              "ssim_note": None,
              "models": [row("dvgo-32", "expert", 27.0, 0.25), row("baseline", "expert", 28.0, 0.2),
                         row("top1", "mixture", 27.5, 0.1), row("top2", "mixture", 28.5, 0.3)],
              "finetuned": {"baseline": {"from": "dvgo-32", "iterations": 200}, "top1": {"from": "init", "iterations": 200},
                            "top2": {"from": "init", "iterations": 200}}}
    table = markdown_table(result)
    assert "| GFLOPs/image | GFLOPs vs baseline |" in table
    assert "| baseline | 28.000 |" in table and "| 0.200 | 1.00x |" in table
    assert "| 0.100 | 0.50x |" in table and "| 0.300 | 1.50x |" in table
    assert ("`baseline` is the largest expert, dvgo-32, trained alone for the same 200 finetuning steps as top1, "
            "top2") in table
    result["finetuned"]["top2"]["iterations"] = 100
    assert "for 200 finetuning steps (top1: 200, top2: 100)" in markdown_table(result)
    no_baseline = {**result, "models": result["models"][:1], "finetuned": {}}
    assert "How to read it" not in markdown_table(no_baseline) and "| 0.250 | - |" in markdown_table(no_baseline)


def test_the_eval_table_says_why_a_top1_below_its_baseline_is_below_it():
    from boostnerf_cli.stages.evaluate import TOP1_WHY, markdown_table

    row = lambda name, psnr, gflops, k=None: {"name": name, "kind": "mixture" if k else "expert", "psnr": psnr,  # noqa: E731
                                              "ssim": None, "lpips": None, "params": 1, "w0": 1,
                                              "gflops_per_image": gflops, "seconds_per_image": 0.1,
                                              **({"routing": {"topk": k, "renormalize": True}} if k else {})}
    result = {"split": "test", "views": 8, "skips": {"empty": True, "terminated": True}, "lpips_note": None,
              "ssim_note": None, "finetuned": {},
              "models": [row("baseline", 28.0, 0.2), row("top1", 26.5, 0.12, 1), row("top2", 28.3, 0.25, 2)]}
    table = markdown_table(result)
    assert "`top1` is 1.50 dB below `baseline`, at 0.60x its GFLOPs: it renders each sample with one expert" in table
    assert TOP1_WHY in table and table.count(TOP1_WHY) == 1  # top2 gets no such line
    above = {**result, "models": [row("baseline", 28.0, 0.2), row("top1", 28.1, 0.12, 1)]}
    assert TOP1_WHY not in markdown_table(above)
    no_costs = {**result, "models": [row("baseline", 28.0, None), row("top1", 26.5, None, 1)]}
    assert "`top1` is 1.50 dB below `baseline`: it renders" in markdown_table(no_costs)
