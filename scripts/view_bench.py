"""Frames per second of `boostnerf view`: the page's own render path (`viewpoint/viewer.py: Viewer.draw`, a colour
frame of the chosen model), along an orbit of the scene (a spiral for a forward-facing one), at each frame height
asked for.

Usage: python scripts/view_bench.py -w WS [--model NAME ...] [--sizes 64,128] [--frames 24] [--device cpu]
                                    [--json FILE]
Default models: the workspace's largest expert and top2. Prints a Markdown table (model, height, frames per second,
milliseconds per frame, GFLOPs per frame) and the load average when it ran: on a shared machine the figures are an
upper bound on the time a frame takes, and a quiet machine gives the real ones.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from boostnerf_cli.lineage import Survey  # noqa: E402
from boostnerf_cli.render.paths import camera_path  # noqa: E402
from boostnerf_cli.stages import view  # noqa: E402
from boostnerf_cli.stages.common import resolve_device  # noqa: E402
from boostnerf_cli.viewpoint.camera import dataset_camera, scaled  # noqa: E402
from boostnerf_cli.workspace import Workspace  # noqa: E402


def measure(viewer: view.Viewer, label: str, height: int, frames: int) -> dict:
    """`frames` colour frames of model `label` `height` pixels high along the orbit, after one to warm up."""
    viewer.choose(label)
    scene, model = viewer.scene, viewer.model
    train = scene.split("train")
    kind = "spiral" if scene.ndc is not None else "orbit"
    poses = camera_path(kind, train.poses, model.bbox.cpu(), scene.near, scene.far, frames, scene.ndc)
    base = dataset_camera(train, 0)
    cameras = [scaled(base._replace(pose=p), height) for p in poses]
    viewer.draw(cameras[0])  # warm-up: the first frame sizes the packing budgets (on a GPU)
    if torch.cuda.is_available() and viewer.models.device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for camera in cameras:
        viewer.draw(camera)
    seconds = time.perf_counter() - t0
    gflops = viewer.draw(cameras[0], count=True).gflops
    return {"model": label, "kind": model.kind, "height": height, "width": cameras[0].width, "frames": frames,
            "fps": frames / seconds, "ms_per_frame": 1000 * seconds / frames, "gflops_per_frame": gflops}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-w", "--workspace", type=Path, required=True)
    parser.add_argument("--model", action="append", help="model(s) to measure (default: the largest expert, top2)")
    parser.add_argument("--sizes", default="64,128", help="frame heights in pixels, comma-separated")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args(argv)
    ws = Workspace(args.workspace)
    device = resolve_device(args.device)
    models = view.Models(ws, device)
    labels = args.model or [n for n in (ws.expert_names()[-1:] + ["top2"]) if n in models.labels()]
    viewer = view.Viewer(ws, Survey(ws).scene(), models, model=labels[0])
    load = os.getloadavg()
    rows = [measure(viewer, label, int(h), args.frames) for label in labels for h in args.sizes.split(",")]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    print(f"{ws.root} on {device}, {torch.get_num_threads()} threads, commit {commit}, load average at start "
          f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, at end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("| model | frame (px) | frames/s | ms/frame | GFLOPs/frame |\n|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['model']} | {r['width']}x{r['height']} | {r['fps']:.1f} | {r['ms_per_frame']:.0f} | "
              f"{r['gflops_per_frame']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps({"workspace": str(ws.root), "device": device, "commit": commit,
                                         "threads": torch.get_num_threads(), "load_average": load, "rows": rows},
                                        indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
