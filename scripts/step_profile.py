"""What one training step and one render chunk cost, per kind: aten operators, host-device syncs, milliseconds.

    python scripts/step_profile.py [--device cpu|cuda] [--steps 20] [--warmup 5] [--json FILE]

Builds a tiny workspace on the procedural scene in a temporary folder (DVGO, TensoRF and Instant-NGP experts; a DVGO
mixture finetuned as top1, top2, ens and the baseline), then measures, after `--warmup` steps, the training step of
each kind (`dvgo`, `tensorf`, `ngp`: the largest expert's step; `top1`, `top2`, `ens`: the mixture's joint step;
`baseline`: the largest expert finetuned alone) and one chunk of rendering of the same model:

- `ops_per_step`: aten operators dispatched (views and other metadata-only operators left out: they launch nothing);
- `syncs_per_step`: the operators that make the host wait for the device on CUDA (tests/simdevice.py's `is_sync`:
  `.item()`, `nonzero`, boolean masks, copies between host and device that are not `non_blocking`, ...). On a CPU
  the step runs on the simulated GPU of tests/simdevice.py, so that copies to and from the device are seen;
- `ms_per_step`: wall time per step on `--device`, with no operator counting.

Maintenance steps (logging, checkpoints, occupancy refreshes, grid growth) are not measured: the loop may
synchronise on those. One JSON object per line per kind, then a markdown table.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parent.parent

TRAIN_KINDS = ("dvgo", "tensorf", "ngp", "top1", "top2", "ens", "baseline")

# Operators that only relabel memory (no kernel runs), left out of ops_per_step.
METADATA_OPS = {
    "view", "_unsafe_view", "reshape", "expand", "t", "transpose", "permute", "squeeze", "unsqueeze", "slice",
    "select", "as_strided", "alias", "detach", "unbind", "split", "split_with_sizes", "chunk", "narrow", "view_as",
    "_reshape_alias", "lift_fresh", "empty_like", "empty", "empty_strided", "_has_compatible_shallow_copy_type",
    "is_same_size", "unfold", "diagonal", "movedim", "expand_as", "real", "resolve_conj", "resolve_neg",
    "sym_size", "sym_stride", "sym_numel", "dim", "size", "stride",
}


# --- the tiny workspace ---------------------------------------------------------------------------
RECIPE = {
    "data": {"image_size": 48, "holdout_every": 8},
    "pretrain": {
        "model": "dvgo", "res": [16, 24, 32], "iters": 100, "seed": 0,
        "geometry": {"res": 16, "iters": 200, "batch_rays": 1024},
        "train": {"batch_rays": 2048, "occupancy_every": 50, "checkpoint_every": 1000, "log_every": 50},
        "dvgo": {"hidden": 64, "layers": 2},
        "tensorf": {"hidden": 64, "layers": 2},
        "ngp": {"hidden": 64, "log2_table": 14},
    },
    "moe": {"gate_res": 16, "topk": 2, "iters": 30, "train": {"batch_rays": 2048, "checkpoint_every": 1000,
                                                              "log_every": 50}},
}
FAMILY_RES = {"dvgo": "16,24,32", "tensorf": "16,24,32", "ngp": "8,12,16"}


def _cli(*args: str) -> None:
    proc = subprocess.run([sys.executable, "-m", "boostnerf_cli", *args], capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"step_profile: `boostnerf {' '.join(args)}` failed:\n{proc.stderr[-2000:]}")


def build_workspaces(root: Path, kinds: list[str]) -> dict[str, Path]:
    """Tiny workspaces: one per expert family needed, the DVGO one with its mixtures finetuned. -> family: folder."""
    root.mkdir(parents=True, exist_ok=True)
    recipe = root / "profile.yaml"
    recipe.write_text(yaml.safe_dump(RECIPE, sort_keys=False))
    families = {k for k in kinds if k in FAMILY_RES} | ({"dvgo"} if set(kinds) - set(FAMILY_RES) else set())
    out = {}
    scene = root / "scene"
    if not scene.exists():
        _cli("make-scene", str(scene), "--size", "48")
    for family in sorted(families):
        ws = root / f"ws-{family}"
        _cli("pretrain", "--data", str(scene), "--recipe", str(recipe), "--workspace", str(ws), "--model", family,
             "--res", FAMILY_RES[family], "--device", "cpu")
        out[family] = ws
    if "dvgo" in out and set(kinds) - set(FAMILY_RES):
        ws = out["dvgo"]
        _cli("build-moe", "--workspace", str(ws), "--device", "cpu")
        for flag in (["--topk", "1"], ["--topk", "2"], ["--ensemble"], ["--baseline"]):
            _cli("finetune", "--workspace", str(ws), *flag, "--device", "cpu")
    return out


# --- training steps and render chunks --------------------------------------------------------------
def training_setup(kind: str, ws: Path, device: str, compile: str = "off"):
    """The task, its rays and its schedule, built as the stage that trains `kind` builds them, with train.compile
    set to `compile`."""
    from boostnerf_cli import models
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.recipe import recipe_from_dict
    from boostnerf_cli.stages import finetune as ft
    from boostnerf_cli.tasks import FieldTask, MixtureTask, train_rays
    from boostnerf_cli.train import Schedule
    from boostnerf_cli.workspace import Workspace

    w = Workspace(ws)
    rec = recipe_from_dict(w.manifest()["recipe"])
    scene = Survey(w).scene()
    if kind in FAMILY_RES or kind == "baseline":
        names = sorted((p.stem for p in w.experts_dir.glob(f"{'dvgo' if kind == 'baseline' else kind}-*.safetensors")),
                       key=lambda n: int(n.rsplit("-", 1)[1]))
        model, occ, meta = models.load_expert(w.expert_path(names[-1]), device)
        model.train()
        tcfg = replace(rec.pretrain.train if kind != "baseline" else rec.moe.train, compile=compile)
        settings = scene.render_settings(meta["step"], model.bbox, tcfg.color_threshold)
        occ = occ.to(device) if occ is not None else None
        task = FieldTask(model, settings, tcfg, skip=occ, base_mask=occ)
        iters = rec.pretrain.iters if kind != "baseline" else rec.moe.iters
        box = model.bbox
    else:
        mix, meta = models.load_mixture(w.model_path("init"), device)
        mix.train()
        name = kind
        if kind == "ens":
            mix.make_ensemble()
        topk = None if kind == "ens" else int(kind[3:])
        cfg, _ = ft.routing(name, topk, rec.moe, mix.cfg, mix.gate.cfg.gate_type)
        mix.configure(**{f: getattr(cfg, f) for f in cfg.__dataclass_fields__})
        tcfg = replace(rec.moe.train, compile=compile)
        settings = scene.render_settings(mix.cfg.step, mix.bbox, tcfg.color_threshold)
        task = MixtureTask(mix, settings, tcfg, rec.moe)
        iters = rec.moe.iters
        box = mix.bbox
    rays = train_rays(scene, box, device, tcfg)
    sched = Schedule(iters, tcfg.batch_rays, tcfg.lr_decay, 10**9, 10**9)
    return task, rays, sched


class Stepper:
    """The training loop's step (`train.optimizer_step`), one call at a time, with the loop's optimiser handling."""

    def __init__(self, task, rays, sched, seed: int = 0):
        self.task, self.rays, self.sched = task, rays, sched
        self.gen = torch.Generator(device="cpu").manual_seed(seed)
        self.opt = None
        self.step = 0

    def __call__(self) -> None:
        from boostnerf_cli.train import optimizer_step

        self.opt, _ = optimizer_step(self.task, self.rays, self.sched, self.opt, self.gen, self.step, False)
        self.step += 1


def render_setup(kind: str, ws: Path, device: str):
    """The model of `kind` as eval loads it, and one chunk of a held-out view's rays. -> a function rendering it."""
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.models import ALL_SKIPS, load_model
    from boostnerf_cli.render.packing import packer_for
    from boostnerf_cli.render.rays import image_rays
    from boostnerf_cli.render.renderer import render_rays
    from boostnerf_cli.workspace import Workspace

    w = Workspace(ws)
    scene = Survey(w).scene()
    if kind in FAMILY_RES:
        names = sorted((p.stem for p in w.experts_dir.glob(f"{kind}-*.safetensors")),
                       key=lambda n: int(n.rsplit("-", 1)[1]))
        name = names[-1]
    else:
        name = kind
    loaded = load_model(w, name, device)
    settings, skip = loaded.render_setup(scene, ALL_SKIPS)
    split = scene.held_out() or scene.splits["train"]
    o, d = image_rays(split.poses[0], split.intrinsics[0], split.height, split.width, settings.ndc)
    reps = -(-settings.chunk // o.shape[0])
    o, d = o.repeat(reps, 1)[: settings.chunk].to(device), d.repeat(reps, 1)[: settings.chunk].to(device)

    packer = packer_for(device)  # what render_image packs with on this device

    @torch.no_grad()
    def chunk() -> None:
        render_rays(loaded.field, o, d, settings, skip, packer=packer)

    return chunk


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def count_syncs(make, device: str, steps: int, warmup: int) -> Counter:
    """Operators that synchronise, over `steps` calls after `warmup` (on the simulated GPU when `device` is the CPU;
    tests/simdevice.py's `SyncCounter`)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from simdevice import GPU, SyncCounter, simulated_gpu

    context, count_device = (simulated_gpu, GPU.type) if device == "cpu" else (nullcontext, device)
    with context():
        fn = make(count_device)
        for _ in range(warmup):
            fn()
        with SyncCounter() as counter:
            for _ in range(steps):
                fn()
    return counter.syncs


def _is_kernel(event) -> bool:
    """A profiler event that launches work: a compiled (fused) kernel, or an aten operator that calls no other aten
    operator and is not metadata-only."""
    name = event.name
    if "cpp_fused" in name or name.startswith("triton_") or "_fused_" in name and not name.startswith("aten::"):
        return True
    if not name.startswith("aten::"):
        return False
    op = name[len("aten::"):]
    if op in METADATA_OPS or op.rstrip("_") in METADATA_OPS:
        return False
    return not any(child.name.startswith("aten::") for child in event.cpu_children)


def count_ops(make, device: str, steps: int, warmup: int) -> Counter:
    """Kernels launched (`_is_kernel`) over `steps` calls after `warmup`, from torch.profiler: eager operators and the
    fused kernels of compiled code alike."""
    import torch._inductor.config as inductor_config
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    inductor_config.cpp.enable_kernel_profile = True  # CPU kernels of compiled code show as profiler events
    fn = make(device)
    for _ in range(warmup):
        fn()
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            fn()
    return Counter(e.name for e in prof.events() if _is_kernel(e))


def time_steps(make, device: str, steps: int, warmup: int) -> float:
    """Median wall time of one call, in ms, after `warmup`, with nothing counting."""
    fn = make(device)
    for _ in range(warmup):
        fn()
    _sync(device)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def measure(make, device: str, steps: int, warmup: int, compile: str = "off") -> dict:
    """`make(device, compile)` -> a function running one step (or chunk): its syncs (counted on the eager step: the
    compiler fuses operators, it does not remove waits), kernels and median wall time, and how many graphs the
    compiler made for it (more than one per setup: it recompiled)."""
    import torch._dynamo.utils as dynamo_utils

    syncs = count_syncs(lambda dev: make(dev, "off"), device, steps, warmup)
    graphs = dynamo_utils.counters["stats"]["unique_graphs"]
    ops = count_ops(lambda dev: make(dev, compile), device, steps, warmup)
    ms = time_steps(lambda dev: make(dev, compile), device, steps, warmup)
    return {"ops_per_step": round(sum(ops.values()) / steps, 1),
            "syncs_per_step": round(sum(syncs.values()) / steps, 2),
            "ms_per_step": round(ms, 2), "compile": compile,
            "graphs": dynamo_utils.counters["stats"]["unique_graphs"] - graphs,
            "syncs": {k: round(v / steps, 2) for k, v in syncs.most_common()},
            "top_ops": {k: round(v / steps, 1) for k, v in ops.most_common(8)}}


def profile(kinds: list[str], device: str, steps: int, warmup: int, workdir: Path | None = None,
            compile: str = "off") -> list[dict]:
    """Measure every kind; `workdir`: where the tiny workspaces are built (reused when already there); `compile`:
    train.compile for the training steps."""
    with tempfile.TemporaryDirectory() as tmp:
        root = workdir or Path(tmp)
        spaces = build_workspaces(root, kinds)
        rows = []
        for kind in kinds:
            ws = spaces["dvgo"] if kind not in FAMILY_RES else spaces[kind]

            def train_step(dev: str, mode: str, kind=kind, ws=ws):
                torch.manual_seed(0)
                return Stepper(*training_setup(kind, ws, dev, mode))

            def render_chunk(dev: str, mode: str, kind=kind, ws=ws):
                return render_setup(kind, ws, dev)

            row = {"kind": kind, "device": device, "torch": torch.__version__, "threads": torch.get_num_threads()}
            row["train"] = measure(train_step, device, steps, warmup, compile)
            row["render"] = measure(render_chunk, device, steps, warmup)
            rows.append(row)
            print(json.dumps(row), flush=True)
        return rows


def generic_table(rows: list[dict]) -> dict:
    """The rows as a docs/data generic table (scripts/tables.py)."""
    columns = ["kind", "step ops", "step syncs", "step ms", "render ops", "render syncs", "render ms"]
    cells = [[r["kind"], f"{r['train']['ops_per_step']:.0f}", f"{r['train']['syncs_per_step']:g}",
              f"{r['train']['ms_per_step']:.1f}", f"{r['render']['ops_per_step']:.0f}",
              f"{r['render']['syncs_per_step']:g}", f"{r['render']['ms_per_step']:.1f}"] for r in rows]
    return {"columns": columns, "rows": cells}


def table(rows: list[dict]) -> str:
    out = ["| kind | step ops | step syncs | step ms | render ops | render syncs | render ms |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        t, c = r["train"], r["render"]
        out.append(f"| {r['kind']} | {t['ops_per_step']:.0f} | {t['syncs_per_step']:g} | {t['ms_per_step']:.1f} "
                   f"| {c['ops_per_step']:.0f} | {c['syncs_per_step']:g} | {c['ms_per_step']:.1f} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu (syncs counted on the simulated GPU) or cuda")
    parser.add_argument("--steps", type=int, default=20, help="measured steps per kind (default 20)")
    parser.add_argument("--warmup", type=int, default=5, help="steps before measuring (default 5)")
    parser.add_argument("--kinds", default=",".join(TRAIN_KINDS), help="comma-separated, of " + ",".join(TRAIN_KINDS))
    parser.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    parser.add_argument("--table", type=Path, help="also write them as a docs/data generic table (scripts/tables.py)")
    parser.add_argument("--compile", default="off", choices=("off", "on", "auto"),
                        help="train.compile for the training steps (default off)")
    parser.add_argument("--workdir", type=Path, help="build the tiny workspaces here and reuse them (default: a "
                        "temporary folder)")
    args = parser.parse_args(argv)
    kinds = [k for k in args.kinds.split(",") if k]
    unknown = [k for k in kinds if k not in TRAIN_KINDS]
    if unknown:
        parser.error(f"argument --kinds: unknown {', '.join(unknown)}: give some of {', '.join(TRAIN_KINDS)}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("argument --device: torch sees no CUDA GPU here")
    rows = profile(kinds, args.device, args.steps, args.warmup, args.workdir, args.compile)
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    if args.table:
        args.table.write_text(json.dumps(generic_table(rows), indent=1) + "\n")


if __name__ == "__main__":
    main()
