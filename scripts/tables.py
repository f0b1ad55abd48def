#!/usr/bin/env python3
"""Rebuild the result tables of docs/*.md from the JSON reports under docs/data/.

A table in a markdown file sits between two HTML comments and is generated from docs/data/NAME.json:

    <!-- table: NAME -->
    | model | PSNR | ... |
    <!-- /table -->

`python scripts/tables.py` rewrites every such table in docs/*.md; `--check` rewrites nothing and exits
1 naming the tables that differ from their data (tests/test_tables.py runs it). docs/data/NAME.json is
one of:

- a raw `boostnerf eval --report` file (`WS/reports/eval.json`, copied as is): one row per model;
- a raw `boostnerf bench` table (`WS/reports/bench.json`): the bench's columns;
- a table spec {"groups": [...], "extra_columns": [...], "note": ...}, each group
  {"label": str, "report": "FILE.json"} (a raw eval report under docs/data/, or a list of them read as one
  report, optionally "models": [names])
  or {"label": str, "models": [rows]} with rows of the eval report's schema (name, psnr, ssim, w0,
  gflops_per_image; null when not measured) transcribed by hand, plus "extra": {column: text}.

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
            files = g["report"] if isinstance(g["report"], list) else [g["report"]]
            by_name = {m["name"]: m for f in files for m in json.loads((DATA / f).read_text())["models"]}
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 if a table differs from its data")
    args = ap.parse_args(argv)
    stale = []
    for md in sorted(DOCS.glob("*.md")):
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
