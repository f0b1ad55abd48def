"""`boostnerf prune`: keep only the grid entries the training views use; write a compact model.

For each table of the model whose rows are places in space (`grid_tables`: a 2-D parameter whose name ends
in `table`, the experts' density and feature grids or hash tables and the gate's grid; or a TensoRF VM
plane or line) the rows (lattice vertices, hash entries, texels) kept are those where the
photometric loss of the training views has a non-zero gradient in any channel, through the exact gate
and through the baked gate that render and eval use (`usage_masks`). MLPs stay dense. The result,
`moe/<name>-pruned.safetensors` (`models.save_pruned`), renders and evaluates like any model under the
name `<name>-pruned`; a dropped row reads back as `fill_row`: the smallest kept value for density
tables, 0 otherwise. The training views render the same before and after (checked and reported).
Why these rows and this fill, and what pruning saves: docs/benchmarks.md, "What does pruning save?".
"""

from __future__ import annotations

import logging
import re
import time

import torch
from torch import Tensor

from boostnerf_cli.costs import photometric_grads
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields import grid as G
from boostnerf_cli.lineage import Survey, decide
from boostnerf_cli.metrics import mse_to_psnr
from boostnerf_cli.models import LoadedModel, load_model, n_views, render_split, save_pruned
from boostnerf_cli.scenes import Scene, Split
from boostnerf_cli.workspace import Workspace, read_json, remove, write_json

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)

SUFFIX = "-pruned"
CHECK_VIEWS = 4  # at most this many of the views pruned on are rendered before and after: unchanged


VM_FACTOR = re.compile(r"(^|\.)(planes|lines)\.\d+$")  # fields/vm.py: (texels, rank) planes, (cells, rank) lines


def grid_tables(field: torch.nn.Module) -> dict[str, Tensor]:
    """The tables of a model whose rows are places in space: 2-D parameters whose name ends in `table` (dense
    grids, hash tables) and TensoRF's VM factors (a plane's rows are its texels, a line's its cells)."""
    return {n: p for n, p in field.named_parameters()
            if p.dim() == 2 and (n.endswith("table") or VM_FACTOR.search(n))}


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
    if baked.cfg.gate_type != "baked":
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


def _renders(model: LoadedModel, scene: Scene, split: Split, device: str, n: int) -> list[Tensor]:
    return [r["rgb"] for r in render_split(model, scene, split, device, views=n)]


def _psnr(images: list[Tensor], split: Split) -> float:
    return sum(mse_to_psnr(float(torch.mean((im - split.images[i]) ** 2))) for i, im in enumerate(images)) / len(images)


def run(survey: Survey, name: str, split_name: str, device: str, views: int | None, force: bool) -> dict:
    """Prune model `name` -> NAME-pruned (skipped when finished from the same model): survey, decide, load, prune,
    check, report."""
    ws = survey.ws
    survey.manifest()
    if name.endswith(SUFFIX):
        raise BoostNerfError(f"{name!r} is already pruned: prune the model it came from")
    survey.current([name])  # a model made from what changed since is made again first
    out_name = name + SUFFIX
    out_path, report_path = ws.model_path(out_name), ws.moe_dir / f"{out_name}.json"
    src = ws.model_file(name)
    if (found := survey.finished(out_name)) is not None and not force:
        decide(found, None).check()  # its source is current (above): stale when it changed after the prune
        log(f"{out_name}: already pruned, skipping (use --force to redo it)")
        return read_json(report_path, "prune report")
    before = load_model(ws, name, device)  # also: a clear error for an unknown name, before any work
    if not grid_tables(before.field):
        raise BoostNerfError(f"{name} has no grid, hash table or VM factor to prune (prune drops the rows of those "
                             "that no training view reads): nothing written")
    scene = survey.scene()
    split = scene.split(split_name)
    t0 = time.perf_counter()
    masks = usage_masks(ws, name, scene, split, device, views, render=before)
    params_before = before.params
    tables, dropped = save_pruned(src, out_path, masks, fill_row, out_name, name, params_before)
    try:  # the checks below fail or are interrupted: no pruned model without its report (it read as "stale" for good)
        after = load_model(ws, out_name, device)
        check = min(CHECK_VIEWS, n_views(split, views))  # views the rows were kept for (--views N: the first N)
        train_before = _renders(before, scene, split, device, check)
        train_after = _renders(after, scene, split, device, check)
        diff = max(float((a - b).abs().max()) for a, b in zip(train_before, train_after))
        # the held-out PSNR before and after, when the scene holds views out (a capture of one view holds none)
        test = scene.held_out()
        test_before = _psnr(_renders(before, scene, test, device, len(test)), test) if test is not None else None
        test_after = _psnr(_renders(after, scene, test, device, len(test)), test) if test is not None else None
    except BaseException:
        remove(out_path)
        raise
    report = {
        "name": out_name,
        "from": name,
        "kind": before.kind,
        "split": split_name,
        "views": n_views(split, views),
        "params_before": params_before,
        "params_after": params_before - dropped,
        "file_bytes_before": src.stat().st_size,
        "file_bytes_after": out_path.stat().st_size,
        "tables": tables,
        "train_check_views": len(train_before),
        "train_max_abs_diff": diff,
        "test_views": len(test) if test is not None else 0,
        "test_psnr_before": round(test_before, 4) if test is not None else None,
        "test_psnr_after": round(test_after, 4) if test is not None else None,
        "seconds": round(time.perf_counter() - t0, 2),
    }
    write_json(report_path, report)
    log(f"{out_name}: {params_before:,} -> {report['params_after']:,} parameters "
        f"({params_before / max(1, report['params_after']):.2f}x), file {report['file_bytes_before'] / 1e6:.2f} -> "
        f"{report['file_bytes_after'] / 1e6:.2f} MB; "
        + (f"test PSNR {test_before:.3f} -> {test_after:.3f}; " if test is not None else "no held-out views; ")
        + f"train views max |diff| {diff:.2e}")
    return report
