#!/usr/bin/env python3
"""Seconds per finetuning step of a workspace's baseline and mixtures, side by side in one run.

    python scripts/train_step_bench.py -w WS [--model baseline --model top1 --model top2] [--steps 5] [--rounds 6]
                                       [--warmup 3] [--json FILE] [--table FILE]

Builds each model's training task from the workspace's moe/init and recipe as `boostnerf finetune` does (the baseline:
the largest expert alone; topK: the mixture routed to its K best experts; ens: every expert), at the recipe's batch
size, and times optimiser steps (`train.optimizer_step`: batch, loss, gradient, update), `--rounds` rounds of
`--steps` steps per model, the models interleaved round by round so a busy machine slows each alike, after `--warmup`
steps each. Prints per model the median seconds per step (wall; and the process's CPU seconds, which another busy
process disturbs less), their ratios to the first model's, and the samples per ray a step keeps. Nothing is written
to the workspace.
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

from boostnerf_cli.lineage import Survey  # noqa: E402
from boostnerf_cli.models import load_expert, load_mixture  # noqa: E402
from boostnerf_cli.recipe import recorded_recipe  # noqa: E402
from boostnerf_cli.stages import finetune  # noqa: E402
from boostnerf_cli.tasks import FieldTask, MixtureTask, train_rays  # noqa: E402
from boostnerf_cli.train import Schedule, optimizer_step  # noqa: E402
from boostnerf_cli.workspace import Workspace  # noqa: E402


def task_of(ws: Workspace, survey: Survey, name: str, rec, device: str):
    """`name`'s training task, as `stages.finetune.run` makes it."""
    scene = survey.scene()
    mix, _ = load_mixture(ws.model_path("init"), device)
    mix.train()
    if name == "baseline":
        model, occ, meta = load_expert(ws.expert_path(mix.cfg.expert_names[-1]), device)
        model.train()
        settings = scene.render_settings(meta["step"], model.bbox, rec.train.color_threshold)
        return FieldTask(model, settings, rec.train, skip=occ, base_mask=occ), train_rays(scene, model.bbox, device,
                                                                                         rec.train)
    topk = None if name == "ens" else int(name[3:])
    if name == "ens":
        mix.make_ensemble()
    cfg, _ = finetune.routing(name, topk, rec, mix.cfg, mix.gate.cfg.gate_type)
    mix.configure(**{k: getattr(cfg, k) for k in cfg.__dataclass_fields__})
    settings = scene.render_settings(mix.cfg.step, mix.bbox, rec.train.color_threshold)
    return MixtureTask(mix, settings, rec.train, rec), train_rays(scene, mix.bbox, device, rec.train)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--model", action="append", help="baseline, topK or ens, the first the reference "
                                                     "(default: baseline top1 top2)")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--table", type=Path)
    args = ap.parse_args(argv)
    ws = Workspace(args.workspace)
    survey = Survey(ws)
    rec = recorded_recipe(ws.manifest().get("recipe"), ws.manifest_path).moe
    names = args.model or ["baseline", "top1", "top2"]
    load = os.getloadavg()
    sched = Schedule.of(rec.iters, rec.train)
    runs = {}
    for name in names:
        task, rays = task_of(ws, survey, name, rec, "cpu")
        runs[name] = {"task": task, "rays": rays, "opt": None, "gen": torch.Generator().manual_seed(0), "step": 0,
                      "seconds": [], "cpu": [], "samples": []}

    def steps(run: dict, n: int, timed: bool) -> None:
        for _ in range(n):
            t, c = time.perf_counter(), time.process_time()
            run["opt"], step = optimizer_step(run["task"], run["rays"], sched, run["opt"], run["gen"], run["step"],
                                              False)
            if timed:
                run["seconds"].append(time.perf_counter() - t)
                run["cpu"].append(time.process_time() - c)
                run["samples"].append(float(step.logs.get("samples", 0.0)))
            run["step"] += 1

    for run in runs.values():
        steps(run, args.warmup, False)
    for _ in range(args.rounds):
        for run in runs.values():
            steps(run, args.steps, True)
    ref = statistics.median(runs[names[0]]["seconds"])
    ref_cpu = statistics.median(runs[names[0]]["cpu"])
    rows = [{"model": name, "seconds_per_step": statistics.median(r["seconds"]),
             "vs": statistics.median(r["seconds"]) / ref, "cpu_seconds_per_step": statistics.median(r["cpu"]),
             "cpu_vs": statistics.median(r["cpu"]) / ref_cpu, "samples_per_ray": statistics.median(r["samples"])}
            for name, r in runs.items()]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    print(f"{ws.root}: batch {sched.batch_rays} rays, {args.rounds} x {args.steps} steps a model after {args.warmup}, "
          f"{torch.get_num_threads()} threads, commit {commit}, load average {load[0]:.2f} at start, "
          f"{os.getloadavg()[0]:.2f} at end")
    columns = ["model", "s / step", f"vs {names[0]}", "CPU s / step", f"vs {names[0]}", "samples / ray"]
    table = [[r["model"], f"{r['seconds_per_step']:.4f}", f"{r['vs']:.2f}x", f"{r['cpu_seconds_per_step']:.4f}",
              f"{r['cpu_vs']:.2f}x", f"{r['samples_per_ray']:.1f}"] for r in rows]
    print("| " + " | ".join(columns) + " |\n|" + "---|" * len(columns))
    for row in table:
        print("| " + " | ".join(row) + " |")
    if args.json:
        args.json.write_text(json.dumps({"workspace": str(ws.root), "commit": commit, "load_average": load,
                                         "threads": torch.get_num_threads(), "rows": rows}, indent=1) + "\n")
    if args.table:
        args.table.write_text(json.dumps({"columns": columns, "rows": table}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
