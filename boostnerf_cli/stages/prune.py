"""`boostnerf prune`: keep only the grid entries the training views use; write a compact model.

The paper measures ||w||_0 (the parameters with a non-zero gradient of the photometric loss) and
leaves pruning the rest as future work. Here: freeze the model, render every training view,
backpropagate the photometric loss, and for each dense grid table (every parameter whose name ends
in `table`: the experts' density and feature grids, the gate's feature grid) keep the rows (lattice
vertices) with a non-zero gradient in any channel. The MLPs stay dense (they are small and every
sample uses them). The result, `moe/<name>-pruned.safetensors`, stores each pruned table as its kept
rows plus a one-bit-per-row mask (`workspace.pack_rows`); loading rebuilds the dense table, so the
pruned model renders and evaluates like any other model under the name `<name>-pruned`.

Which rows are used. A row with a zero gradient is either never read by a rendered sample, read
with a zero trilinear weight (a sample on a lattice plane), or read only by samples whose
transmittance underflowed to exactly 0 (behind an opaque surface): none of these changes a training
view's pixels, so the training views render the same after pruning (checked and reported).
A mixture renders with its gate baked on a lattice (`Mixture.for_rendering`); a baked lattice vertex
blends gate rows around it that the exact gate at the training samples may not read, so the rows
the baked path needs are found too: the gradient reaches the baked logits, and is carried back to
the gate's rows through the baking (a vector-Jacobian product at the baked vertices that received
gradient). The kept rows are the union of both paths, for the experts as well (the baked routing
may send a sample to another expert near a routing boundary).

What a dropped row becomes (`fill`, stored per table): density tables take the smallest kept value
of the table, i.e. the emptiest density the model learned where the training views saw it (every
family's density is increasing in its raw value); other tables take 0 (the initial value of DVGO
features). A dropped row is never read with a non-zero effect by the training views, so the fill
only matters for new views that read grid entries no training view reached: "empty" there adds no
floaters. docs/benchmarks.md records the measurement behind this choice.
"""

from __future__ import annotations

import time
from typing import Callable

import torch
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields import grid as G
from boostnerf_cli.metrics import mse_to_psnr
from boostnerf_cli.render.renderer import render_image
from boostnerf_cli.scenes import Scene, Split
from boostnerf_cli.stages.common import LoadedModel, load_model, workspace_scene
from boostnerf_cli.stages.count_params import photometric_grads
from boostnerf_cli.workspace import Workspace, load_tensors, pack_rows, save_tensors, write_json

SUFFIX = "-pruned"
CHECK_VIEWS = 4  # training views rendered before and after to check they are unchanged


def grid_tables(field: torch.nn.Module) -> dict[str, Tensor]:
    """The dense grids of a model: 2-D parameters whose name ends in `table`."""
    return {n: p for n, p in field.named_parameters() if n.endswith("table") and p.dim() == 2}


def _rows_used(grad: Tensor | None, rows: int, device) -> Tensor:
    if grad is None:
        return torch.zeros(rows, dtype=torch.bool, device=device)
    return (grad != 0).any(dim=1)


def usage_masks(ws: Workspace, name: str, scene: Scene, split: Split, device: str,
                views: int | None = None, render: LoadedModel | None = None) -> dict[str, Tensor]:
    """-> {table name: (rows,) bool}, True for the rows whose gradient is non-zero on the split.

    `render`: the model as `load_model(ws, name, device)` gives it (loaded here when None)."""
    exact = load_model(ws, name, device, exact_gate=True)
    tables = grid_tables(exact.field)
    grads = photometric_grads(exact.field, exact.skip, exact.settings(scene), split, device, views)
    masks = {n: _rows_used(grads[n], t.shape[0], t.device) for n, t in tables.items()}
    if exact.kind != "mixture":
        return masks
    render = render or load_model(ws, name, device)  # what render and eval run: the gate baked
    baked = render.field.gate
    if baked.cfg.kind != "baked":
        return masks
    logit_table = baked.logit_table
    grads = photometric_grads(render.field, render.skip, render.settings(scene), split, device, views,
                              extra={"gate.logit_table": logit_table})
    for n in masks:
        if grads.get(n) is not None:
            masks[n] |= _rows_used(grads[n], masks[n].shape[0], masks[n].device)
    g = grads["gate.logit_table"]
    gate_tables = {n: t for n, t in tables.items() if n.startswith("gate.")}
    if g is None or not gate_tables:
        return masks
    # Carry the baked logits' gradient back to the gate's rows: sum_v <g_v, logits(vertex_v)>.
    rows = (g != 0).any(dim=1).nonzero().squeeze(1)
    pts = G.lattice_points(baked.bbox, baked.shape)[rows]
    gate = exact.field.gate
    for t in gate_tables.values():
        t.grad = None
    for i in range(0, rows.numel(), 1 << 16):
        (gate.logits(pts[i : i + (1 << 16)]) * g[rows[i : i + (1 << 16)]]).sum().backward()
    for n, t in gate_tables.items():
        masks[n] |= _rows_used(t.grad, t.shape[0], t.device)
        t.grad = None
    return masks


def fill_row(table_name: str, table: Tensor, keep: Tensor) -> list[float]:
    """The value of a dropped row: the emptiest kept density for density tables, else 0."""
    channels = table.shape[1]
    if "density" in table_name.rsplit(".", 1)[-1] and bool(keep.any()):
        return table[keep].min(dim=0).values.tolist()
    return [0.0] * channels


def _source_path(ws: Workspace, name: str):
    return ws.expert_path(name) if ws.expert_path(name).exists() else ws.model_path(name)


@torch.no_grad()
def _renders(model: LoadedModel, scene: Scene, split: Split, device: str, n: int) -> list[Tensor]:
    settings = model.settings(scene)
    return [render_image(model.field, split.poses[i], split.intrinsics[i], split.height, split.width, settings,
                         model.skip, device=device)["rgb"] for i in range(min(n, len(split)))]


def _psnr(images: list[Tensor], split: Split) -> float:
    return sum(mse_to_psnr(float(torch.mean((im - split.images[i]) ** 2))) for i, im in enumerate(images)) / len(images)


def run(ws: Workspace, name: str, split_name: str, device: str, views: int | None, force: bool,
        log: Callable[[str], None]) -> dict:
    ws.require_manifest()
    if name.endswith(SUFFIX):
        raise BoostNerfError(f"{name!r} is already pruned: prune the model it came from")
    out_name = name + SUFFIX
    out_path, report_path = ws.model_path(out_name), ws.moe_dir / f"{out_name}.json"
    if out_path.exists() and report_path.exists() and not force:
        from boostnerf_cli.workspace import read_json

        log(f"{out_name}: already pruned, skipping (use --force to redo it)")
        return read_json(report_path, "prune report")
    before = load_model(ws, name, device)  # also: a clear error for an unknown name, before any work
    src = _source_path(ws, name)
    scene = workspace_scene(ws)
    split = scene.split(split_name)
    t0 = time.perf_counter()
    masks = usage_masks(ws, name, scene, split, device, views, render=before)
    tensors, meta = load_tensors(src)
    if meta.get("packed"):
        raise BoostNerfError(f"{src} is already a pruned model")
    packed, tables, dropped = {}, [], 0
    for tname, keep in masks.items():
        table, keep = tensors.pop(tname), keep.cpu()
        fill = fill_row(tname, table, keep)
        parts = pack_rows(table, keep)
        tensors[f"{tname}@values"], tensors[f"{tname}@mask"] = parts["values"], parts["mask"]
        packed[tname] = {"rows": table.shape[0], "fill": fill}
        kept = int(keep.sum())
        dropped += (table.shape[0] - kept) * table.shape[1]
        tables.append({"name": tname, "rows": table.shape[0], "kept_rows": kept, "channels": table.shape[1],
                       "fill": fill})
    params_before = before.params
    meta = {k: v for k, v in meta.items() if k != "format_version"}
    save_tensors(out_path, tensors, {**meta, "name": out_name, "pruned_from": name, "packed": packed,
                                     "stored_params": params_before - dropped})
    after = load_model(ws, out_name, device)
    train_before = _renders(before, scene, split, device, CHECK_VIEWS)
    train_after = _renders(after, scene, split, device, CHECK_VIEWS)
    diff = max(float((a - b).abs().max()) for a, b in zip(train_before, train_after))
    test = scene.split("test")
    test_before = _psnr(_renders(before, scene, test, device, len(test)), test)
    test_after = _psnr(_renders(after, scene, test, device, len(test)), test)
    report = {
        "name": out_name,
        "from": name,
        "kind": before.kind,
        "split": split_name,
        "views": min(views or len(split), len(split)),
        "params_before": params_before,
        "params_after": params_before - dropped,
        "file_bytes_before": src.stat().st_size,
        "file_bytes_after": out_path.stat().st_size,
        "tables": tables,
        "train_check_views": len(train_before),
        "train_max_abs_diff": diff,
        "test_views": len(test),
        "test_psnr_before": round(test_before, 4),
        "test_psnr_after": round(test_after, 4),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    write_json(report_path, report)
    log(f"{out_name}: {params_before:,} -> {report['params_after']:,} parameters "
        f"({params_before / max(1, report['params_after']):.2f}x), file {report['file_bytes_before'] / 1e6:.2f} -> "
        f"{report['file_bytes_after'] / 1e6:.2f} MB; test PSNR {test_before:.3f} -> {test_after:.3f}; "
        f"train views max |diff| {diff:.2e}")
    return report
