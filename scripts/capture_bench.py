"""Benchmark of `boostnerf capture` (docs/capture.md): seconds per phase, poses against known ones, and a DVGO
mixture trained on capture's poses against the same recipe on known poses.

    python scripts/capture_bench.py timing --counts 20 50 150 --size 512 --out OUT
        procedural photos (make-scene --content textured --rig orbit, SIZE px) captured; seconds per phase, and the
        poses against the ones they were rendered with
    python scripts/capture_bench.py poses --scene DIR --out OUT
        capture DIR's photos (an LLFF scene: images_N/ and poses_bounds.npy) and compare with its shipped poses
        (median rotation error, centre error as a fraction of the cameras' spread)
    python scripts/capture_bench.py mixture --scene DIR --captured OUT/capture --recipe RECIPE --out OUT
        pretrain, build-moe, finetune (baseline, Top-2), eval on the shipped poses and on capture's: held-out PSNR
    python scripts/capture_bench.py matching --captured OUT/capture-50 --out OUT
        exhaustive against retrieval matching on one capture's features (seconds, verified pairs)

Each writes OUT/<what>.json with the figures, the machine's load averages (os.getloadavg) before and after, and the
commit; timings taken on a busy machine are marked for a rerun on a quiet one.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cli(*args: str) -> str:
    """Run the boostnerf CLI of this checkout; -> its stdout (raises with its stderr on failure)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "boostnerf_cli", *args], capture_output=True, text=True, env=env)
    if proc.returncode:
        raise SystemExit(f"boostnerf {' '.join(args)} failed:\n{proc.stderr[-2000:]}")
    return proc.stdout


def commit() -> str:
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


def record(out: Path, name: str, data: dict, load_before: tuple) -> None:
    data = {"commit": commit(), "load_before": [round(v, 2) for v in load_before],
            "load_after": [round(v, 2) for v in os.getloadavg()], "cpus": os.cpu_count(), **data}
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(data, indent=2))
    print(json.dumps(data, indent=2))


def timing(args) -> None:
    sys.path.insert(0, str(ROOT))
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.alignment import compare_scenes

    load = os.getloadavg()
    rows = []
    for n in args.counts:
        src = args.out / f"photos-{n}"
        if not src.exists():
            cli("make-scene", str(src), "--format", "colmap", "--content", "textured", "--rig", "orbit",
                "--size", str(args.size), "--train-views", str(n), "--test-views", "0")
        cap = args.out / f"capture-{n}"
        t = time.perf_counter()
        cli("capture", "--images", str(src / "images"), "--out", str(cap), "--force")
        wall = time.perf_counter() - t
        report = json.loads((cap / "capture.json").read_text())
        errors = compare_scenes(load_scene(cap, holdout_every=0), load_scene(src, holdout_every=0))
        rows.append({"images": n, "size": args.size, "wall_seconds": round(wall, 1), "seconds": report["seconds"],
                     "matching": report["matching"], "registered": report["registered"], "points": report["points"],
                     "mean_reprojection_error": report["mean_reprojection_error"], **errors})
        record(args.out, "timing", {"rows": rows}, load)  # after each count: a long run keeps what it measured


def poses(args) -> None:
    sys.path.insert(0, str(ROOT))
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.alignment import compare_scenes

    load = os.getloadavg()
    folder = sorted(p for p in args.scene.iterdir() if p.is_dir() and p.name.startswith("images"))[0]
    cap = args.out / "capture"
    t = time.perf_counter()
    cli("capture", "--images", str(folder), "--out", str(cap), *(["--force"] if args.force else []))
    wall = time.perf_counter() - t
    report = json.loads((cap / "capture.json").read_text())
    errors = compare_scenes(load_scene(cap, holdout_every=0), load_scene(args.scene, holdout_every=0))
    record(args.out, "poses", {"scene": args.scene.name, "images": folder.name, "wall_seconds": round(wall, 1),
                               "capture": report, **errors}, load)


def _chain(scene: Path, recipe: Path, ws: Path) -> dict:
    for step in (("pretrain", "--data", str(scene)), ("build-moe",), ("finetune", "--baseline"),
                 ("finetune", "--topk", "2")):
        cli(*step, "--workspace", str(ws), "--recipe", str(recipe), "--device", "cpu")
    cli("eval", "--workspace", str(ws), "--split", "test", "--report", "--device", "cpu")
    return json.loads((ws / "reports" / "eval.json").read_text())


def mixture(args) -> None:
    load = os.getloadavg()
    results = {}
    for name, scene in (("shipped", args.scene), ("captured", args.captured)):
        ws = args.out / f"ws-{name}"
        report = _chain(scene, args.recipe, ws)
        results[name] = {m["name"]: m.get("psnr") for m in report.get("models", [])}
    record(args.out, "mixture", {"recipe": str(args.recipe), "held_out_psnr": results}, load)


def matching(args) -> None:
    """Seconds of each matching kind on one finished capture's features (its database copied): where exhaustive
    matching stops being the faster (`capture.EXHAUSTIVE_MAX`)."""
    import shutil
    import tempfile

    sys.path.insert(0, str(ROOT))
    import pycolmap

    from boostnerf_cli.stages import capture

    pycolmap.logging.minloglevel = 2
    load = os.getloadavg()
    names = [p.name for p in capture.photo_files(args.captured / "images")]
    rows = []
    for kind in ("exhaustive", "retrieval"):
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            shutil.copy(args.captured / "database.db", work / "database.db")
            t = time.perf_counter()
            verified = capture._match(pycolmap, work, names, kind, 0)
            rows.append({"kind": kind, "images": len(names), "seconds": round(time.perf_counter() - t, 1),
                         "pairs": len(capture.pairs(len(names), "exhaustive", None)) if kind == "exhaustive" else None,
                         "verified_pairs": verified})
    record(args.out, f"matching-{len(names)}", {"rows": rows}, load)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    t = sub.add_parser("timing")
    t.add_argument("--counts", type=int, nargs="+", default=[20, 50, 150])
    t.add_argument("--size", type=int, default=512)
    t.add_argument("--out", type=Path, required=True)
    p = sub.add_parser("poses")
    p.add_argument("--scene", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--force", action="store_true")
    m = sub.add_parser("mixture")
    m.add_argument("--scene", type=Path, required=True)
    m.add_argument("--captured", type=Path, required=True)
    m.add_argument("--recipe", type=Path, required=True)
    m.add_argument("--out", type=Path, required=True)
    k = sub.add_parser("matching")
    k.add_argument("--captured", type=Path, required=True)
    k.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    {"timing": timing, "poses": poses, "mixture": mixture, "matching": matching}[args.what](args)


if __name__ == "__main__":
    main()
