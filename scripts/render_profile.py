#!/usr/bin/env python3
"""Where the seconds of rendering an image go, per model, side by side in one run.

    python scripts/render_profile.py -w WS [--model NAME ...] [--views 4] [--repeats 5] [--device cpu]
                                     [--json FILE] [--table FILE]

For each model (default: the workspace's baseline, top1 and top2, those that exist), after one warm-up image (not
counted: it sizes the packing budgets, compiles and fills caches), renders the first `--views` test views
`--repeats` times, the models interleaved round by round so that a busy machine slows each alike, and reports per
image: the median wall time (`seconds`), its ratio to the first model's, the same for the process's CPU time
(`cpu_seconds`: what another busy process disturbs less), GFLOPs and their ratio, the throughput
(GFLOPs / seconds), and the milliseconds of each part of the render (boostnerf_cli/render/timing.py, measured in
one more, timed pass): rays, sampling, skipping (the occupancy grid and packing; `V_D` the density volume),
routing (the gate's lookup and top-k), dispatch (listing each expert's samples and adding its outputs back), each
expert's field (`expert E`, E its index in the mixture; a single model's own field is `field density` and
`field color`; a mixture's own work around its experts counts there too), compositing. `--json` writes the rows;
`--table` a generic table for docs/data (`python scripts/tables.py` prints it in docs/performance.md).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from boostnerf_cli import flops  # noqa: E402
from boostnerf_cli.lineage import Survey  # noqa: E402
from boostnerf_cli.models import ALL_SKIPS, load_model  # noqa: E402
from boostnerf_cli.render import timing  # noqa: E402
from boostnerf_cli.render.packing import packer_for  # noqa: E402
from boostnerf_cli.render.renderer import render_view  # noqa: E402
from boostnerf_cli.stages.common import resolve_device  # noqa: E402
from boostnerf_cli.workspace import Workspace  # noqa: E402

PARTS = ("rays", "sampling", "skipping", "V_D", "routing", "dispatch", "field density", "field color", "compositing")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--model", action="append", help="model(s), the first the reference (default: baseline top1 top2)")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--split", default="test")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--blend", action="store_true",
                    help="also each mixture as NAME/blend: every sample blended, no decision per cell (moe/cells.py)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--table", type=Path)
    args = ap.parse_args(argv)
    ws = Workspace(args.workspace)
    device = resolve_device(args.device)
    scene = Survey(ws).scene()
    split = scene.split(args.split)
    names = args.model or [n for n in ("baseline", "top1", "top2") if ws.model_file(n).exists()]
    load = os.getloadavg()
    t0 = time.perf_counter()
    models = {}
    variants = [(n, False) for n in names] + ([(n, True) for n in names] if args.blend else [])
    for name, blend in variants:
        t = time.perf_counter()
        model = load_model(ws, name, device)
        if blend and model.kind != "mixture":
            continue
        if blend:
            model.field.cells = lambda: None  # this instance blends every sample
            name = f"{name}/blend"
        settings, skip = model.render_setup(scene, ALL_SKIPS)
        packer = packer_for(device)
        render_view(model.field, split, 0, settings, skip, device, packer)  # the warm-up
        models[name] = (model, settings, skip, packer, time.perf_counter() - t)
    views = min(args.views, len(split))
    seconds: dict[str, list[float]] = {name: [] for name in models}
    cpu: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.repeats):
        for name, (model, settings, skip, packer, _) in models.items():
            for i in range(views):
                if device == "cuda":
                    torch.cuda.synchronize()
                t, c = time.perf_counter(), time.process_time()
                render_view(model.field, split, i, settings, skip, device, packer)
                if device == "cuda":
                    torch.cuda.synchronize()
                seconds[name].append(time.perf_counter() - t)
                cpu[name].append(time.process_time() - c)
    rows = []
    for name, (model, settings, skip, packer, setup) in models.items():
        with flops.count_flops() as counted:
            render_view(model.field, split, 0, settings, skip, device, packer)
        with timing.parts(device) as parts:
            for i in range(views):
                render_view(model.field, split, i, settings, skip, device, packer)
        sec = statistics.median(seconds[name])
        gflops = counted.total / 1e9
        rows.append({"model": name, "seconds": sec, "cpu_seconds": statistics.median(cpu[name]), "gflops": gflops,
                     "gflop_per_s": gflops / sec,
                     "setup_seconds": setup, "ms": {k: 1000 * v / views for k, v in parts.items()}})
    ref = rows[0]
    for r in rows:
        r["seconds_ratio"], r["gflops_ratio"] = r["seconds"] / ref["seconds"], r["gflops"] / ref["gflops"]
        r["cpu_ratio"] = r["cpu_seconds"] / ref["cpu_seconds"]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    print(f"{ws.root}: {split.width}x{split.height} px, {views} views x {args.repeats}, on {device}, "
          f"{torch.get_num_threads()} threads, commit {commit}, load average {load[0]:.2f} at start, "
          f"{os.getloadavg()[0]:.2f} at end ({time.perf_counter() - t0:.0f} s)")
    extra = sorted({k for r in rows for k in r["ms"]} - set(PARTS))
    columns = ["model", "s / image", "vs " + ref["model"], "CPU s / image", "vs " + ref["model"], "GFLOPs",
               "vs " + ref["model"], "GFLOP/s",
               *[f"{p} ms" for p in PARTS if any(p in r["ms"] for r in rows)], *[f"{p} ms" for p in extra]]
    keys = [c[:-3] for c in columns[8:]]
    table = [[r["model"], f"{r['seconds']:.4f}", f"{r['seconds_ratio']:.2f}x", f"{r['cpu_seconds']:.4f}",
              f"{r['cpu_ratio']:.2f}x", f"{r['gflops']:.3f}", f"{r['gflops_ratio']:.2f}x", f"{r['gflop_per_s']:.1f}",
              *[f"{r['ms'][k]:.1f}" if k in r["ms"] else "-" for k in keys]] for r in rows]
    print("| " + " | ".join(columns) + " |\n|" + "---|" * len(columns))
    for row in table:
        print("| " + " | ".join(row) + " |")
    if args.json:
        args.json.write_text(json.dumps({"workspace": str(ws.root), "device": device, "commit": commit,
                                         "threads": torch.get_num_threads(), "load_average": load,
                                         "views": views, "repeats": args.repeats, "rows": rows}, indent=1) + "\n")
    if args.table:
        args.table.write_text(json.dumps({"columns": columns, "rows": table}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
