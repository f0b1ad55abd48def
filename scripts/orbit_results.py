#!/usr/bin/env python3
"""A phone walk around an object: bounded against unbounded on the procedural half- and quarter-orbit captures.

    python scripts/orbit_results.py OUT [RIG ...] [--record] [--size 252]  (rigs: half-orbit quarter-orbit)

--size sets the photos' side and the recipe's data.image_size (the capture recipe's 252 by default).

1. `boostnerf make-scene OUT/RIG/scene --format nerfstudio --rig RIG --content textured --size 252 --train-views 28
   --test-views 4`: the procedural objects on a table in a closed, dotted room, photographed from an arc of 180 or 90
   degrees at table height and a little above (every 8th view held out: 4 test views);
2. for each kind (bounded, unbounded), recipes/chain.sh with recipes/capture-dvgo-cpu.yaml (the recipe for one's own
   captures: three DVGO experts 32/48/64 at 252 px) and data.scene set to that kind: the experts, the baseline and
   Top-2, in OUT/RIG/ws-KIND;
3. prints each workspace's eval table and which kind `auto` picks.

With --record: each eval.json to docs/data/orbit-RIG-KIND.json and the comparison to
docs/data/orbit-bounded-vs-unbounded.json; `python scripts/tables.py` then rebuilds the table of docs/results.md.
A finished chain is kept on a rerun (the chain skips what it finished).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from boostnerf_cli.scenes import load_scene  # noqa: E402

RECIPE = ROOT / "recipes" / "capture-dvgo-cpu.yaml"
RIGS = ("half-orbit", "quarter-orbit")
KINDS = ("bounded", "unbounded")


def cli(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "boostnerf_cli", *args], check=True,
                   env={**os.environ, "PYTHONPATH": str(ROOT)})


def chain(out: Path, scene: Path, kind: str, size: int) -> dict:
    rec = yaml.safe_load(RECIPE.read_text())
    rec["data"].update(scene=kind, image_size=size)
    recipe = out / f"recipe-{kind}.yaml"
    recipe.write_text(yaml.safe_dump(rec, sort_keys=False))
    ws = out / f"ws-{kind}"
    env = {**os.environ, "MODELS": "baseline top2", "PYTHONPATH": str(ROOT), "DEVICE": "cpu"}
    subprocess.run(["bash", str(ROOT / "recipes" / "chain.sh"), str(recipe), str(scene), str(ws)], check=True, env=env)
    return json.loads((ws / "reports" / "eval.json").read_text())


def psnr_of(report: dict, name: str) -> float | None:
    return next((m["psnr"] for m in report["models"] if m["name"] == name), None)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("rigs", nargs="*", default=list(RIGS))
    ap.add_argument("--size", type=int, default=252, help="the photos' side and the recipe's data.image_size")
    ap.add_argument("--record", action="store_true", help="write the reports under docs/data")
    args = ap.parse_args(argv)
    rows = []
    for rig in args.rigs:
        out = args.out / rig
        scene = out / "scene"
        if not scene.exists():
            cli("make-scene", str(scene), "--format", "nerfstudio", "--rig", rig, "--content", "textured",
                "--size", str(args.size), "--train-views", "28", "--test-views", "4")
        auto = load_scene(scene).extra["kind"]
        print(f"{rig}: auto picks {auto['kind']} ({auto['why']})")
        reports = {kind: chain(out, scene, kind, args.size) for kind in KINDS}
        for kind, report in reports.items():
            print(f"{rig} {kind}: " + ", ".join(f"{m['name']} {m['psnr']:.2f}" for m in report["models"]))
            if args.record:
                (ROOT / "docs" / "data" / f"orbit-{rig}-{kind}.json").write_text(json.dumps(report, indent=2) + "\n")
        for name in [m["name"] for m in reports["bounded"]["models"]]:
            b, u = psnr_of(reports["bounded"], name), psnr_of(reports["unbounded"], name)
            if b is not None and u is not None:
                rows.append([rig, name, f"{b:.2f}", f"{u:.2f}", f"{u - b:+.2f}"])
        gain = {kind: psnr_of(r, "top2") - psnr_of(r, "baseline") for kind, r in reports.items()}
        rows.append([rig, "Top-2 over its baseline", f"{gain['bounded']:+.2f}", f"{gain['unbounded']:+.2f}", "-"])
        rows.append([rig, "auto picks", "", auto["kind"], "-"])
    if args.record:
        (ROOT / "docs" / "data" / "orbit-bounded-vs-unbounded.json").write_text(json.dumps(
            {"columns": ["rig", "DVGO model", "PSNR, bounded", "PSNR, unbounded", "difference"], "rows": rows},
            indent=2) + "\n")
    for row in rows:
        print("  ".join(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
