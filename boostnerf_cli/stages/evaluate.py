"""`boostnerf eval`: one table of every model's quality and cost.

reports/eval.json schema (documented in docs/reports.md):
{"split": str, "views": int, "lpips_note": str | null, "ssim_note": str | null,
 "models": [{"name", "kind", "psnr", "ssim" (null under 11 px), "lpips" (null when unavailable), "seconds_per_image",
             "warmup_seconds", "load_seconds", "samples_per_image", "colored_per_image", "params", "w0",
             "gflops_per_image"}, ...],
 "finetuned": {name: {"from", "iterations"}} (the finetuned models among them, from the manifest)}
"""

from __future__ import annotations

import logging
import time

from boostnerf_cli.costs import model_costs
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.metrics import image_metrics, load_lpips
from boostnerf_cli.metrics.image import LPIPS_MIN_SIZE, SSIM_WINDOW
from boostnerf_cli.models import ALL_SKIPS, LoadedModel, Skips, Viewing, load_model, n_views, render_split
from boostnerf_cli.scenes import Scene, Split
from boostnerf_cli.workspace import atomic_path, number, write_json

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)


def evaluate_model(model: LoadedModel, scene: Scene, split: Split, device: str, lpips_model, skips: Skips = ALL_SKIPS,
                   views: int | None = None) -> dict:
    """Mean per-image PSNR / SSIM / LPIPS of one model over a split."""
    rows = []
    for i, r in enumerate(render_split(model, scene, split, device, skips, views, warm=True)):
        m = image_metrics(r["rgb"], split.images[i], lpips_model)
        rows.append({**m, "seconds": r["seconds"], "samples": r["n_samples"], "colored": r["n_color"],
                     "warmup": r["warmup_seconds"]})
    n = len(rows)
    mean = lambda k: sum(row[k] for row in rows) / n  # noqa: E731
    return {
        "name": model.name,
        "kind": model.kind,
        "psnr": round(mean("psnr"), 4),
        "ssim": round(mean("ssim"), 5) if rows[0]["ssim"] is not None else None,
        "lpips": round(mean("lpips"), 5) if lpips_model is not None else None,
        "seconds_per_image": round(mean("seconds"), 4),
        "warmup_seconds": round(rows[0]["warmup"], 4),
        "samples_per_image": round(mean("samples")),
        "colored_per_image": round(mean("colored")),
        "params": model.params,
        # how a mixture routes: a top2 finetuned with --no-renormalize is another model than the default top2
        **({"routing": {"topk": model.field.cfg.topk, "renormalize": model.field.cfg.renormalize}}
           if model.kind == "mixture" else {}),
    }


def run(survey: Survey, names: list[str] | None, viewing: Viewing, device: str, report: bool = False,
        costs: bool = True) -> dict:
    """Score every model of `names` (default: all) on `viewing`'s views; `report`: write reports/eval.json and .md;
    `costs`: also ||w||_0 and GFLOPs per image."""
    split_name, views, skips, exact_gate = viewing.split, viewing.views, viewing.skips, viewing.exact_gate
    ws, scene = survey.ws, survey.scene()
    split = scene.split(split_name)
    names = survey.current(names)
    if not names:
        raise BoostNerfError(
            f"{ws.root} has no trained models yet: run `boostnerf pretrain --workspace {ws.root}` first")
    lpips_model, lpips_note = load_lpips(device)
    if lpips_model is not None and min(split.height, split.width) < LPIPS_MIN_SIZE:
        lpips_model, lpips_note = None, (
            f"LPIPS left out: its AlexNet needs images of at least {LPIPS_MIN_SIZE} px a side, these are "
            f"{split.width} x {split.height} (pretrain at a larger --image-size to have it)")
    if lpips_model is None:
        log(lpips_note)
    ssim_note = None
    if min(split.height, split.width) < SSIM_WINDOW:
        ssim_note = (f"SSIM left out: its {SSIM_WINDOW} x {SSIM_WINDOW} window needs images of at least "
                     f"{SSIM_WINDOW} px a side, these are {split.width} x {split.height} "
                     "(pretrain at a larger --image-size to have it)")
        log(ssim_note)
    rows = []
    for name in names:
        t0 = time.perf_counter()
        model = load_model(ws, name, device, exact_gate=True)  # ||w||_0 needs the trainable gate
        loading = time.perf_counter() - t0
        log(f"{name}: rendering {n_views(split, views)} {split_name} view{'s' if n_views(split, views) != 1 else ''}"
            + (" (and again for its costs)" if costs else ""))  # minutes on a large split: say what runs
        cost = {}
        if costs:
            c = model_costs(model, scene, split, device, views, exact_gate, skips)  # leaves it ready to render
            cost = {"w0": c["w0"], "gflops_per_image": c["gflops_per_image"]}
        t0 = time.perf_counter()
        model = model.for_rendering(exact_gate)  # the gate baked (rendering's lookup table)
        loading += time.perf_counter() - t0
        scores = evaluate_model(model, scene, split, device, lpips_model, skips, views)
        row = {**scores, "load_seconds": round(loading, 4), **cost}
        log(f"{name}: PSNR {number(row['psnr'], '.3f')}  SSIM {number(row['ssim'], '.4f')}  "
            f"{row['seconds_per_image']:.3f}s/image")
        rows.append(row)
    result = {"split": split_name, "views": n_views(split, views), "skip": skips.empty and skips.terminated,
              "skips": {"empty": skips.empty, "terminated": skips.terminated},
              "lpips_note": lpips_note or None, "ssim_note": ssim_note, "models": rows,
              "finetuned": {k: v for k, v in survey.manifest().get("moe", {}).items()
                            if k in names and "iterations" in v}}
    if report:
        write_json(ws.reports_dir / "eval.json", result)
        with atomic_path(ws.reports_dir / "eval.md") as tmp:
            tmp.write_text(markdown_table(result))
    return result


def markdown_table(result: dict) -> str:
    """The eval report as a Markdown table, in the paper's Table 1 columns."""
    baseline = next((r for r in result["models"] if r["name"] == "baseline"), {})
    ratio = lambda r, key: (f"{r[key] / baseline[key]:.2f}x" if r.get(key) is not None  # noqa: E731
                            and baseline.get(key) else "-")
    lines = [
        f"Split `{result['split']}`, {result['views']} views, skips {Skips(**result['skips']).describe()}.",
        "",
        "| model | PSNR | SSIM | LPIPS | params | ‖w‖₀ | GFLOPs/image | GFLOPs vs baseline | s/image | "
        "s vs baseline |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["models"]:
        lines.append(
            f"| {r['name']} | {number(r['psnr'], '.3f')} | {number(r['ssim'], '.4f')} | "
            f"{number(r['lpips'], '.4f')} | {r['params']:,} | "
            f"{number(r.get('w0'), ',')} | {number(r.get('gflops_per_image'), '.3f')} | "
            f"{ratio(r, 'gflops_per_image')} | {r['seconds_per_image']:.3f} | {ratio(r, 'seconds_per_image')} |"
        )
    reading = [how_to_read(result.get("finetuned") or {}), top1_note(result["models"])]
    notes = [n for n in reading if n] + [result[k] for k in ("ssim_note", "lpips_note") if result.get(k)]
    for note in notes:  # each a paragraph of its own
        lines += ["", note]
    return "\n".join(lines) + "\n"


def how_to_read(finetuned: dict) -> str:
    """One line on the comparison the table makes, from the manifest's `moe` entries of the finetuned models it
    lists ({name: {from, iterations}}): which row is the baseline and what it was trained for."""
    base = finetuned.get("baseline")
    if not base:
        return ""
    others = {k: v["iterations"] for k, v in finetuned.items() if k != "baseline"}
    steps = base["iterations"]
    if others and set(others.values()) == {steps}:
        trained = f"for the same {steps} finetuning steps as {', '.join(others)}"
    else:
        trained = f"for {steps} finetuning steps" + (
            f" ({', '.join(f'{k}: {v}' for k, v in others.items())})" if others else "")
    return (f"How to read it: `baseline` is the largest expert, {base['from']}, trained alone {trained}; "
            f"GFLOPs vs baseline is a model's GFLOPs per image over the baseline's. The "
            f"expert rows are the pretrained experts before those steps.")


# docs/results.md's answer to why a Top-1 mixture stays below its baseline on lego at 100 px
TOP1_WHY = "docs/results.md#why-does-top-1-stay-below-its-baseline-at-100-px"
TOP1_POINTER = f"Why Top-1 stays below its baseline on lego at 100 px: {TOP1_WHY}."


def top1_note(models: list[dict]) -> str:
    """A line for each Top-1 mixture of the table below the baseline: by how much and at what cost, as this table
    shows them, and where the docs say why on lego (a claim about one scene, so only pointed at)."""
    base = next((r for r in models if r["name"] == "baseline"), None)
    below = [r for r in models if base and r.get("routing", {}).get("topk") == 1 and r["psnr"] < base["psnr"]]
    lines = []
    for r in below:
        cost = (f", at {r['gflops_per_image'] / base['gflops_per_image']:.2f}x its GFLOPs"
                if r.get("gflops_per_image") is not None and base.get("gflops_per_image") else "")
        lines.append(f"`{r['name']}` is {base['psnr'] - r['psnr']:.2f} dB below `baseline`{cost}: it renders each "
                     f"sample with one expert. {TOP1_POINTER}")
    return "\n\n".join(lines)
