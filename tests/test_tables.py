"""The result tables in docs/ are what scripts/tables.py makes of the reports in docs/data/."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent
_spec = importlib.util.spec_from_file_location("tables", ROOT / "scripts" / "tables.py")
tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(tables)


def _marked() -> list[tuple[Path, str]]:
    return [(md, m["name"]) for md in tables.documents() for m in tables.BLOCK.finditer(md.read_text())]


def test_every_marked_table_matches_its_data():
    marked = _marked()
    names = {n for _, n in marked}
    assert {"official-paper-layout", "results-cpu-recipes", "benchmarks-lego", "readme-costs"} <= names
    for md, _ in {(md, None) for md, _ in marked}:
        text = md.read_text()
        new, changed = tables.rebuild(text)
        assert not changed, f"{md.name}: {changed} differ from docs/data (run python scripts/tables.py)"
        assert new == text
    assert tables.main(["--check"]) == 0


def test_every_data_file_has_a_table_and_a_provenance_line():
    names = {n for _, n in _marked()}
    files = sorted((ROOT / "docs" / "data").glob("*.json"))
    specs = [json.loads(p.read_text()) for p in files]
    reports = {f for spec in specs for f in tables.reports_of(spec)}
    readme = (ROOT / "docs" / "data" / "README.md").read_text()
    for path in files:
        assert path.stem in names or path.name in reports, f"{path.name} is used by no table"
        assert f"`{path.name}`" in readme, f"{path.name}: say where it comes from in docs/data/README.md"


@pytest.mark.parametrize("name, typed, edited", [
    ("results-cpu-recipes", "| 35.238 | +0.32 |", "| 35.338 | +0.42 |"),  # a model table
    ("benchmarks-cost-targets", "**6.74x**", "**6.75x**"),  # a transcribed generic table
])
def test_a_hand_edited_table_is_caught(name, typed, edited):
    md = next(x[0] for x in _marked() if x[1] == name)
    text = md.read_text().replace(typed, edited)
    assert text != md.read_text()
    _, changed = tables.rebuild(text)
    assert changed == [name]


def test_a_table_from_raw_eval_reports_with_deltas_against_each_baseline(tmp_path, monkeypatch):
    """What the lead engineer does with new runs: copy WS/reports/eval.json files to docs/data/ and list them."""
    def report(psnr_base, psnr_top2):
        row = {"kind": "mixture", "lpips": None, "seconds_per_image": 0.1, "samples_per_image": 1,
               "colored_per_image": 1, "params": 2_000_000}
        return {"split": "test", "views": 8, "lpips_note": None, "models": [
            {**row, "name": "dvgo-80", "kind": "expert", "psnr": 33.781, "ssim": 0.9801, "w0": 1_090_123,
             "gflops_per_image": 2.789},
            {**row, "name": "baseline", "kind": "expert", "psnr": psnr_base, "ssim": 0.98404, "w0": 1_051_655,
             "gflops_per_image": 2.5701},
            {**row, "name": "top2", "psnr": psnr_top2, "ssim": 0.98512, "w0": 1_720_000, "gflops_per_image": 2.6969}]}

    data = tmp_path / "data"
    data.mkdir()
    (data / "dvgo-eval.json").write_text(json.dumps(report(34.2494, 34.5451)))
    (data / "ngp-eval.json").write_text(json.dumps(report(33.1271, 33.4482)))
    (data / "families.json").write_text(json.dumps({"groups": [
        {"label": "DVGO", "report": "dvgo-eval.json"},
        {"label": "NGP", "report": "ngp-eval.json", "models": ["baseline", "top2"]}]}))
    monkeypatch.setattr(tables, "DATA", data)
    assert tables.render("families") == (
        "| model | PSNR | vs baseline | SSIM | ‖w‖₀ | GFLOPs / image |\n"
        "|---|---|---|---|---|---|\n"
        "| DVGO: dvgo-80 | 33.781 | -0.47 | 0.9801 | 1,090,123 | 2.789 |\n"
        "| DVGO: baseline | 34.249 |  | 0.9840 | 1,051,655 | 2.570 |\n"
        "| DVGO: top2 | 34.545 | +0.30 | 0.9851 | 1,720,000 | 2.697 |\n"
        "| NGP: baseline | 33.127 |  | 0.9840 | 1,051,655 | 2.570 |\n"
        "| NGP: top2 | 33.448 | +0.32 | 0.9851 | 1,720,000 | 2.697 |\n")
    # a group read from two reports (a model finetuned in another workspace): deltas against the first's baseline
    (data / "ens-eval.json").write_text(json.dumps({"models": [
        {"name": "ens", "psnr": 34.9631, "ssim": 0.98691, "w0": 2_284_373, "gflops_per_image": 4.7101}]}))
    (data / "with-ens.json").write_text(json.dumps({"groups": [
        {"label": "M = 3", "report": ["dvgo-eval.json", "ens-eval.json"], "models": ["baseline", "ens"]}]}))
    assert tables.render("with-ens").splitlines()[2:] == [
        "| M = 3: baseline | 34.249 |  | 0.9840 | 1,051,655 | 2.570 |",
        "| M = 3: ens | 34.963 | +0.71 | 0.9869 | 2,284,373 | 4.710 |"]
    # one raw eval.json copied as the table's own file: a single group
    (data / "one.json").write_text(json.dumps(report(34.2494, 34.5451)))
    assert tables.render("one").splitlines()[4] == "| top2 | 34.545 | +0.30 | 0.9851 | 1,720,000 | 2.697 |"


@pytest.mark.parametrize("value,compact,text", [(593_532, True, "594k"), (1_072_525, True, "1.07M"),
                                                (1_072_525, False, "1,072,525"), (None, True, "-"),
                                                ("1.1M", False, "1.1M")])
def test_parameter_counts(value, compact, text):
    assert tables._count(value, compact) == text


def test_a_generic_table_prints_its_cells_as_written(tmp_path, monkeypatch):
    """A table that is neither a model nor a bench table: {"columns", "rows"}, every cell a string kept as typed."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "targets.json").write_text(json.dumps({"columns": ["target", "measured", "met?"], "rows": [
        ["skips >= 6x faster", "**6.47x** (0.05 dB)", "yes"], ["overhead <= 15%", "24.9%", ""]]}))
    monkeypatch.setattr(tables, "DATA", data)
    assert tables.render("targets") == (
        "| target | measured | met? |\n"
        "|---|---|---|\n"
        "| skips >= 6x faster | **6.47x** (0.05 dB) | yes |\n"
        "| overhead <= 15% | 24.9% |  |\n")
    text = "before\n<!-- table: targets -->\n" + tables.render("targets") + "<!-- /table -->\nafter\n"
    assert tables.rebuild(text) == (text, [])
    _, changed = tables.rebuild(text.replace("**6.47x**", "**7.47x**"))  # a hand-edited cell
    assert changed == ["targets"]
    (data / "bad.json").write_text(json.dumps({"columns": ["a", "b"], "rows": [["1"]]}))
    with pytest.raises(ValueError):
        tables.render("bad")


def test_the_paper_layout_puts_each_size_and_model_in_a_column(tmp_path, monkeypatch):
    """The paper's appendix tables: measures as rows, M = 3 / 4 ... x baseline / Top-1 / ... as columns."""
    def report(base, top1, seconds):
        return {"models": [
            {"name": "dvgo-64", "psnr": 31.0, "ssim": 0.97, "w0": 900_000, "gflops_per_image": 1.5},
            {"name": "baseline", "psnr": base, "ssim": 0.98594, "w0": 2_246_310, "gflops_per_image": 2.834,
             "extra": {"train s": str(seconds[0])}},
            {"name": "top1", "psnr": top1, "ssim": 0.98431, "w0": 4_329_470, "gflops_per_image": 1.739,
             "extra": {"train s": str(seconds[1])}}]}

    data = tmp_path / "data"
    data.mkdir()
    (data / "m3.json").write_text(json.dumps(report(34.6712, 34.2874, (376, 650))))
    (data / "m4.json").write_text(json.dumps(report(34.4271, 34.5, (391, 702))))
    (data / "m4-top1.json").write_text(json.dumps({"models": [
        {"name": "top1", "psnr": 34.9, "ssim": 0.9875, "w0": 3_000_000, "gflops_per_image": 2.0}]}))
    spec = {"sizes": [{"label": "M = 3", "report": "m3.json"},
                      {"label": "M = 4", "report": ["m4.json", "m4-top1.json"]}],
            "models": [["baseline", "baseline"], ["top1", "Top-1"]],
            "reference": [{"label": "paper: PSNR", "cells": ["32.97", "33.17", "33.07", "33.34"]}]}
    (data / "paper.json").write_text(json.dumps(spec))
    monkeypatch.setattr(tables, "DATA", data)
    assert tables.render("paper") == (
        "|  | M = 3: baseline | M = 3: Top-1 | M = 4: baseline | M = 4: Top-1 |\n"
        "|---|---|---|---|---|\n"
        "| PSNR | 34.671 | 34.287 | 34.427 | 34.900 |\n"
        "| vs baseline |  | -0.38 |  | +0.47 |\n"
        "| SSIM | 0.9859 | 0.9843 | 0.9859 | 0.9875 |\n"
        "| ‖w‖₀ | 2.25M | 4.33M | 2.25M | 3M |\n"
        "| GFLOPs / image | 2.834 | 1.739 | 2.834 | 2.000 |\n"
        "| GFLOPs vs baseline |  | 0.61x |  | 0.71x |\n"
        "| train, minutes | 6.3 | 10.8 | 6.5 | - |\n"
        "| paper: PSNR | 32.97 | 33.17 | 33.07 | 33.34 |\n")
    assert tables.reports_of(spec) == ["m3.json", "m4.json", "m4-top1.json"]
    spec["reference"][0]["cells"].pop()
    (data / "paper.json").write_text(json.dumps(spec))
    with pytest.raises(ValueError, match="want 4 string cells"):
        tables.render("paper")


def test_a_cost_table_gives_gflops_minutes_and_render_seconds_against_the_baseline(tmp_path, monkeypatch):
    """README's "Is it worth it?": one row per report, each cost as "baseline -> model (ratio)", "-" where a report
    has no training seconds."""
    def report(train: bool):
        extra = (lambda s: {"extra": {"train s": s}}) if train else (lambda s: {})
        return {"models": [
            {"name": "baseline", "psnr": 34.6709, "gflops_per_image": 2.8338, "seconds_per_image": 0.1396,
             **extra("363")},
            {"name": "top2", "psnr": 35.0249, "gflops_per_image": 2.7778, "seconds_per_image": 0.1901, **extra("803")}]}

    data = tmp_path / "data"
    data.mkdir()
    (data / "timed.json").write_text(json.dumps(report(True)))
    (data / "untimed.json").write_text(json.dumps(report(False)))
    (data / "costs.json").write_text(json.dumps({"first_column": "scene", "costs": {"model": "top2", "header": "Top-2",
        "rows": [{"label": "a", "report": "timed.json"}, {"label": "b", "report": "untimed.json"}]},
        "notes": [["c", "+0.30 dB", "55.56 -> 102.63 (1.85x)", "-", "-"]]}))
    monkeypatch.setattr(tables, "DATA", data)
    assert tables.render("costs").splitlines()[2:] == [
        "| a | +0.35 dB | 2.83 -> 2.78 (0.98x) | 6.0 -> 13.4 (2.21x) | 0.140 -> 0.190 (1.36x) |",
        "| b | +0.35 dB | 2.83 -> 2.78 (0.98x) | - | 0.140 -> 0.190 (1.36x) |",
        "| c | +0.30 dB | 55.56 -> 102.63 (1.85x) | - | - |"]
    assert tables.reports_of(json.loads((data / "costs.json").read_text())) == ["timed.json", "untimed.json"]
