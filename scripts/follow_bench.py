"""How much `boostnerf view --follow` slows the training it follows: one expert trained alone, and trained while a
viewer follows it with a page open in headless Chromium (the viewer reads every checkpoint and renders it), in
alternating trials, each in a fresh copy of one workspace (the scene and its geometry made once, not timed).

Usage: python scripts/follow_bench.py [--folder DIR] [--trials 2] [--iters 300] [--checkpoint-every 50]
                                      [--res 32] [--threads 1]
The time compared is the expert's training seconds (its report's `seconds`). Prints one line per trial, the mean of
each arm, the slowdown in percent and the load average: on a shared machine other processes' load changes from trial
to trial, so a slowdown of a few percent needs a quiet machine (or many trials) to be told from the noise.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def boostnerf(*args: str, env: dict, **kwargs) -> subprocess.Popen | subprocess.CompletedProcess:
    command = [sys.executable, "-m", "boostnerf_cli", *args]
    if kwargs.pop("background", False):
        return subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return subprocess.run(command, env=env, check=True, capture_output=True, text=True, **kwargs)


def trial(base: Path, folder: Path, n: int, follow: bool, args, env: dict) -> float:
    """One training of the expert in a fresh copy of `base` -> its training seconds."""
    ws = folder / f"trial{n}"
    shutil.rmtree(ws, ignore_errors=True)
    shutil.copytree(base, ws, ignore=shutil.ignore_patterns(f"dvgo-{args.res}.*", "checkpoints"))
    viewer = browser = None
    if follow:
        from cdp import Browser, chromium_binary

        port = 8300 + n
        viewer = boostnerf("view", "-w", str(ws), "--follow", "--port", str(port), "--device", "cpu", env=env,
                           background=True)
        time.sleep(8)  # the viewer reads the scene and starts serving
        binary = chromium_binary()
        if binary is not None:
            browser = Browser(binary)
            browser.open(f"http://127.0.0.1:{port}/")
            time.sleep(5)
    try:
        boostnerf("pretrain", "-w", str(ws), "--recipe", str(args.recipe), "--res", str(args.res), "--iters",
                  str(args.iters), "--device", "cpu", env=env)
    finally:
        if browser is not None:
            browser.close()
        if viewer is not None:
            viewer.terminate()
            err = viewer.communicate(timeout=60)[1]
            lines = [ln for ln in err.splitlines() if ln.strip()]
            print(f"  viewer said: {' | '.join(lines[-4:])}")
    return json.loads((ws / "experts" / f"dvgo-{args.res}.json").read_text())["seconds"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, default=Path(tempfile.gettempdir()) / "boostnerf-follow-bench")
    parser.add_argument("--trials", type=int, default=2, help="trials per arm, alternating")
    parser.add_argument("--iters", type=int, default=300)
    parser.add_argument("--checkpoint-every", type=int, default=50)
    parser.add_argument("--res", type=int, default=32)
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of the training and the viewer")
    args = parser.parse_args(argv)
    folder = args.folder
    folder.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "PYTHONPATH": str(ROOT)}
    import yaml

    recipe = yaml.safe_load((ROOT / "recipes" / "demo-dvgo-cpu.yaml").read_text())
    recipe["pretrain"]["train"]["checkpoint_every"] = args.checkpoint_every
    args.recipe = folder / "recipe.yaml"
    args.recipe.write_text(yaml.safe_dump(recipe))
    base = folder / "base"
    if not (base / "experts" / "geometry.safetensors").exists():
        scene = folder / "scene"
        if not scene.exists():
            boostnerf("make-scene", str(scene), "--size", "48", "--content", "detail", env=env)
        boostnerf("pretrain", "-w", str(base), "--data", str(scene), "--recipe", str(args.recipe), "--res",
                  str(args.res), "--iters", "1", "--device", "cpu", env=env)  # the geometry (and a 1-step expert)
    times: dict[bool, list[float]] = {False: [], True: []}
    load = os.getloadavg()
    for n in range(2 * args.trials):
        follow = n % 2 == 1
        seconds = trial(base, folder, n, follow, args, env)
        times[follow].append(seconds)
        print(f"trial {n}: {'with a viewer following' if follow else 'alone'}: {seconds:.2f} s "
              f"(load average {os.getloadavg()[0]:.2f})")
    alone, followed = (sum(times[k]) / len(times[k]) for k in (False, True))
    print(f"dvgo-{args.res}, {args.iters} steps, a checkpoint every {args.checkpoint_every}, {args.threads} thread(s): "
          f"alone {alone:.2f} s, followed {followed:.2f} s, slowdown {100 * (followed / alone - 1):+.1f}%; "
          f"load average at start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, at end "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
