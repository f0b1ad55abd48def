"""`boostnerf bench`: run time against error on one scene, every variant in one table.

WS (the bench folder) holds one workspace per variant family under `WS/variants/<name>/`, one
finished row per variant under `WS/rows/<row>.json` (a rerun skips them: the bench resumes), and the
table of every finished row of the suite: `WS/reports/bench.json`, `bench.csv` and, with matplotlib
(the `plots` extra), `bench-psnr-gflops.png` and `bench-psnr-time.png`.

Workspaces (experts are trained once and hard-linked between workspaces, never retrained):
  main            the recipe's experts; rows: each expert alone, baseline, top1, top2, ens
  naive-res       one expert at 1.25x the largest resolution      } the paper's naive alternatives
  naive-step      the largest expert with half the sampling step  } (Fig. 1), each trained from scratch
  naive-wide      the largest expert with a 2x wider colour MLP   } for pretrain.iters + moe.iters steps
  m3, m4, m5      M experts evenly spaced from the smallest to the largest resolution; top1..topM
                  (the M of the recipe is `main`, whose top1/top2 rows are not repeated)
  gate-res-R      gate grid of R^3 (half and twice the recipe's), top-k of the recipe
  gate-linear, gate-switch   the other gate types (switch with top-1, as Switch-NeRF)
  penalty-P       the other auxiliary-loss penalties, from main's untrained mixture, top1 and top2
The quick suite is main + naive; the full suite adds the ablations. Rows that could only repeat another are left
out, with a note (`catalogue_notes`): the gate and penalty rows for one expert (the gate has no choice to make),
and the penalty rows at moe.lam 0 (no auxiliary loss to weigh).

train_seconds: the training wall time of everything a model needs, the shared geometry stage
excluded (it is the same for every variant): an expert's pretraining; for a mixture the sum of
its experts' pretraining plus its finetuning; for the baseline the largest expert's pretraining
plus its finetuning. The other columns come from `eval` on the test split (skips on).
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import io
import json
import logging
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import CONFIGS
from boostnerf_cli.lineage import Survey, moved, scene_digest
from boostnerf_cli.models import Viewing
from boostnerf_cli.moe.router import PENALTIES
from boostnerf_cli.recipe import Recipe, check_recipe, recipe_dict, recorded_recipe
from boostnerf_cli.workspace import Workspace, atomic_path, read_json, recorded_path, write_json

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)

SUITES = ("quick", "full")
COLUMNS = ("name", "group", "psnr", "ssim", "train_seconds", "seconds_per_image", "gflops_per_image", "params", "w0")


@dataclass
class Setup:
    """How one variant workspace is made."""

    name: str
    kind: str  # main | naive (trains its own expert) | ladder (trains the experts main lacks) | link (main's experts)
    recipe: Recipe
    link_init: bool = False  # start from main's untrained mixture (same gate initialisation)


@dataclass
class Row:
    name: str
    group: str
    setup: str
    model: str
    train: str | None = None  # None (pretrained expert), "baseline", "ens" or "topK"
    experts: int | None = None
    topk: int | None = None
    extra: dict = field(default_factory=dict)


def _options_for(rec: Recipe, resolutions: list[int]) -> dict:
    """The recipe's family options (its own family's section) for other resolutions: a per-resolution mapping takes
    the value of the nearest resolution it has, by `pretrain.expert_options`'s rule (the larger on a tie), so a
    bench expert is the expert `pretrain --res` trains."""
    from boostnerf_cli.stages.pretrain import expert_options

    section = rec.pretrain.family_config()
    per_res = {r: expert_options(rec.pretrain, r) for r in resolutions}
    return {key: {r: per_res[r][key] for r in resolutions} if isinstance(value, dict) else value
            for key, value in section.items()}


# the option that widens each family's colour MLP (naive-wide; its default is the family config's)
WIDTH_KEY = {"dvgo": "hidden", "tensorf": "hidden", "ngp": "color_hidden"}


def _variant(rec: Recipe, res: list[int], **train) -> Recipe:
    r = copy.deepcopy(rec)
    setattr(r.pretrain, r.pretrain.model, _options_for(rec, res))
    r.pretrain.res = list(res)
    for k, v in train.items():
        setattr(r.pretrain.train, k, v)
    return check_recipe(r, "bench variant's setting")  # checked once, as a recipe read is


def ladder(lo: int, hi: int, m: int) -> list[int]:
    """M resolutions evenly spaced from lo to hi (both included), rounded; fewer when they collide."""
    return sorted({round(lo + (hi - lo) * i / (m - 1)) for i in range(m)})


def catalogue(rec: Recipe, suite: str) -> tuple[dict[str, Setup], list[Row]]:
    """Every workspace and row of a suite, in table order."""
    if suite not in SUITES:
        raise BoostNerfError(f"unknown suite {suite!r}: use quick or full")
    res = sorted(rec.pretrain.res)
    family, largest, m0 = rec.pretrain.model, res[-1], len(res)
    k0 = max(1, min(rec.moe.topk, m0))
    setups = {"main": Setup("main", "main", _variant(rec, res))}
    rows = [Row(f"{family}-{r}", "expert", "main", f"{family}-{r}") for r in res]
    rows.append(Row("baseline", "baseline", "main", "baseline", "baseline"))
    rows += [Row(f"top{k}", "moe", "main", f"top{k}", f"top{k}", m0, k) for k in (1, 2) if k <= m0]
    if m0 >= 2:
        rows.append(Row("ens", "moe", "main", "ens", "ens", m0, m0))

    # the paper's naive alternatives: one bigger expert each, trained for the mixture's total steps
    total = rec.pretrain.iters + rec.moe.iters
    big = max(largest + 1, round(1.25 * largest))
    wide = _options_for(rec, [largest])
    key = WIDTH_KEY[family]
    hidden = wide.get(key, getattr(CONFIGS[family](), key))
    wide[key] = {largest: 2 * (hidden[largest] if isinstance(hidden, dict) else hidden)}
    naive = {
        "naive-res": (_variant(rec, [big]), big),
        "naive-step": (_variant(rec, [largest], step_ratio=rec.pretrain.train.step_ratio / 2), largest),
        "naive-wide": (_variant(rec, [largest]), largest),
    }
    setattr(naive["naive-wide"][0].pretrain, family, wide)
    for name, (r, size) in naive.items():
        r.pretrain.iters = total
        setups[name] = Setup(name, "naive", r)
        rows.append(Row(name, "naive", name, f"{family}-{size}"))
    if suite == "quick":
        return setups, rows

    for m in (3, 4, 5):  # number of experts x top-k
        experts = res if m == m0 else ladder(res[0], largest, m)
        if len(experts) != m:
            continue
        name = "main" if m == m0 else f"m{m}"
        if name != "main":
            setups[name] = Setup(name, "ladder", _variant(rec, experts))
        for k in range(1, m + 1):
            if name == "main" and k <= 2:
                continue  # the main rows top1, top2
            rows.append(Row(f"M{m}-top{k}", "topk", name, f"top{k}", f"top{k}", m, k, {"res": experts}))
    if m0 < 2:  # one expert: every gate routes to it, so the gate and penalty rows would repeat top1
        return setups, rows
    for gr in sorted({max(2, rec.moe.gate_res // 2), rec.moe.gate_res * 2} - {rec.moe.gate_res}):
        r = copy.deepcopy(setups["main"].recipe)
        r.moe.gate_res = gr
        setups[f"gate-res-{gr}"] = Setup(f"gate-res-{gr}", "link", r)
        rows.append(Row(f"gate-res-{gr}", "gate-res", f"gate-res-{gr}", f"top{k0}", f"top{k0}", m0, k0))
    for gt, k in (("linear", k0), ("switch", 1)):
        if gt == rec.moe.gate_type:
            continue
        r = copy.deepcopy(setups["main"].recipe)
        r.moe.gate_type = gt
        setups[f"gate-{gt}"] = Setup(f"gate-{gt}", "link", r)
        rows.append(Row(f"gate-{gt}", "gate-type", f"gate-{gt}", f"top{k}", f"top{k}", m0, k))
    for p in PENALTIES if rec.moe.lam > 0 else ():  # at lambda 0 no penalty weighs anything: rows = top1, top2
        if p == rec.moe.penalty:
            continue
        r = copy.deepcopy(setups["main"].recipe)
        r.moe.penalty = p
        setups[f"penalty-{p}"] = Setup(f"penalty-{p}", "link", r, link_init=True)
        for k in (1, 2):
            if k <= m0:
                rows.append(Row(f"penalty-{p}-top{k}", "penalty", f"penalty-{p}", f"top{k}", f"top{k}", m0, k))
    return setups, rows


def catalogue_notes(rec: Recipe, suite: str) -> list[str]:
    """What `catalogue` fits or leaves out of the recipe's suite, one line each (printed by bench and bench --list)."""
    m0, notes = len(rec.pretrain.res), []
    if suite == "full" and 2 <= m0 < rec.moe.topk:  # the only rows that use the recipe's k
        notes.append(f"moe.topk = {rec.moe.topk} but the recipe has {m0} expert{'s' if m0 > 1 else ''}: the rows that "
                     f"use the recipe's k (gate-res, gate-linear) use {m0}")
    if suite == "full" and m0 < 2:
        notes.append("one expert: the gate-res, gate-type and penalty rows are left out (every gate routes to it, so "
                     "they would repeat top1)")
    elif suite == "full" and rec.moe.lam == 0:
        notes.append("moe.lam = 0: the penalty rows are left out (without the auxiliary loss the penalty weighs "
                     "nothing, so they would repeat top1 and top2)")
    return notes


def select(rows: list[Row], only: list[str] | None, suite: str) -> list[Row]:
    """Rows named in `only` (row names or group names); all rows when None."""
    if not only:
        return rows
    known = {r.name for r in rows} | {r.group for r in rows}
    unknown = [n for n in only if n not in known]
    if unknown:
        raise BoostNerfError(f"--only: no row or group {unknown[0]!r} in the {suite} suite "
                             f"(rows: {', '.join(r.name for r in rows)}; groups: "
                             f"{', '.join(dict.fromkeys(r.group for r in rows))})")
    return [r for r in rows if r.name in only or r.group in only]


# --- running -----------------------------------------------------------------------------------
def row_path(root: Path, name: str) -> Path:
    """BENCH/rows/NAME.json: row NAME's result, written when it finishes (a rerun skips the rows that have one)."""
    return root / "rows" / f"{name}.json"


def _link(src: Path, dst: Path) -> None:
    """Hard-link a finished artifact into another workspace (copy across file systems)."""
    if dst.exists() or not src.exists():
        return
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


class Bench:
    def __init__(self, root: Path, data: Path, setups: dict[str, Setup], device: str, views: int | None):
        self.root, self.data, self.setups, self.device, self.views = root, data, setups, device, views
        self.ready: set[str] = set()

    def ws(self, name: str) -> Workspace:
        return Workspace(self.root / "variants" / name)

    def row_path(self, name: str) -> Path:
        return row_path(self.root, name)

    def prepare(self, setup: Setup) -> Workspace:
        """Make a variant workspace ready: its experts trained or linked, its mixture built."""
        from boostnerf_cli.stages import pretrain

        ws = self.ws(setup.name)
        if setup.name in self.ready:
            return ws
        main = self.ws("main")
        if setup.kind == "main":
            pretrain.run(Survey(ws), self.data, setup.recipe, self.device, False)
        else:
            self.prepare(self.setups["main"])
            _link(main.geometry_path, ws.geometry_path)
            wanted = {pretrain.expert_name(setup.recipe.pretrain.model, r) for r in setup.recipe.pretrain.res}
            for name in main.expert_names():
                if setup.kind == "link" or (setup.kind == "ladder" and name in wanted):
                    _link(main.expert_path(name), ws.expert_path(name))
                    _link(main.expert_report_path(name), ws.expert_report_path(name))
            if setup.kind == "link":
                if not ws.manifest_path.exists():
                    write_json(ws.manifest_path, {**main.manifest(), "recipe": recipe_dict(setup.recipe)})
            else:
                pretrain.run(Survey(ws), self.data, setup.recipe, self.device, False)
            if setup.link_init:
                self.build(main, self.setups["main"])
                _link(main.model_path("init"), ws.model_path("init"))
                _link(main.moe_dir / "init.json", ws.moe_dir / "init.json")
        self.ready.add(setup.name)
        return ws

    def build(self, ws: Workspace, setup: Setup) -> None:
        from boostnerf_cli.stages import build_moe

        if not ws.model_path("init").exists():
            # Each row finetunes with its own top-k; the untrained mixture's only has to fit its experts.
            moe = setup.recipe.moe
            moe = dataclasses.replace(moe, topk=min(moe.topk, len(setup.recipe.pretrain.res)))
            build_moe.build(Survey(ws), None, moe, self.device)

    def run_row(self, row: Row) -> dict:
        from boostnerf_cli.stages import evaluate, finetune

        setup = self.setups[row.setup]
        ws = self.prepare(setup)
        if row.train is not None:
            self.build(ws, setup)
            topk = int(row.train[3:]) if row.train.startswith("top") else None
            finetune.run(Survey(ws), row.train, topk, setup.recipe.moe, self.device, False)
        result = evaluate.run(Survey(ws), [row.model], Viewing("test", self.views), self.device)
        ev = result["models"][0]
        out = {
            "name": row.name,
            "group": row.group,
            "psnr": ev["psnr"],
            "ssim": ev["ssim"],
            "train_seconds": round(self.train_seconds(ws, row), 2),
            "seconds_per_image": ev["seconds_per_image"],
            "gflops_per_image": ev["gflops_per_image"],
            "params": ev["params"],
            "w0": ev["w0"],
            "workspace": str(Path("variants") / row.setup),
            "model": row.model,
            "experts": row.experts,
            "topk": row.topk,
            "views": result["views"],
            "samples_per_image": ev["samples_per_image"],
            **row.extra,
        }
        write_json(self.row_path(row.name), out)
        return out

    def train_seconds(self, ws: Workspace, row: Row) -> float:
        def expert_seconds(name: str) -> float:
            return float(read_json(ws.expert_report_path(name), "expert report")["seconds"])

        if row.train is None:
            return expert_seconds(row.model)
        report = read_json(ws.moe_dir / f"{row.train}.json", "finetune report")
        if row.train == "baseline":
            return expert_seconds(report["from"]) + float(report["seconds"])
        return sum(expert_seconds(n) for n in report["experts"]) + float(report["seconds"])


def bench_config(data: Path, views: int | None, rec: Recipe, root: Path) -> dict:
    """What a bench folder `root` is for, as its bench-config.json reads back: through JSON, so that a
    per-resolution mapping (`hidden: {64: 64, ...}`, int keys) compares equal to its stored copy. The scene's path
    as a workspace records it (`recorded_path`: the generated scene inside the folder travels with it)."""
    return json.loads(json.dumps({"data": recorded_path(Path(data), root), "views": views, "recipe": recipe_dict(rec)}))


def folder_recipe(root: Path) -> Recipe | None:
    """The recipe a bench folder was made with (its bench-config.json), for a rerun given no --recipe, as a
    workspace's recorded recipe serves its later stages; None for a new folder."""
    config_path = root / "bench-config.json"
    if not config_path.exists():
        return None
    return recorded_recipe(read_json(config_path, "bench config").get("recipe"), config_path)


def check_config(root: Path, data: Path | None, views: int | None, rec: Recipe, listing: bool = False) -> dict:
    """The bench's config (`bench_config`; data None: the default scene WS/scene, or when `listing` the folder's own
    scene), refused when the folder holds a bench made with another one (`run`, and `--list`, whose "finished"
    would otherwise stand for another recipe). The same scene at another path (the folder or the scene moved, a
    symbolic link repointed) is that scene when its images and cameras are those the variants were trained on."""
    config_path = root / "bench-config.json"
    previous = read_json(config_path, "bench config") if config_path.exists() else None
    if data is None:
        data = root / previous["data"] if listing and previous and "data" in previous else root / "scene"
    config = bench_config(data, views, rec, root)
    if moved(previous, config, "data"):
        _check_moved_scene(root, Path(data), rec, root / previous["data"])
    elif previous is not None and previous != config:
        changed = next(k for k in config if previous.get(k) != config[k])
        raise BoostNerfError(f"{root} holds a bench made with another {changed} ({config_path}): "
                             "use a new --workspace, or delete it to start over")
    return config


def _check_moved_scene(root: Path, data: Path, rec: Recipe, was: Path) -> None:
    """Refuse a scene at a new path whose images or cameras differ from those the bench's variants were trained on
    (their manifests' scene digest); the variants repoint themselves when they next run (pretrain's `moved`)."""
    digests = {read_json(m, "workspace manifest").get("scene_digest")
               for m in (root / "variants").glob("*/manifest.json")}
    digests.discard(None)
    if not digests:
        return  # nothing trained on the old one
    from boostnerf_cli.scenes import load_scene

    scene = load_scene(data, image_size=rec.data.image_size, holdout_every=rec.data.holdout_every,
                       format=rec.data.format, bbox=rec.data.bbox, kind=rec.data.scene)
    if scene_digest(scene) not in digests:
        raise BoostNerfError(f"the scene at {data} is not the one the bench in {root} was made with, at {was} (its "
                             "images or cameras differ): use a new --workspace, or delete it to start over")


def run(root: Path, data: Path | None, rec: Recipe, suite: str, only: list[str] | None, device: str,
        views: int | None) -> dict:
    setups, rows = catalogue(rec, suite)
    chosen = select(rows, only, suite)
    for note in catalogue_notes(rec, suite):
        log(f"note: {note}")
    if data is None:
        from boostnerf_cli.scenes import make_scene

        data = root / "scene"
        if not (data / "transforms_train.json").exists():
            log(f"no --data given: generating the default procedural scene in {data}")
            make_scene(data, size=rec.data.image_size or 64, seed=rec.pretrain.seed)
    if not Path(data).exists():
        raise BoostNerfError(f"--data {data} does not exist")
    config = check_config(root, data, views, rec)
    config_path = root / "bench-config.json"
    if not config_path.exists() or read_json(config_path, "bench config") != config:  # new, or its scene moved
        write_json(config_path, config)
    bench = Bench(root, Path(data), setups, device, views)
    for i, row in enumerate(chosen, 1):
        if bench.row_path(row.name).exists():
            log(f"bench [{i}/{len(chosen)}] {row.name}: finished, skipping")
            continue
        log(f"bench [{i}/{len(chosen)}] {row.name} ({row.group}, workspace variants/{row.setup})")
        r = bench.run_row(row)
        log(f"bench [{i}/{len(chosen)}] {row.name}: PSNR {r['psnr']:.3f}, {r['gflops_per_image']:.3f} GFLOPs/image, "
            f"{r['seconds_per_image']:.3f} s/image, trained in {r['train_seconds']:.0f}s")
        if i < len(chosen):  # the table of every finished row stays current: an interrupted bench leaves it too
            write_table(root, suite, rows, plots=False)
    return write_table(root, suite, rows)


def write_table(root: Path, suite: str, rows: list[Row], plots: bool = True) -> dict:
    """bench.json / bench.csv / plots of every finished row of the suite, in catalogue order."""
    done = [read_json(row_path(root, r.name), "bench row") for r in rows if row_path(root, r.name).exists()]
    reports = root / "reports"
    table = {"suite": suite, "rows": done, "missing": [r.name for r in rows if not row_path(root, r.name).exists()]}
    write_json(reports / "bench.json", table)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    for r in done:
        writer.writerow([r[c] for c in COLUMNS])
    with atomic_path(reports / "bench.csv") as tmp:
        tmp.write_text(buf.getvalue())
    table["plots"] = plot(done, reports) if plots else []
    return table


GROUP_STYLE = {"expert": "o", "baseline": "s", "moe": "*", "naive": "^", "topk": "D", "gate-res": "v",
               "gate-type": "P", "penalty": "X"}


def plot(rows: list[dict], folder: Path) -> list[str]:
    """PSNR against GFLOPs per image and against seconds per image; [] without matplotlib."""
    def finite(v: float | None) -> bool:  # a row read back holds null for a value that was not finite
        return v is not None and math.isfinite(v)

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log("matplotlib is not installed (pip install -e \".[plots]\" in the clone): the table is written, the plots "
            "are skipped")
        return []
    written = []
    for key, label, stem in (("gflops_per_image", "GFLOPs per image", "bench-psnr-gflops"),
                             ("seconds_per_image", "seconds per image (render)", "bench-psnr-time")):
        fig, ax = plt.subplots(figsize=(7, 5), dpi=120)
        for group in dict.fromkeys(r["group"] for r in rows):
            pts = [r for r in rows if r["group"] == group and finite(r[key]) and finite(r["psnr"])]
            ax.scatter([r[key] for r in pts], [r["psnr"] for r in pts], marker=GROUP_STYLE.get(group, "o"),
                       s=60 if group == "moe" else 36, label=group)
            for r in pts:
                ax.annotate(r["name"], (r[key], r["psnr"]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB), test split")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        with atomic_path(folder / f"{stem}.png") as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)
        written.append(str(folder / f"{stem}.png"))
    return written
