#!/usr/bin/env python3
"""Rebuild the result tables of README.md, docs/*.md and research/README.md from the JSON reports under docs/data/.

A table in a markdown file sits between two HTML comments and is generated from docs/data/NAME.json:

    <!-- table: NAME -->
    | model | PSNR | ... |
    <!-- /table -->

`python scripts/tables.py` rewrites every such table in README.md, docs/*.md and research/README.md; `--check`
rewrites nothing and exits 1 naming the tables that differ from their data (tests/test_tables.py runs it).
docs/data/NAME.json is one of:

- a raw `boostnerf eval --report` file (`WS/reports/eval.json`, copied as is): one row per model;
- a raw `boostnerf bench` table (`WS/reports/bench.json`): the bench's columns;
- a table spec {"groups": [...], "extra_columns": [...], "note": ...}, each group
  {"label": str, "report": "FILE.json"} (a raw eval report under docs/data/, or a list of them read as one
  report, optionally "models": [names])
  or {"label": str, "models": [rows]} with rows of the eval report's schema (name, psnr, ssim, w0,
  gflops_per_image; null when not measured) transcribed by hand, plus "extra": {column: text}.

- a table in the paper's appendix layout {"sizes": [{"label": "M = 3", "report": FILE or [FILEs]}, ...],
  "models": [[name, header], ...], "reference": [{"label": str, "cells": [str, ...]}, ...]}: one column per size
  and model (the paper's baseline / Top-1 / Top-2 / Ens under each M), one row per measure (PSNR, its
  difference to the size's baseline, SSIM, ||w||_0, GFLOPs per image and their ratio to the baseline's, and
  training minutes from the reports' "train s" extra), then the reference rows printed as written (the
  paper's own figures);

- a summary {"summary": {"models": [[name, header], ...], "rows": [{"label": str, "report": FILE}, ...],
  "experts": header}, "first_column": header, "notes": [[cell, ...], ...]}: one row per report, a column of the
  experts' PSNRs (with "experts"), one column per model: the baseline's PSNR, every other model's PSNR against it
  and its GFLOPs per image as a ratio of the baseline's; then the notes rows printed as written (figures no report
  of this layout holds: transcribed, each with its provenance);

- a cost table {"costs": {"model": name, "rows": [{"label": str, "report": FILE or [FILEs]}, ...]},
  "first_column": header, "notes": [[cell, ...], ...]}: one row per report, the model's PSNR against the baseline's,
  then its GFLOPs per image, training minutes (the reports' "train s" extra; "-" where a report has none) and render
  seconds per image, each as "baseline -> model (ratio)"; a row's "seconds": FILE (the `--json` of
  scripts/render_profile.py, the models timed side by side) gives its render seconds instead of the report's; then
  the notes rows printed as written;

- a generic table {"columns": [header, ...], "rows": [[cell, ...], ...]} for a table that is neither a
  model nor a bench table (a transcribed comparison, a list of targets): every cell is a string printed
  exactly as written (bold `**...**`, units and all), and each row has as many cells as there are columns.

Model tables have the columns model, PSNR, vs baseline, SSIM, ||w||_0, GFLOPs / image and then the
extra columns; "vs baseline" is each row's PSNR minus its group's baseline row (the row named
"baseline", or the group's "baseline": NAME). A value given as a string is printed as written (a
transcribed figure keeps the precision it was noted with); null prints "-".
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
DATA = DOCS / "data"
BLOCK = re.compile(r"(<!-- table: (?P<name>[\w.-]+) -->\n)(?P<body>.*?)(<!-- /table -->)", re.S)
MODEL_COLUMNS = ["model", "PSNR", "vs baseline", "SSIM", "‖w‖₀", "GFLOPs / image"]
BENCH_COLUMNS = ["name", "group", "PSNR", "SSIM", "train s", "s/image", "GFLOPs/image", "params", "‖w‖₀"]


def _num(v, decimals: int) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    return f"{v:.{decimals}f}"


def _count(v, compact: bool) -> str:
    """A parameter count: 1,072,525 (or 1.07M / 594k when `compact`)."""
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if not compact:
        return f"{int(v):,}"
    if v >= 1e6:
        return f"{v / 1e6:.3g}M"
    return f"{v / 1e3:.3g}k" if v >= 1e3 else str(int(v))


def _psnr(v) -> float | None:
    return None if v is None else float(v)


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _table(columns: list[str], rows: list[list[str]]) -> str:
    return "\n".join([_row(columns), "|" + "---|" * len(columns), *(_row(r) for r in rows)]) + "\n"


def _group(label: str, models: list[dict], every: list[dict], baseline: str) -> dict:
    return {"label": label, "models": models, "base": next((m for m in every if m["name"] == baseline), None)}


def _files(group: dict) -> list[str]:
    """The report files a group (or a size) reads: "report" as one name or a list of them."""
    report = group.get("report", [])
    return report if isinstance(report, list) else [report]


def reports_of(spec: dict) -> list[str]:
    """Every docs/data file that a table spec reads."""
    parts = (spec.get("groups", []) + spec.get("sizes", []) + spec.get("summary", {}).get("rows", [])
             + spec.get("costs", {}).get("rows", []))
    return [f for g in parts for f in _files(g)] + [g["seconds"] for g in parts if "seconds" in g]


def _read(files: list[str]) -> dict:
    """The models of one report, or of several read as one (a later file's model replaces a same-named one)."""
    return {m["name"]: m for f in files for m in json.loads((DATA / f).read_text())["models"]}


def _groups(spec: dict) -> list[dict]:
    """The table's groups, each {"label", "base": the baseline's eval-report row or None, "models": [rows]}.

    The baseline is looked up among every model the group reads, so a group may show its mixtures alone and
    still give their PSNR against a baseline that another row already shows."""
    if "models" in spec and "groups" not in spec:  # a raw eval report
        return [_group("", spec["models"], spec["models"], spec.get("baseline", "baseline"))]
    groups = []
    for g in spec["groups"]:
        models = every = g.get("models")
        if "report" in g:  # one report, or several whose models are read as one (later names win)
            by_name = _read(_files(g))
            every = list(by_name.values())
            models = [by_name[n] for n in models] if models else every
        groups.append(_group(g.get("label", ""), models, every, g.get("baseline", "baseline")))
    return groups


def model_table(spec: dict) -> str:
    extra = spec.get("extra_columns", [])
    compact = spec.get("compact_counts", False)
    rows = []
    for g in _groups(spec):
        base = g["base"]
        for m in g["models"]:
            psnr, ref = _psnr(m.get("psnr")), _psnr(base.get("psnr")) if base is not None else None
            delta = "" if m is base or psnr is None or ref is None else f"{psnr - ref:+.2f}"
            name = m.get("label", m["name"])
            rows.append([f"{g['label']}: {name}" if g["label"] else name, _num(m.get("psnr"), 3), delta,
                         _num(m.get("ssim"), 4), _count(m.get("w0"), compact), _num(m.get("gflops_per_image"), 3),
                         *(str(m.get("extra", {}).get(c, "")) for c in extra)])
    return _table(MODEL_COLUMNS + extra, rows)


def size_table(spec: dict) -> str:
    """The paper's appendix layout: a column per (size, model), a row per measure."""
    columns, cells = [""], {k: [] for k in ("PSNR", "vs baseline", "SSIM", "‖w‖₀", "GFLOPs / image",
                                             "GFLOPs vs baseline", "train, minutes")}
    for size in spec["sizes"]:
        by_name = _read(_files(size))
        base = by_name.get(size.get("baseline", "baseline"))
        for name, header in spec["models"]:
            m = by_name[name]
            columns.append(f"{size['label']}: {header}")
            psnr, flops = _psnr(m.get("psnr")), m.get("gflops_per_image")
            ref_psnr = _psnr(base.get("psnr")) if base else None
            ref_flops = base.get("gflops_per_image") if base else None
            compare = m is not base and base is not None
            seconds = m.get("extra", {}).get("train s")
            cells["PSNR"].append(_num(psnr, 3))
            cells["vs baseline"].append(f"{psnr - ref_psnr:+.2f}" if compare and None not in (psnr, ref_psnr) else "")
            cells["SSIM"].append(_num(m.get("ssim"), 4))
            cells["‖w‖₀"].append(_count(m.get("w0"), True))
            cells["GFLOPs / image"].append(_num(flops, 3))
            cells["GFLOPs vs baseline"].append(f"{flops / ref_flops:.2f}x" if compare and flops and ref_flops else "")
            cells["train, minutes"].append("-" if seconds is None else f"{float(seconds) / 60:.1f}")
    rows = [[k, *v] for k, v in cells.items()]
    for ref in spec.get("reference", []):
        if len(ref["cells"]) != len(columns) - 1 or not all(isinstance(c, str) for c in ref["cells"]):
            raise ValueError(f"reference row {ref['label']!r}: want {len(columns) - 1} string cells")
        rows.append([ref["label"], *ref["cells"]])
    return _table(columns, rows)


def summary_table(spec: dict) -> str:
    """One row per report: the baseline's PSNR, then each model's PSNR and GFLOPs against the baseline's."""
    models, experts = spec["summary"]["models"], spec["summary"].get("experts")
    columns = [spec.get("first_column", ""), *([experts] if experts else []), *(header for _, header in models)]
    rows = []
    for line in spec["summary"]["rows"]:
        by_name = _read(_files(line))
        base = by_name[line.get("baseline", "baseline")]
        cells = []
        if experts:  # the experts trained alone (every expert of the report but the baseline), smallest first
            alone = [m for m in by_name.values() if m.get("kind") == "expert" and m is not base]
            cells.append(" / ".join(f"{m['psnr']:.2f}" for m in alone) + " dB")
        for name, _ in models:
            m = by_name[name]
            if m is base:
                cells.append(f"{m['psnr']:.2f} dB")
            else:
                ratio = m["gflops_per_image"] / base["gflops_per_image"]
                cells.append(f"{m['psnr'] - base['psnr']:+.2f} dB at {ratio:.2f}x")
        rows.append([line["label"], *cells])
    for note in spec.get("notes", []):
        if len(note) != len(columns) or not all(isinstance(c, str) for c in note):
            raise ValueError(f"summary note {note!r}: want {len(columns)} string cells")
        rows.append(note)
    return _table(columns, rows)


COST_COLUMNS = ["vs baseline", "GFLOPs / image: baseline -> {m}", "training, minutes: baseline -> {m}",
                "render, s / image: baseline -> {m}"]


def _pair(base, model, decimals: int) -> str:
    """`base -> model (ratio)`, or "-" when either is missing."""
    if base is None or model is None:
        return "-"
    return f"{base:.{decimals}f} -> {model:.{decimals}f} ({model / base:.2f}x)"


def cost_table(spec: dict) -> str:
    """One row per report: what the model gains over the baseline and what it costs, in GFLOPs and in seconds."""
    name = spec["costs"]["model"]
    header = spec["costs"].get("header", name)
    columns = [spec.get("first_column", ""), *(c.format(m=header) for c in COST_COLUMNS)]
    rows = []
    for line in spec["costs"]["rows"]:
        by_name = _read(_files(line))
        n = line.get("baseline", "baseline")
        base, m = by_name[n], by_name[name]

        def minutes(model):
            s = model.get("extra", {}).get("train s")
            return None if s is None else float(s) / 60

        seconds = {n: base.get("seconds_per_image"), name: m.get("seconds_per_image")} if "seconds" not in line else {
            r["model"]: r["seconds"] for r in json.loads((DATA / line["seconds"]).read_text())["rows"]}
        rows.append([line["label"], f"{m['psnr'] - base['psnr']:+.2f} dB",
                     _pair(base["gflops_per_image"], m["gflops_per_image"], 2 if base["gflops_per_image"] < 20 else 1),
                     _pair(minutes(base), minutes(m), 1),
                     _pair(seconds.get(n), seconds.get(name), 3)])
    for note in spec.get("notes", []):
        if len(note) != len(columns) or not all(isinstance(c, str) for c in note):
            raise ValueError(f"cost note {note!r}: want {len(columns)} string cells")
        rows.append(note)
    return _table(columns, rows)


def bench_table(spec: dict) -> str:
    rows = [[r["name"], r["group"], _num(r["psnr"], 3), _num(r["ssim"], 4), f"{r['train_seconds']:.0f}",
             _num(r["seconds_per_image"], 3), _num(r["gflops_per_image"], 3), _count(r["params"], False),
             _count(r["w0"], False)] for r in spec["rows"]]
    return _table(BENCH_COLUMNS, rows)


def generic_table(spec: dict) -> str:
    columns, rows = spec["columns"], spec["rows"]
    for r in rows:
        if len(r) != len(columns) or not all(isinstance(c, str) for c in r):
            raise ValueError(f"generic table row {r!r}: want {len(columns)} string cells")
    return _table(columns, rows)


def render(name: str) -> str:
    spec = json.loads((DATA / f"{name}.json").read_text())
    if "suite" in spec:
        return bench_table(spec)
    if "columns" in spec:
        return generic_table(spec)
    if "sizes" in spec:
        return size_table(spec)
    if "summary" in spec:
        return summary_table(spec)
    if "costs" in spec:
        return cost_table(spec)
    return model_table(spec)


def rebuild(text: str) -> tuple[str, list[str]]:
    """`text` with every marked table regenerated -> (new text, names of the tables that changed)."""
    changed = []

    def one(m: re.Match) -> str:
        body = render(m["name"])
        if body != m["body"]:
            changed.append(m["name"])
        return m.group(1) + body + m.group(4)

    return BLOCK.sub(one, text), changed


def documents() -> list[Path]:
    """The markdown files whose tables this script makes: README.md, docs/*.md and research/README.md."""
    return [ROOT / "README.md", *sorted(DOCS.glob("*.md")), ROOT / "research" / "README.md"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 if a table differs from its data")
    args = ap.parse_args(argv)
    stale = []
    for md in documents():
        text = md.read_text()
        new, changed = rebuild(text)
        stale += [f"{md.relative_to(ROOT)}: {n}" for n in changed]
        if changed and not args.check:
            md.write_text(new)
    if stale:
        print(("differs from docs/data: " if args.check else "rebuilt: ") + ", ".join(stale))
    return 1 if stale and args.check else 0


if __name__ == "__main__":
    sys.exit(main())
