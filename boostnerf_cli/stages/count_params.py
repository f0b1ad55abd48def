"""`boostnerf count-params`: parameters, ||w||_0 and GFLOPs per image of every model -> reports/count-params.json
(what they count: `boostnerf_cli.costs`)."""

from __future__ import annotations

import logging

from boostnerf_cli.costs import model_costs
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import load_model, n_views
from boostnerf_cli.workspace import write_json

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)


def run(survey: Survey, names: list[str] | None, split_name: str, device: str, views: int | None) -> dict:
    ws, scene = survey.ws, survey.scene()
    split = scene.split(split_name)
    names = survey.current(names)
    if not names:
        raise BoostNerfError(f"{ws.root} has no trained models yet: "
                             f"run `boostnerf pretrain --workspace {ws.root}` first")
    rows = []
    for name in names:
        row = model_costs(load_model(ws, name, device, exact_gate=True), scene, split, device, views)
        log(f"{name}: {row['params']:,} parameters, ||w||_0 {row['w0']:,}, {row['gflops_per_image']:.3f} GFLOPs/image")
        rows.append(row)
    result = {"split": split_name, "views": n_views(split, views), "models": rows}
    write_json(ws.reports_dir / "count-params.json", result)
    return result
