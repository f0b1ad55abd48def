"""`boostnerf render` and `boostnerf eval`: images on disk, and one table of every model's quality.

reports/eval.json schema (documented in docs/reports.md):
{"split": str, "views": int, "lpips_note": str | null,
 "models": [{"name", "kind", "psnr", "ssim", "lpips" (null when unavailable), "seconds_per_image",
             "samples_per_image", "colored_per_image", "params", "w0", "gflops_per_image"}, ...]}
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import imageio.v3 as iio
import numpy as np
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.metrics import image_metrics, load_lpips
from boostnerf_cli.render.renderer import render_image
from boostnerf_cli.scenes import Scene, Split
from boostnerf_cli.stages.common import ALL_SKIPS, LoadedModel, Skips, all_model_names, load_model, workspace_scene
from boostnerf_cli.workspace import Workspace, atomic_path, write_json


def to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def depth_to_uint16(depth: torch.Tensor, far: float) -> np.ndarray:
    """Depth in world units -> 16-bit PNG values, 65535 = `far` (documented in docs/stages.md)."""
    return (depth.clamp(0, far) / far * 65535.0 + 0.5).numpy().astype(np.uint16)


def write_png(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, array, extension=".png")


def render_split(model: LoadedModel, scene: Scene, split: Split, device: str, skips: Skips = ALL_SKIPS,
                 views: int | None = None) -> list[dict]:
    """Render the first `views` views of a split (all by default) -> outputs with timings."""
    settings, skip = model.render_setup(scene, skips)
    out = []
    for i in range(len(split) if views is None else min(views, len(split))):
        t0 = time.perf_counter()
        r = render_image(model.field, split.poses[i], split.intrinsics[i], split.height, split.width, settings,
                         skip, device=device)
        r["seconds"] = time.perf_counter() - t0
        out.append(r)
    return out


def run_render(ws: Workspace, names: list[str] | None, split_name: str, device: str, skips: Skips, views: int | None,
               log: Callable[[str], None], per_expert: bool = False, exact_gate: bool = False) -> list[Path]:
    scene = workspace_scene(ws)
    split = scene.split(split_name)
    written = []
    for name in names or all_model_names(ws):
        model = load_model(ws, name, device, exact_gate)
        folder = ws.renders_dir(name, split_name)
        for i, r in enumerate(render_split(model, scene, split, device, skips, views)):
            stem = Path(split.names[i]).name
            write_png(folder / f"{stem}.png", to_uint8(r["rgb"]))
            write_png(folder / f"{stem}_depth.png", depth_to_uint16(r["depth"], scene.far))
            written.append(folder / f"{stem}.png")
        if per_expert and model.kind == "mixture":
            from boostnerf_cli.stages.pictures import render_experts_and_gate

            written += render_experts_and_gate(model, scene, split, folder, device, skips, views, log)
        log(f"{name}: wrote {len(written)} images to {folder}")
    return written


def evaluate_model(model: LoadedModel, scene: Scene, split: Split, device: str, lpips_model, skips: Skips = ALL_SKIPS,
                   views: int | None = None) -> dict:
    """Mean per-image PSNR / SSIM / LPIPS of one model over a split."""
    rows = []
    for i, r in enumerate(render_split(model, scene, split, device, skips, views)):
        m = image_metrics(r["rgb"], split.images[i], lpips_model)
        rows.append({**m, "seconds": r["seconds"], "samples": r["n_samples"], "colored": r["n_color"]})
    n = len(rows)
    mean = lambda k: sum(row[k] for row in rows) / n  # noqa: E731
    return {
        "name": model.name,
        "kind": model.kind,
        "psnr": round(mean("psnr"), 4),
        "ssim": round(mean("ssim"), 5),
        "lpips": round(mean("lpips"), 5) if lpips_model is not None else None,
        "seconds_per_image": round(mean("seconds"), 4),
        "samples_per_image": round(mean("samples")),
        "colored_per_image": round(mean("colored")),
        "params": model.params,
    }


def run_eval(ws: Workspace, names: list[str] | None, split_name: str, device: str, skips: Skips, views: int | None,
             report: bool, log: Callable[[str], None], costs: bool = True, exact_gate: bool = False) -> dict:
    scene = workspace_scene(ws)
    split = scene.split(split_name)
    names = names or all_model_names(ws)
    if not names:
        raise BoostNerfError(f"{ws.root} has no trained models yet: run `boostnerf pretrain --workspace {ws.root}` first")
    lpips_model, lpips_note = load_lpips(device)
    if lpips_model is None:
        log(lpips_note)
    rows = []
    for name in names:
        model = load_model(ws, name, device, exact_gate=True)  # ||w||_0 needs the trainable gate
        cost = {}
        if costs:
            from boostnerf_cli.stages.count_params import model_costs

            c = model_costs(model, scene, split, device, views, exact_gate)  # leaves it ready to render
            cost = {"w0": c["w0"], "gflops_per_image": c["gflops_per_image"]}
        row = {**evaluate_model(model.for_rendering(exact_gate), scene, split, device, lpips_model, skips, views), **cost}
        log(f"{name}: PSNR {row['psnr']:.3f}  SSIM {row['ssim']:.4f}  {row['seconds_per_image']:.3f}s/image")
        rows.append(row)
    result = {"split": split_name, "views": min(views or len(split), len(split)), "skip": skips.empty and skips.terminated,
              "skips": {"empty": skips.empty, "terminated": skips.terminated},
              "lpips_note": lpips_note or None, "models": rows}
    if report:
        write_json(ws.reports_dir / "eval.json", result)
        with atomic_path(ws.reports_dir / "eval.md") as tmp:
            tmp.write_text(markdown_table(result))
    return result


def markdown_table(result: dict) -> str:
    """The eval report as a Markdown table, in the paper's Table 1 columns."""
    def num(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    lines = [
        f"Split `{result['split']}`, {result['views']} views, skips {Skips(**result['skips']).describe()}.",
        "",
        "| model | PSNR | SSIM | LPIPS | params | ‖w‖₀ | GFLOPs/image | s/image |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["models"]:
        lines.append(
            f"| {r['name']} | {r['psnr']:.3f} | {r['ssim']:.4f} | {num(r['lpips'], '.4f')} | {r['params']:,} | "
            f"{num(r.get('w0'), ',')} | {num(r.get('gflops_per_image'), '.3f')} | {r['seconds_per_image']:.3f} |"
        )
    if result.get("lpips_note"):
        lines += ["", f"LPIPS: {result['lpips_note']}"]
    return "\n".join(lines) + "\n"
