#!/usr/bin/env python3
"""Does the mixture help on unbounded scenes? The procedural unbounded capture, each family's M = 3 chain.

    python scripts/unbounded_results.py OUT [FAMILY ...] [--record] [--reuse]  (families: dvgo tensorf ngp; default all)

1. `boostnerf make-scene OUT/scene --format nerfstudio --rig unbounded --size 48 --train-views 28`: the procedural
   objects on a ground that runs far past any box, under a banded sky dome, seen by a ring of cameras inside it
   (every 8th view held out: 4 test views);
2. for each family, recipes/chain.sh with recipes/unbounded-dvgo-cpu.yaml (the family's own expert sizes and options
   for tensorf and ngp, `FAMILIES` below; written to OUT/recipes/): experts, baseline, Top-1, Top-2, ensemble, on the
   contracted scene (data.scene: unbounded) in OUT/ws-FAMILY;
3. DVGO again with data.scene: bounded (the cameras' box, as before scene kinds existed), in OUT/ws-dvgo-bounded;
4. prints each workspace's eval table, the share of the test pixels whose content lies outside the bounded box, and
   writes OUT/compare.png: one test view, ground truth | bounded Top-2 | unbounded Top-2.

With --record: copies each eval.json to docs/data/unbounded-FAMILY.json (and the bounded one to
docs/data/unbounded-dvgo-bounded.json), the picture to docs/images/unbounded-compare.png, and the figures of the
comparison to docs/data/unbounded-bounded-vs-unbounded.json; `python scripts/tables.py` then rebuilds the tables of
docs/results.md. A finished workspace is kept on a rerun (the chain skips what it finished).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from boostnerf_cli import images  # noqa: E402
from boostnerf_cli.scenes import load_scene  # noqa: E402
from boostnerf_cli.scenes.procedural import content_outside  # noqa: E402

RECIPE = ROOT / "recipes" / "unbounded-dvgo-cpu.yaml"
# the other families' experts and options, at about the DVGO chain's cost (their CPU recipes' settings, smaller grids)
FAMILIES = {
    "dvgo": {},
    "tensorf": {"pretrain": {"model": "tensorf", "res": [32, 48, 64],
                             "train": {"lr_grid": 0.03},
                             "tensorf": {"density_rank": 8, "app_rank": 16, "app_dim": 27, "hidden": 64, "layers": 2,
                                         "view_pe": 2, "feat_pe": 0, "alpha_init": 0.0001, "l1_weight": 0.00008,
                                         "fit_steps": 100}},
                "moe": {"gate_init": "random", "lam": 0.0, "train": {"lr_grid": 0.01}}},
    "ngp": {"pretrain": {"model": "ngp", "res": [4, 6, 8], "train": {"lr_grid": 0.04, "lr_mlp": 0.005, "growth": []},
                         "ngp": {"log2_table": 15, "features": 2, "base_res": 8, "max_res": 96, "grid_res": 64,
                                 "hidden": 32, "geo_feat": 15, "color_hidden": 32, "color_layers": 2, "view_pe": 4,
                                 "alpha_init": 0.0001, "fit_steps": 100}},
            "moe": {"gate_init": "random", "lam": 0.00003, "train": {"lr_grid": 0.005}}},
}


def merge(base: dict, changes: dict) -> dict:
    out = dict(base)
    for k, v in changes.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def recipe_for(out: Path, family: str, scene: str) -> Path:
    rec = merge(yaml.safe_load(RECIPE.read_text()), FAMILIES[family])
    rec["data"]["scene"] = scene
    path = out / "recipes" / f"unbounded-{family}-{scene}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    return path


def chain(recipe: Path, scene: Path, ws: Path, models: str = "baseline top1 top2 ens", reuse: bool = False) -> dict:
    if reuse and (ws / "reports" / "eval.json").exists():  # a finished chain: its report as it is
        return json.loads((ws / "reports" / "eval.json").read_text())
    env = {**os.environ, "MODELS": models, "PYTHONPATH": str(ROOT)}
    subprocess.run(["bash", str(ROOT / "recipes" / "chain.sh"), str(recipe), str(scene), str(ws)], check=True, env=env)
    return json.loads((ws / "reports" / "eval.json").read_text())


def render_first_view(ws: Path, model: str) -> Path:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-m", "boostnerf_cli", "render", "--workspace", str(ws), "--model", model,
                    "--views", "1", "--device", "cpu"], check=True, env=env, stdout=subprocess.DEVNULL)
    return [p for p in sorted((ws / "renders" / model).rglob("*.png")) if not p.stem.endswith("_depth")][0]


def psnr_of(report: dict, name: str) -> float | None:
    return next((m["psnr"] for m in report["models"] if m["name"] == name), None)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("families", nargs="*", default=list(FAMILIES))
    ap.add_argument("--record", action="store_true", help="write the reports and the picture under docs/")
    ap.add_argument("--reuse", action="store_true",
                    help="take a finished workspace's report without rerunning its chain")
    args = ap.parse_args(argv)
    out: Path = args.out
    scene = out / "scene"
    if not scene.exists():
        subprocess.run([sys.executable, "-m", "boostnerf_cli", "make-scene", str(scene), "--format", "nerfstudio",
                        "--rig", "unbounded", "--size", "48", "--train-views", "28", "--test-views", "4"],
                       check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    reports = {}
    bounded = chain(recipe_for(out, "dvgo", "bounded"), scene, out / "ws-dvgo-bounded", "baseline top2", args.reuse)
    for family in args.families:
        reports[family] = chain(recipe_for(out, family, "unbounded"), scene, out / f"ws-{family}", reuse=args.reuse)
    box_scene = load_scene(scene, kind="bounded")
    test = box_scene.splits["test"]
    share = content_outside(scene, test.poses, test.intrinsics, test.height, test.width, box_scene.bbox)
    print(f"test pixels whose content lies outside the bounded box {box_scene.bbox.flatten().tolist()}: "
          f"{100 * share:.1f}%")
    for family, report in reports.items():
        print(f"{family}: " + ", ".join(f"{m['name']} {m['psnr']:.2f}" for m in report["models"]))
    print("dvgo bounded: " + ", ".join(f"{m['name']} {m['psnr']:.2f}" for m in bounded["models"]))
    truth = images.to_uint8(test.images[0])
    panels = [("ground truth", truth)]
    if "dvgo" in reports:
        for label, ws in (("bounded box, Top-2", out / "ws-dvgo-bounded"), ("contracted, Top-2", out / "ws-dvgo")):
            panels.append((label, iio.imread(render_first_view(ws, "top2"))[..., :3]))
    if len(panels) > 1:
        picture = images.panel_grid([[(label, images.upscale(img, 4)) for label, img in panels]])
        images.write_png(out / "compare.png", picture)
    if args.record:
        data = ROOT / "docs" / "data"
        for family, report in reports.items():
            (data / f"unbounded-{family}.json").write_text(json.dumps(report, indent=2) + "\n")
        (data / "unbounded-dvgo-bounded.json").write_text(json.dumps(bounded, indent=2) + "\n")
        if "dvgo" in reports:  # the comparison and the picture: DVGO's
            rows = []
            for name in [m["name"] for m in bounded["models"]]:
                b, u = psnr_of(bounded, name), psnr_of(reports["dvgo"], name)
                if b is not None and u is not None:
                    rows.append([name, f"{b:.2f}", f"{u:.2f}", f"{u - b:+.2f}"])
            rows.append(["test pixels whose content lies outside the bounded box", f"{100 * share:.1f}%", "-", "-"])
            (data / "unbounded-bounded-vs-unbounded.json").write_text(json.dumps(
                {"columns": ["DVGO model", "PSNR, bounded box", "PSNR, contracted", "difference"], "rows": rows},
                indent=2) + "\n")
            shutil.copy(out / "compare.png", ROOT / "docs" / "images" / "unbounded-compare.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
