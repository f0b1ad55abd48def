"""Issue 17: does one scene give the same box and held-out PSNR in every dataset layout?

Writes the thin procedural scene (`make-scene --content thin`, 80 px, 28 train and 4 test views) in the Blender,
nerfstudio and NSVF layouts and runs `boostnerf pretrain` on each with the recipe of tests/test_thin_structures.py
(geometry 32^3 for 300 steps, one DVGO-40 expert for 800 steps) at each seed given, then prints per layout and
seed the box the geometry stage drew, its coverage counts and the expert's held-out PSNR. docs/results.md, issue
17, records the output.

    python research/layout_agreement.py OUT [SEED ...]      (default seeds: 0 1)
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import yaml
from safetensors import safe_open

ROOT = Path(__file__).resolve().parent.parent
LAYOUTS = ("blender", "nerfstudio", "nsvf")


def recipe(out: Path) -> Path:
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import make_recipe  # the tests' tiny recipe, changed as test_thin_structures.py changes it
    from test_thin_structures import RECIPE_CHANGES

    return make_recipe(out / "thin.yaml", **RECIPE_CHANGES)


def main(out: Path, seeds: list[int]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    r = recipe(out)
    for layout in LAYOUTS:
        if not (out / layout).exists():
            subprocess.run([sys.executable, "-m", "boostnerf_cli", "make-scene", str(out / layout), "--size", "80",
                            "--train-views", "28", "--test-views", "4", "--content", "thin", "--format", layout],
                           check=True, capture_output=True)
    print(yaml.safe_dump({"recipe": str(r)}), end="")
    for seed in seeds:
        for layout in LAYOUTS:
            ws = out / f"ws-{layout}-s{seed}"
            if not (ws / "experts" / "dvgo-40.json").exists():
                subprocess.run([sys.executable, "-m", "boostnerf_cli", "pretrain", "-w", str(ws), "--data",
                                str(out / layout), "--recipe", str(r), "--device", "cpu", "--seed", str(seed)],
                               check=True, capture_output=True)
            meta = json.loads(safe_open(str(ws / "experts" / "geometry.safetensors"), "pt").metadata()["boostnerf"])
            psnr = json.loads((ws / "experts" / "dvgo-40.json").read_text())["test_psnr"]
            lo, hi = meta["fine_bbox"]
            box = " / ".join(f"{a:.2f} .. {b:.2f}" for a, b in zip(lo, hi))
            print(f"seed {seed} {layout:10s} box {box}  held-out {psnr:.2f} dB  coverage {meta['coverage']}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), [int(s) for s in sys.argv[2:]] or [0, 1])
