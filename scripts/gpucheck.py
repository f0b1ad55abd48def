#!/usr/bin/env python3
"""What scripts/gpu-check.sh and scripts/paper-check.sh share: their settings per scale, the recipes they derive, a
CLI wrapper that reports compile time, a utilisation sampler, and the tables they print.

    python scripts/gpucheck.py settings SCRIPT SCALE           SCALES[SCRIPT][SCALE]["script"] as shell assignments
                                                               (a variable the environment sets is kept)
    python scripts/gpucheck.py recipe SCRIPT SCALE BASE OUT    BASE (a recipe file) with the scale's overrides -> OUT;
                                                               prints the experts' resolutions
    python scripts/gpucheck.py device DEVICE                   one line: the device's name, torch, CUDA, the date
    python scripts/gpucheck.py cli ARGS...                     `boostnerf ARGS...`, then one line on stderr: the seconds
                                                               torch.compile spent in the process
    python scripts/gpucheck.py sample-cpu FILE                 CPU utilisation every 0.5 s, in nvidia-smi's CSV format
    python scripts/gpucheck.py stage OUT NAME STATUS T0 T1 LOG record a finished stage, print its OK/FAIL line
    python scripts/gpucheck.py summary OUT                     the stages with their GPU utilisation -> OUT/stages.md
    python scripts/gpucheck.py models OUT/FILE.md --recipe R --model NAME WS STAGE ...   the held-out table
    python scripts/gpucheck.py table TABLE.json FILE.md TITLE  append a generic table (the oracle's, step_profile's)
    python scripts/gpucheck.py plan SCRIPT SCALE RECIPE SCENE PLAN.json   paper-check's joint steps -> PLAN.json
    python scripts/gpucheck.py describe-plan PLAN.json         the plan in words and numbers
    python scripts/gpucheck.py pack OUT FILE.tar.gz            the logs, reports and tables of OUT, no models

Utilisation samples are lines `TIMESTAMP, INDEX, UTIL %, MEMORY MiB` (nvidia-smi --query-gpu=timestamp,index,
utilization.gpu,memory.used --format=csv,noheader,nounits; TIMESTAMP as `2026/11/26 12:00:00.123`, local time), so
that the CPU sampler's lines (DEVICE=cpu: the CPU's busy share and the host memory used) go through the same code.
A stage's window is its start and end, in seconds since the epoch (bash's EPOCHREALTIME).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shlex
import sys
import tarfile
import time
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parent

def merged(base: dict, over: dict) -> dict:
    """`base` with `over`'s keys set, mappings merged key by key (a list or a value replaces)."""
    out = dict(base)
    for key, value in over.items():
        out[key] = merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


# --- the settings of each script at each scale (the only place the tiny settings live) -----------------------------
# "recipe": overrides merged into the recipe the script starts from; "script": the script's own settings, given to
# it as shell variables (`settings`). "full" is the GPU run; "tiny" the CPU check of the script's logic
# (DEVICE=cpu SCALE=tiny): small images, few steps, a few minutes on two cores.
_TINY_TRAIN = {"batch_rays": 1024, "log_every": 20, "checkpoint_every": 40, "occupancy_every": 40}
_TINY_CHAIN = {"data": {"image_size": 40},
               "pretrain": {"res": [12, 16, 20], "iters": 200, "train": _TINY_TRAIN,
                            "geometry": {"res": 12, "iters": 100, "batch_rays": 1024}},
               "moe": {"gate_res": 12, "train": {"batch_rays": 1024, "log_every": 20, "checkpoint_every": 40}}}
SCALES: dict[str, dict[str, dict]] = {
    "gpu-check-a": {  # part (a): the base is PART_A below, per family
        "full": {"recipe": {}, "script": {}},
        "tiny": {"recipe": {"moe": {"iters": 40}}, "script": {}},  # experts as trained as on the GPU: V_D needs them
    },
    "gpu-check-b": {  # part (b): recipes/blender-dvgo-paper-gpucheck.yaml
        "full": {"recipe": {"pretrain": {"train": {"log_every": 250}},
                            "moe": {"iters": 1000, "train": {"log_every": 250}}},
                 "script": {"BUDGET_S": 480, "COST_VIEWS": 2, "ORACLE_ARGS": "--map-res 16,32 --train-views 24",
                            "PROFILE_ARGS": "--steps 20 --warmup 5 --compile on"}},
        "tiny": {"recipe": merged(_TINY_CHAIN, {"pretrain": {"iters": 60}, "moe": {"iters": 40}}),
                 "script": {"BUDGET_S": 1500, "COST_VIEWS": 1, "ORACLE_ARGS": "--map-res 4,8 --train-views 4",
                            "PROFILE_ARGS": "--kinds dvgo,top2 --steps 2 --warmup 1"}},
    },
    "paper-check": {  # recipes/blender-dvgo-paper-official.yaml; the F_* and SPEED: plan_chain
        "full": {"recipe": {},
                 "script": {"BUDGET_S": 540, "FIXED_S": 120, "SPEED": 1, "F_MIN": 1000, "F_ROUND": 100,
                            "COST_VIEWS": 2, "ORACLE_MAP_RES": "16,32", "ORACLE_TRAIN_VIEWS": 8}},
        "tiny": {"recipe": merged(_TINY_CHAIN, {"pretrain": {"iters": 60}, "moe": {"iters": 60}}),
                 "script": {"BUDGET_S": 400, "FIXED_S": 120, "SPEED": 0.001, "F_MIN": 20, "F_ROUND": 10,
                            "COST_VIEWS": 1, "ORACLE_MAP_RES": "4,8", "ORACLE_TRAIN_VIEWS": 4}},
    },
}

# Part (a)'s tiny recipe per family (48 px generated scene): every stage runs, nothing is measured.
PART_A_ARCH = {
    "dvgo": ("16,24", {"dvgo": {"hidden": 32, "layers": 1}}),
    "tensorf": ("16,24", {"tensorf": {"hidden": 32, "layers": 1, "density_rank": 4, "app_rank": 8, "app_dim": 12}}),
    "ngp": ("4,6", {"ngp": {"hidden": 32, "log2_table": 12, "base_res": 4, "max_res": 48, "grid_res": 32}}),
}


def part_a_recipe(family: str) -> dict:
    res, arch = PART_A_ARCH[family]
    return {
        "data": {"image_size": 48, "holdout_every": 8},
        "pretrain": {"model": family, "res": [int(r) for r in res.split(",")], "iters": 200,
                     "geometry": {"res": 16, "iters": 200, "batch_rays": 1024},
                     "train": {"batch_rays": 1024, "checkpoint_every": 100, "occupancy_every": 100}, **arch},
        "moe": {"gate_res": 12, "iters": 100, "train": {"batch_rays": 1024, "checkpoint_every": 50}},
    }


def settings(script: str, scale: str, env: dict | None = None) -> dict:
    """SCALES[script][scale]["script"], each value replaced by the environment's variable of that name if set."""
    env = os.environ if env is None else env
    return {k: env.get(k, v) for k, v in SCALES[script][scale]["script"].items()}


def shell_assignments(values: dict) -> str:
    """`NAME=value` lines for bash's eval (values quoted)."""
    return "".join(f"{k}={shlex.quote(str(v))}\n" for k, v in values.items())


# --- a stage's log: its `ready in` lines, its compile time ------------------------------------------------------------
READY = re.compile(r"(?P<what>[\w.@-]+): ready in (?P<s>[\d.]+) s(?: \((?P<parts>[^)]*)\))?")
COMPILED = re.compile(r"gpucheck: torch\.compile took (?P<s>[\d.]+) s")


def ready_lines(text: str) -> list[dict]:
    """Every `NAME: ready in X s (parts)` line of a stage's log, in order."""
    return [{"what": m["what"], "seconds": float(m["s"]), "parts": m["parts"] or ""} for m in READY.finditer(text)]


def ready_text(ready: list[dict]) -> str:
    return "; ".join(f"{r['what']} {r['seconds']:.1f} s" + (f" ({r['parts']})" if r["parts"] else "") for r in ready)


def compile_seconds(text: str) -> float | None:
    """The seconds torch.compile took in the stage's processes (their `cli` wrapper lines, summed); None: no line."""
    found = [float(m["s"]) for m in COMPILED.finditer(text)]
    return sum(found) if found else None


def run_cli(args: list[str]) -> None:
    """`boostnerf ARGS`, and at exit one stderr line with the wall time torch.compile took in this process (dynamo's
    own count: every frame's compile, forward and backward, inductor's code generation included)."""
    import atexit

    def say() -> None:
        utils = sys.modules.get("torch._dynamo.utils")  # never imported: nothing was compiled
        seconds = 0.0
        if utils is not None:
            try:
                seconds = float(utils.calculate_time_spent().get("total_wall_time", 0.0))
            except Exception:  # another torch's internals: say nothing rather than a wrong figure
                return
        print(f"gpucheck: torch.compile took {seconds:.1f} s in this process", file=sys.stderr, flush=True)

    atexit.register(say)
    sys.argv = ["boostnerf", *args]
    from boostnerf_cli.cli import main

    main()


def device_line(device: str) -> str:
    """`NVIDIA H200; torch 2.11.0+cu130 (CUDA 13.0); 2026-11-26`: what ran the check, and when."""
    import datetime

    import torch

    name = torch.cuda.get_device_name(0) if device == "cuda" else "CPU (DEVICE=cpu)"
    return f"{name}; torch {torch.__version__} (CUDA {torch.version.cuda}); {datetime.date.today()}"


# --- utilisation samples --------------------------------------------------------------------------------------------
def stamp(t: float) -> str:
    """Seconds since the epoch as nvidia-smi writes its timestamp (local time, milliseconds)."""
    return time.strftime("%Y/%m/%d %H:%M:%S", time.localtime(t)) + f".{int((t % 1) * 1000):03d}"


def parse_samples(text: str, index: int = 0) -> list[tuple[float, float, float]]:
    """(time, utilisation %, memory MiB) of device `index`, from sampler lines; lines that do not parse (a header,
    `[N/A]`, a line cut by the sampler's end) are left out."""
    out = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != 4:
            continue
        try:
            day, _, frac = cells[0].partition(".")
            t = time.mktime(time.strptime(day, "%Y/%m/%d %H:%M:%S")) + (float("0." + frac) if frac else 0.0)
            if int(cells[1]) != index:
                continue
            out.append((t, float(cells[2]), float(cells[3])))
        except ValueError:
            continue
    return out


def window_stats(samples: list[tuple[float, float, float]], t0: float, t1: float) -> dict | None:
    """Mean and max utilisation and max memory over the samples taken in [t0, t1]; a window shorter than the
    sampling period takes the sample nearest its middle. None without samples."""
    inside = [s for s in samples if t0 <= s[0] <= t1]
    if not inside and samples:
        mid = (t0 + t1) / 2
        nearest = min(samples, key=lambda s: abs(s[0] - mid))
        inside = [nearest] if abs(nearest[0] - mid) <= 1.0 + (t1 - t0) / 2 else []
    if not inside:
        return None
    utils = [s[1] for s in inside]
    return {"mean": sum(utils) / len(utils), "max": max(utils), "mem_max": max(s[2] for s in inside),
            "samples": len(inside)}


def sample_cpu(path: Path, period: float = 0.5) -> None:
    """Write the CPU's busy share (all cores, from /proc/stat) and the host memory used, every `period` seconds, as
    nvidia-smi's lines, until killed: the stand-in for the GPU sampler when DEVICE=cpu."""

    def jiffies() -> tuple[int, int]:
        cells = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        idle = cells[3] + (cells[4] if len(cells) > 4 else 0)
        return sum(cells), idle

    def used_mib() -> float:
        info = dict(line.split(":", 1) for line in Path("/proc/meminfo").read_text().splitlines() if ":" in line)
        kib = lambda k: int(info[k].split()[0])  # noqa: E731
        return (kib("MemTotal") - kib("MemAvailable")) / 1024

    with path.open("a") as f:
        total, idle = jiffies()
        while True:
            time.sleep(period)
            t2, i2 = jiffies()
            busy = 100.0 * (1 - (i2 - idle) / max(1, t2 - total))
            total, idle = t2, i2
            f.write(f"{stamp(time.time())}, 0, {busy:.0f}, {used_mib():.0f}\n")
            f.flush()


# --- stages ---------------------------------------------------------------------------------------------------------
def read_stages(out: Path) -> list[dict]:
    """OUT/stages.tsv: one line per finished stage, NAME STATUS T0 T1 LOG (tab-separated; LOG relative to OUT, so
    that a call's records moved aside together keep their logs)."""
    path = out / "stages.tsv"
    rows = []
    for line in path.read_text().splitlines() if path.exists() else []:
        name, status, t0, t1, log = line.split("\t")
        rows.append({"name": name, "status": status, "t0": float(t0), "t1": float(t1), "log": str(out / log)})
    return rows


def read_samples(out: Path) -> list[tuple[float, float, float]]:
    util = out / "util.csv"
    return parse_samples(util.read_text()) if util.exists() else []


def _log_text(stage: dict) -> str:
    path = Path(stage["log"])
    return path.read_text(errors="replace") if path.exists() else ""


def stage_line(name: str, status: str, seconds: float, log_text: str) -> str:
    """The line a stage prints when it ends: status, name, wall time, its `ready in` lines and compile time."""
    ready = ready_lines(log_text)
    compiled = compile_seconds(log_text)
    line = f"{status:<5} {name:<38} {seconds:6.1f}s"
    if ready:
        line += f"  ready: {ready_text(ready)}"
    if compiled:
        line += f"  compile {compiled:.1f} s"
    if status in ("FAIL", "CUT"):
        last = [ln for ln in log_text.splitlines() if ln.strip() and not COMPILED.match(ln)]
        line += f"  ({last[-1].strip() if last else 'no output'})"
    return line


def record_stage(out: Path, name: str, status: str, t0: float, t1: float, log: Path) -> str:
    rel = log.resolve().relative_to(out.resolve()) if log.resolve().is_relative_to(out.resolve()) else log
    with (out / "stages.tsv").open("a") as f:
        f.write(f"{name}\t{status}\t{t0:.3f}\t{t1:.3f}\t{rel}\n")
    text = log.read_text(errors="replace") if log.exists() else ""
    return stage_line(name, status, t1 - t0, text)


def beside(stages: list[dict], i: int) -> int:
    """How many other stages ran at some time during stage i's window."""
    s = stages[i]
    return sum(1 for j, o in enumerate(stages) if j != i and o["t0"] < s["t1"] and o["t1"] > s["t0"])


def table(columns: list[str], rows: list[list[str]]) -> str:
    sys.path.insert(0, str(SCRIPTS))
    from tables import generic_table  # scripts/tables.py: the docs' markdown tables

    return generic_table({"columns": columns, "rows": rows})


def pct(stats: dict | None) -> str:
    return "-" if stats is None else f"{stats['mean']:.0f} / {stats['max']:.0f}"


def summary(stages: list[dict], samples: list[tuple[float, float, float]], start: float, unit: str) -> str:
    """The stages as a markdown table: when each started, how long it ran, beside how many others, its `ready in`,
    its compile time, and the utilisation of the device over its window."""
    rows = []
    for i, s in enumerate(stages):
        text = _log_text(s)
        stats = window_stats(samples, s["t0"], s["t1"]) if s["status"] != "SKIP" else None
        compiled = compile_seconds(text)
        rows.append([s["status"], s["name"], f"{s['t0'] - start:.0f}", f"{s['t1'] - s['t0']:.1f}",
                     str(beside(stages, i)),
                     ready_text(ready_lines(text)) or "-", "-" if compiled is None else f"{compiled:.1f}", pct(stats),
                     "-" if stats is None else f"{stats['mem_max']:.0f}"])
    note = (f"{unit} utilisation is the device's over each stage's window (mean / max %, sampled every 0.5 s): stages "
            "run concurrently, so it is shared by every stage running then ('beside': how many others ran during the "
            "window). 'compile': seconds torch.compile took in the stage's process (first steps; later calls reuse "
            "inductor's on-disk cache).")
    return note + "\n\n" + table(["status", "stage", "start s", "wall s", "beside", "ready in", "compile s",
                                  f"{unit} util %", "memory MiB (max)"], rows)


# --- the held-out table ---------------------------------------------------------------------------------------------
def steady(history: list[dict], iters: int, seconds: float) -> tuple[float | None, float | None]:
    """(seconds per step at the fastest logged interval after the first, seconds beyond that rate over the run): the
    first interval holds the compile and the first budget waits, growth steps recompile; None without two
    intervals."""
    points = [(h["step"], h["seconds"]) for h in history]
    rates = [(s2 - s1) / (k2 - k1) for (k1, s1), (k2, s2) in zip(points, points[1:]) if k2 > k1]
    if not rates:
        return None, None
    rate = min(rates)
    return rate, max(0.0, seconds - iters * rate)


def _num(v, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def model_rows(models: list[dict], baseline: str = "baseline") -> list[list[str]]:
    """Rows of the held-out table, one per model dict: name, eval (its eval.json row), costs (count-params row),
    train (its training report or None), batch (rays per training step), stage_stats (utilisation over its training
    stage, window_stats) and cost_views."""
    base = next((m for m in models if m["name"] == baseline and m.get("eval")), None)
    rows = []
    for m in models:
        ev, cost, tr = m.get("eval") or {}, m.get("costs") or {}, m.get("train") or {}
        psnr, flops = ev.get("psnr"), cost.get("gflops_per_image")
        vs = flops_vs = "-"
        if base is not None and m is not base:
            if psnr is not None and base["eval"].get("psnr") is not None:
                vs = f"{psnr - base['eval']['psnr']:+.2f}"
            ref = (base.get("costs") or {}).get("gflops_per_image")
            if flops and ref:
                flops_vs = f"{flops / ref:.2f}x"
        iters, secs = tr.get("iterations"), tr.get("seconds")
        rate, extra = steady(tr.get("history", []), iters or 0, secs or 0.0) if tr else (None, None)
        mrays = iters * m["batch"] / secs / 1e6 if iters and secs else None
        rows.append([m["name"], _num(psnr, ".3f"), vs, _num(ev.get("ssim"), ".4f"), _num(flops, ".3g"), flops_vs,
                     _num(cost.get("w0"), ","),
                     f"{iters} in {secs:.0f}" if iters and secs else "-", _num(mrays, ".3g"),
                     _num(m["batch"] / rate / 1e6 if rate else None, ".3g"), _num(extra, ".0f"),
                     _num(tr.get("startup_seconds"), ".1f"), _num(ev.get("seconds_per_image"), ".3f"),
                     pct(m.get("stage_stats"))])
    return rows


MODEL_COLUMNS = ["model", "held-out PSNR", "vs baseline", "SSIM", "GFLOPs/image", "GFLOPs vs baseline", "‖w‖₀",
                 "training steps in s", "M rays/s", "steady M rays/s", "warm-up s", "ready in s", "s/image",
                 "GPU util % of its training stage"]

MODEL_NOTE = ("PSNR, SSIM and s/image: `eval --no-costs` on every held-out view; GFLOPs/image and ‖w‖₀: "
              "`count-params "
              "--views {views}` (its first {views} held-out views). Training: the report's steps and seconds (the "
              "first steps' compile included); 'M rays/s' over the whole run, 'steady' at its fastest logged "
              "interval after the first; 'warm-up s': the run's seconds beyond that steady rate (compiling, "
              "recompiles at grid growth, occupancy refreshes); 'ready in': the stage's start-up before the first "
              "step (an expert trained after another in one process counts from that one's end). GPU utilisation: "
              "over the whole stage that trained the model, the device's, shared with the stages beside it.")


def training_stage(name: str, stage: str, calls: list[tuple[list[dict], list]]) -> dict | None:
    """Utilisation over the stage that trained model `name`: of the records named `stage` (each call's: its stages and
    its samples), the latest whose log says `NAME: ready in` (a stage that found the model finished says nothing)."""
    found = [(s, samples) for stages, samples in calls for s in stages
             if s["name"] == stage and any(r["what"] == name for r in ready_lines(_log_text(s)))]
    if not found:
        return None
    s, samples = max(found, key=lambda f: f[0]["t0"])
    return window_stats(samples, s["t0"], s["t1"])


def _model_entry(name: str, ws: Path, stage: str, rec: dict, calls: list) -> dict:
    def row(report: str) -> dict | None:
        path = ws / "reports" / report
        rows = json.loads(path.read_text())["models"] if path.exists() else []
        return next((r for r in rows if r["name"] == name), None)

    expert = (ws / "experts" / f"{name}.json").exists()
    train_path = ws / ("experts" if expert else "moe") / f"{name}.json"
    return {"name": name, "eval": row("eval.json"), "costs": row("count-params.json"),
            "train": json.loads(train_path.read_text()) if train_path.exists() else None,
            "batch": (rec["pretrain"] if expert else rec["moe"])["train"]["batch_rays"],
            "stage_stats": training_stage(name, stage, calls)}


# --- paper-check's plan ---------------------------------------------------------------------------------------------
# The speeds the chain is sized from: the GPU speed targets (docs/gpu.md) on one H100 / H200 (lego, 8192 rays a
# step), times SPEED
# (1: the targets; e.g. 0.16 for a DVGO-160 expert at 0.79 M rays/s, as OUT/gpu-check.md's table gives it).
TARGET_RAYS_PER_S = 5e6  # a DVGO 160^3 expert's training step
TARGET_RES = 160
TARGET_MIXTURE = 2.5  # a Top-2 step, over the step of its largest expert alone (Top-1: the same bound)
TARGET_IMAGE_S = 0.1  # one 800 x 800 image of dvgo-160
TARGET_PIXELS = 800 * 800


def expert_step_s(res: int, batch_rays: int, speed: float) -> float:
    """Seconds of one DVGO training step at `res`^3: the target's, per ray, times res / 160 (DVGO's samples per ray
    grow with the grid: one every step_ratio voxels)."""
    return batch_rays / (TARGET_RAYS_PER_S * speed) * res / TARGET_RES


def image_s(res: int, pixels: int, speed: float) -> float:
    """Seconds of one image of a DVGO expert at `res`^3: the target's, per pixel, times res / 160."""
    return TARGET_IMAGE_S / speed * pixels / TARGET_PIXELS * res / TARGET_RES


def held_out_views(scene: Path, holdout_every: int) -> int:
    """How many views `eval` renders: a Blender scene's test split, or every `holdout_every`-th training view."""
    test = scene / "transforms_test.json"
    if test.exists() and json.loads(test.read_text()).get("frames"):
        return len(json.loads(test.read_text())["frames"])
    return math.ceil(len(json.loads((scene / "transforms_train.json").read_text())["frames"]) / holdout_every)


def render_counts(held_out: int, cost_views: int, oracle_train_views: int, oracle_lattices: int) -> dict:
    """Image renders at the end of the M = 3 chain, in units of one render of the largest expert: eval renders every
    held-out view of 3 experts, the baseline (1 unit each) and Top-1 / Top-2 (2 units each: a mixture renders its
    gate and up to k experts); count-params 3 passes over `cost_views` views (||w||_0's backward pass is counted as
    2); the partition oracle renders the held-out views with each expert, splats held-out and training views with
    each, and renders 4 routed choices of the held-out views per lattice (2 units each)."""
    units = 3 * 1 + 1 + 2 * 2
    return {"eval": units * (held_out + 3 * cost_views),
            "oracle": 3 * held_out + 3 * (held_out + oracle_train_views) + 2 * 4 * held_out * oracle_lattices}


def plan_chain(recipe: dict, held_out: int, s: dict) -> dict:
    """The joint steps F of each finetuned model (baseline, Top-1, Top-2: they run at once on the one GPU) that fill
    the budget at the target speeds (times s["SPEED"]):

        F = (budget - fixed - pretrain - s_image * renders) / (s_baseline + s_top1 + s_top2)

    pretrain: the geometry's and the experts' steps (the experts train at once, so their seconds add up on the one
    GPU); s_baseline: a step of the largest expert; s_top1 = s_top2 = TARGET_MIXTURE x that; s_image: an image of the
    largest expert; renders: render_counts; fixed: the processes' start-ups, scene decoding, compiles and checkpoint
    writes. F is rounded down to F_ROUND, within [F_MIN, the recipe's moe.iters]; `fits`: whether F_MIN fits."""
    speed, pre, moe = float(s["SPEED"]), recipe["pretrain"], recipe["moe"]
    res = [int(r) for r in pre["res"]]
    geometry = pre["geometry"]
    pretrain_s = (geometry["iters"] * expert_step_s(geometry["res"], geometry["batch_rays"], speed)
                  + sum(pre["iters"] * expert_step_s(r, pre["train"]["batch_rays"], speed) for r in res))
    alone = expert_step_s(max(res), moe["train"]["batch_rays"], speed)
    step_s = {"baseline": alone, "top1": TARGET_MIXTURE * alone, "top2": TARGET_MIXTURE * alone}
    renders = render_counts(held_out, int(s["COST_VIEWS"]), int(s["ORACLE_TRAIN_VIEWS"]),
                            len(str(s["ORACLE_MAP_RES"]).split(",")))
    image = image_s(max(res), recipe["data"]["image_size"] ** 2, speed)
    tail = image * (renders["eval"] + renders["oracle"])
    window = float(s["BUDGET_S"]) - float(s["FIXED_S"]) - pretrain_s - tail
    per_step = sum(step_s.values())
    f_min, f_max, f_round = int(s["F_MIN"]), int(moe["iters"]), int(s["F_ROUND"])
    raw = window / per_step
    iters = int(max(f_min, min(f_max, max(raw, 0.0) // f_round * f_round)))
    return {"iters": iters, "fits": raw >= f_min, "speed": speed, "budget_s": float(s["BUDGET_S"]),
            "fixed_s": float(s["FIXED_S"]), "pretrain_s": round(pretrain_s, 1), "seconds_per_step":
            {k: round(v, 6) for k, v in step_s.items()}, "seconds_per_image": round(image, 4), "renders": renders,
            "tail_s": round(tail, 1), "raw_iters": round(raw, 1), "f_min": f_min, "f_max": f_max, "f_round": f_round,
            "expected_s": round(float(s["FIXED_S"]) + pretrain_s + iters * per_step + tail, 1)}


def describe_plan(plan: dict) -> str:
    """The plan as paper-check prints it: F, the formula with its numbers, the speeds it assumed."""
    r, st = plan["renders"], plan["seconds_per_step"]
    lines = [
        f"Plan (OUT/plan.json, made by the first call, kept by later ones): F = {plan['iters']} joint steps for each "
        "finetuned model.",
        f"    F = (budget - fixed - pretrain - s_image * renders) / (s_baseline + s_top1 + s_top2), rounded down to "
        f"{plan['f_round']}, within [{plan['f_min']}, {plan['f_max']}]",
        f"      = ({plan['budget_s']:g} - {plan['fixed_s']:g} - {plan['pretrain_s']:g} - {plan['seconds_per_image']:g}"
        f" * ({r['eval']} + {r['oracle']})) / ({st['baseline'] * 1000:.3g} + {st['top1'] * 1000:.3g} + "
        f"{st['top2'] * 1000:.3g} ms) = {plan['raw_iters']:g} -> {plan['iters']}",
        f"    speeds: the GPU speed targets x SPEED = {plan['speed']:g} (DVGO-160 at "
        f"{TARGET_RAYS_PER_S / 1e6 * plan['speed']:g}"
        f" M rays/s, a mixture step {TARGET_MIXTURE:g}x its largest expert's, an 800 px dvgo-160 image in "
        f"{TARGET_IMAGE_S / plan['speed']:.3g} s)",
        f"    expected: {plan['expected_s']:g} s of the budget's {plan['budget_s']:g} s"
        + ("" if plan["fits"] else f"; F = {plan['f_min']} (the least) does not fit: the chain needs another call"),
    ]
    return "\n".join(lines) + "\n"


# --- results back from the device machine ---------------------------------------------------------------------------
PACKED = {".md", ".json", ".tsv", ".csv", ".log", ".txt", ".yaml"}
NOT_PACKED = {"cache", "checkpoints", "scene", "renders", "variants"}


def pack(out: Path, dest: Path, limit: int = 4 << 20) -> int:
    """OUT's logs, reports, tables and plan (no models, images or caches; files up to `limit` bytes) -> a .tar.gz.
    -> the number of files."""
    n = 0
    with tarfile.open(dest, "w:gz") as tar:
        for p in sorted(out.rglob("*")):
            rel = p.relative_to(out)
            if (p.is_file() and not p.is_symlink() and p.suffix in PACKED and p.stat().st_size <= limit
                    and not NOT_PACKED & set(rel.parts[:-1]) and p.resolve() != dest.resolve()):
                tar.add(p, arcname=str(Path(out.name) / rel))
                n += 1
    return n


# --- the command line -----------------------------------------------------------------------------------------------
def _yaml():
    import yaml

    return yaml


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["cli"]:  # everything after it is boostnerf's
        run_cli(argv[1:])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("settings")
    p.add_argument("script", choices=sorted(SCALES))
    p.add_argument("scale", choices=("full", "tiny"))
    p = sub.add_parser("recipe")
    p.add_argument("script", choices=sorted(SCALES))
    p.add_argument("scale", choices=("full", "tiny"))
    p.add_argument("base", help="a recipe file, or part-a:FAMILY")
    p.add_argument("out", type=Path)
    p = sub.add_parser("device")
    p.add_argument("device", choices=("cuda", "cpu"))
    p = sub.add_parser("sample-cpu")
    p.add_argument("file", type=Path)
    p = sub.add_parser("stage")
    p.add_argument("out", type=Path)
    p.add_argument("name")
    p.add_argument("status", choices=("OK", "FAIL", "CUT", "SKIP"))
    p.add_argument("t0", type=float)
    p.add_argument("t1", type=float)
    p.add_argument("log", type=Path)
    p = sub.add_parser("summary")
    p.add_argument("out", type=Path)
    p.add_argument("--start", type=float, required=True, help="the script's start (epoch seconds)")
    p.add_argument("--unit", default="GPU")
    p = sub.add_parser("models")
    p.add_argument("file", type=Path, help="the markdown file to append the table to")
    p.add_argument("--out", type=Path, required=True, help="the script's OUT (stages.tsv, util.csv)")
    p.add_argument("--recipe", type=Path, required=True)
    p.add_argument("--model", nargs=3, action="append", required=True, metavar=("NAME", "WORKSPACE", "STAGE"))
    p.add_argument("--cost-views", type=int, required=True)
    p = sub.add_parser("table")
    p.add_argument("json", type=Path, help='a generic table {"columns", "rows"} (scripts/tables.py)')
    p.add_argument("file", type=Path, help="the markdown file to append it to")
    p.add_argument("title")
    p = sub.add_parser("plan")
    p.add_argument("script", choices=sorted(SCALES))
    p.add_argument("scale", choices=("full", "tiny"))
    p.add_argument("recipe", type=Path)
    p.add_argument("scene", type=Path)
    p.add_argument("json", type=Path)
    p = sub.add_parser("describe-plan")
    p.add_argument("plan", type=Path)
    p = sub.add_parser("pack")
    p.add_argument("out", type=Path)
    p.add_argument("dest", type=Path)
    a = ap.parse_args(argv)

    if a.cmd == "settings":
        sys.stdout.write(shell_assignments(settings(a.script, a.scale)))
    elif a.cmd == "recipe":
        yaml = _yaml()
        if a.base.startswith("part-a:"):
            base = part_a_recipe(a.base.split(":", 1)[1])
        else:
            base = yaml.safe_load(Path(a.base).read_text())
        rec = merged(base, SCALES[a.script][a.scale]["recipe"])
        a.out.write_text(yaml.safe_dump(rec, sort_keys=False))
        print(" ".join(str(r) for r in rec["pretrain"]["res"]))
    elif a.cmd == "device":
        print(device_line(a.device))
    elif a.cmd == "sample-cpu":
        sample_cpu(a.file)
    elif a.cmd == "stage":
        print(record_stage(a.out, a.name, a.status, a.t0, a.t1, a.log), flush=True)
    elif a.cmd == "summary":
        text = summary(read_stages(a.out), read_samples(a.out), a.start, a.unit)
        (a.out / "stages.md").write_text(text)
        print(text)
    elif a.cmd == "models":
        calls = [(read_stages(d), read_samples(d)) for d in [a.out, *sorted(a.out.glob("call-*"))]]
        rec = _yaml().safe_load(a.recipe.read_text())
        models = [_model_entry(n, Path(w), s, rec, calls) for n, w, s in a.model]
        text = MODEL_NOTE.format(views=a.cost_views) + "\n\n" + table(MODEL_COLUMNS, model_rows(models))
        with a.file.open("a") as f:
            f.write(text)
        print(text)
    elif a.cmd == "table":
        t = json.loads(a.json.read_text())
        text = f"\n{a.title}:\n\n" + table(t["columns"], t["rows"])
        with a.file.open("a") as f:
            f.write(text)
        print(text)
    elif a.cmd == "plan":
        rec = _yaml().safe_load(a.recipe.read_text())
        plan = plan_chain(rec, held_out_views(a.scene, rec["data"]["holdout_every"]), settings(a.script, a.scale))
        a.json.write_text(json.dumps(plan, indent=1) + "\n")
        sys.stdout.write(describe_plan(plan))
    elif a.cmd == "describe-plan":
        sys.stdout.write(describe_plan(json.loads(a.plan.read_text())))
    elif a.cmd == "pack":
        print(f"packed {pack(a.out, a.dest)} files into {a.dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
